"""Benchmarks and record tools of naka-gs: run from a clone, not installed with the package.

``python -m benchmarks.<name> --help`` from the repository root (README "Benchmarks"): ``grid`` (accuracy vs
time over training runs), ``rasterizer``, ``ppm``, ``correction_speed``, ``correction_eval``, ``cuda_parity``,
``scene_sheet``, ``sim_stats``. They import ``naka_gs_plugin`` and never the other way round.
"""
