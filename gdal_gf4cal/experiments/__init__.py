"""The papers' experiments, rebuilt on simulated scenes from the public API only.

Each module ``<name>.py`` defines ``run(out_dir, *, progress=None, seed=<default>, **kwargs) -> dict``: it prints
the paper's tables, writes ``out_dir/report.json`` and returns the report. ``gf4cal experiment <name> --out DIR``
dispatches to it by name (see :mod:`gdal_gf4cal.cli.experiment`).
"""
