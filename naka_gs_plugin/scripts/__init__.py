"""Every console script, nerfstudio's convention: one module per script, a tyro dataclass with ``main()``
and a module-level ``entrypoint()``. ``naka-gs-<name>`` lives in ``scripts/<name>.py`` (dashes as
underscores) as the class ``<Name>`` in CamelCase (``naka-gs-bench-ppm``: ``scripts/bench_ppm.py``,
``BenchPpm``); the library code a script calls stays in its package."""
