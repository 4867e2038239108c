"""Every console script, nerfstudio's convention: one module per script, a tyro dataclass with ``main()``
and a module-level ``entrypoint()``. ``naka-gs-<name>`` lives in ``scripts/<name>.py`` (dashes as
underscores) as the class ``<Name>`` in CamelCase (``naka-gs-process-data``: ``scripts/process_data.py``,
``ProcessData``); the library code a script calls stays in its package. Benchmarks and record tools are not
installed: they live in the repository's ``benchmarks/`` (``python -m benchmarks.<name>`` from a clone)."""
