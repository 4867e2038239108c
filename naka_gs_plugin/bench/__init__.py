"""Benchmarks: scripts that print measured figures as ratios from one run."""
