"""Synthetic low-light scenes with known ground truth."""
