"""``gf4cal experiment NAME --out DIR``: run one of the papers' experiments on simulated scenes.

Dispatches by name to ``gdal_gf4cal.experiments.<name>.run(out_dir, ...)``; a module there is an experiment
(``gf4``: look-angle calibration, seed 000, METHODS §5). Each prints its tables and writes ``DIR/report.json``.
"""
from __future__ import annotations

import importlib
import pkgutil

from ..errors import Gf4calError

NAME = "experiment"
HELP = "Run a paper's experiment on simulated scenes (e.g. 'gf4': look-angle calibration, Tables 2-4)."


def available():
    """Names of the experiment modules in :mod:`gdal_gf4cal.experiments`."""
    from .. import experiments
    return sorted(m.name for m in pkgutil.iter_modules(experiments.__path__) if not m.name.startswith("_"))


def add_parser(parser):
    parser.add_argument("name", metavar="NAME", help="experiment: " + ", ".join(available()))
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (report.json and more)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: the experiment's own)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    from ..progress import TextProgressBar
    names = available()
    if args.name not in names:
        raise Gf4calError(f"unknown experiment {args.name!r}; choose one of: {', '.join(names)}")
    mod = importlib.import_module(f"gdal_gf4cal.experiments.{args.name}")
    kwargs = {"progress": None if args.quiet else TextProgressBar()}
    if args.seed is not None:
        kwargs["seed"] = args.seed
    mod.run(args.out, **kwargs)
    return 0
