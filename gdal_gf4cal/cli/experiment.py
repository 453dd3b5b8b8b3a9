"""``gf4cal experiment NAME --out DIR``: run one of the papers' experiments on simulated scenes.

Dispatches by name to ``gdal_gf4cal.experiments.<name>.run(out_dir, ...)``; a module there is an experiment
(``gf4``: look-angle calibration, seed 000, METHODS §5; ``jl1``: block calibration, seed 003, METHODS §8). Each
prints its tables and writes ``DIR/report.json``; ``--size W H`` crops the simulated images of those that take it.
"""
from __future__ import annotations

from ..progress import TextProgressBar
from ..workflows import run_experiment
from ..workflows.experiment import available as _available
from . import print_warnings


NAME = "experiment"
HELP = "Run a paper's experiment on simulated scenes (e.g. 'gf4': look-angle calibration, Tables 2-4)."


def available():
    """Names of the experiment modules in :mod:`gdal_gf4cal.experiments`."""
    return _available()


def add_parser(parser):
    parser.add_argument("name", metavar="NAME", help="experiment: " + ", ".join(available()))
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (report.json and more)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: the experiment's own)")
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), default=None,
                        help="crop of the simulated images (experiments that take it, e.g. jl1: pan px per CCD)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into an existing, non-empty folder (never over an input)")


def run(args) -> int:
    kwargs = {}
    if args.seed is not None:
        kwargs["seed"] = args.seed
    if args.size is not None:
        kwargs["size"] = tuple(args.size)
    rep = run_experiment(args.name, args.out, overwrite=args.overwrite,
                         progress=None if args.quiet else TextProgressBar(), **kwargs)
    print_warnings(rep)
    return 0
