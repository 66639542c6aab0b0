"""Evaluation: image metrics, distribution distances, and method comparisons with reports."""
