"""The ``gf4cal`` command line: one module per sub-command, each with ``add_parser(subparsers)`` and ``run(args)``.

The CLI only parses options, calls the library and prints. Any :class:`Gf4calError` becomes one line on stderr and
exit status 2; a cancelled run exits 130. No traceback reaches the user (``GF4CAL_DEBUG=1`` shows it).
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import List, Optional

from ..errors import CancelledError, Gf4calError

# Sub-command modules, in help order. Each defines NAME, HELP, add_parser(parser) and run(args) -> int.
COMMANDS = [
    "info",
    "refine",
    "intersect",
    "simulate",
    "calibrate_lookangle",
    "apply_calibration",
    "experiment",
    "collect_gcps",
]


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    parser = argparse.ArgumentParser(prog="gf4cal", description="Geometric calibration of satellite images "
                                     "from their RPC, a DEM and control points.")
    parser.add_argument("--version", action="version", version=f"gf4cal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMANDS:
        mod = importlib.import_module(f".{name}", __name__)
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        mod.add_parser(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except CancelledError:
        print("gf4cal: cancelled", file=sys.stderr)
        return 130
    except (Gf4calError, OSError, ValueError) as exc:
        if os.environ.get("GF4CAL_DEBUG"):
            raise
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"gf4cal: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gf4cal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
