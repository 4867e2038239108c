"""Photometric enhancement of low-light training images (Naka-Rushton response, then correction)."""
