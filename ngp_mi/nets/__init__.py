"""Network building blocks (generators, encoders, discriminators)."""
