"""Trainable systems: each owns its networks, losses and optimisers."""
