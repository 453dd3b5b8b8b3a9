"""The ``gf4cal`` command line: one module per sub-command, each with ``add_parser(subparsers)`` and ``run(args)``.

The CLI only parses options, calls the library and prints. Any :class:`Gf4calError` becomes one line on stderr and
exit status 2 (any other exception too); a cancelled or interrupted run (Ctrl-C, SIGTERM) exits 130 and keeps no
output. No traceback reaches the user (``GF4CAL_DEBUG=1`` shows it, ``0`` does not). Commands call the workflows
layer (:mod:`gdal_gf4cal.workflows`) and print its report, with ``report["notes"]`` and ``report["warnings"]`` as
``gf4cal: note:`` / ``gf4cal: warning:`` lines. Python warnings raised outside a workflow's own collection (NumPy,
matplotlib, ...) never reach stderr in their raw two-line form: a run that succeeds prints each once as a
``gf4cal: warning:`` line, a run that fails prints only its error line.
"""
from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import warnings
from typing import List, Optional

from .. import threads
from ..errors import CancelledError, Gf4calError

# Sub-command modules, in help order. Each defines NAME, HELP, add_parser(parser) and run(args) -> int.
COMMANDS = [
    "info",
    "refine",
    "ortho",
    "intersect",
    "simulate",
    "calibrate_lookangle",
    "apply_calibration",
    "experiment",
    "collect_gcps",
    "register_pan_ms",
    "block_adjust",
    "bundle_adjust",
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


def _debug() -> bool:
    """``GF4CAL_DEBUG=1`` (or yes/true/on) shows tracebacks; unset, ``0``, no, false or off does not."""
    return os.environ.get("GF4CAL_DEBUG", "").strip().lower() in ("1", "yes", "true", "on")


def add_gcp_reader_arguments(parser) -> None:
    """``--columns`` and ``--gcp-pixel-convention``: how to read a GCP file (:func:`gdal_gf4cal.gcp.read_gcps`)."""
    parser.add_argument("--columns", metavar="MAP",
                        help="column map of a header-less CSV/text GCP file, e.g. \"id,sample,line,lon,lat,h\" "
                             "(x,y for map coordinates with --gcp-crs; skip a column with -)")
    parser.add_argument("--gcp-pixel-convention", choices=("center", "corner"),
                        help="image coordinates of the GCP file: corner = GDAL (pixel corners at integers), "
                             "center = pixel centres at integers (orthority, ASP); default: the format's own")


def add_plausibility_argument(parser, what: str = "GCPs") -> None:
    """``--no-plausibility-check``: the override every plausibility refusal names (:mod:`gdal_gf4cal.plausibility`)."""
    parser.add_argument("--no-plausibility-check", action="store_true",
                        help=f"experts: accept {what} beyond the RPC's domain, far from the RPC's prediction, with "
                        "heights outside the RPC's range or disagreeing with --dem (feet, vertical datum); points "
                        "outside the image but inside its RPC's domain are used anyway, with a warning")


def add_rpc_argument(parser) -> None:
    """``--rpc RPC`` of a one-image command: the RPC file of an image that carries none
    (:func:`gdal_gf4cal.crop.image_rpc`)."""
    parser.add_argument("--rpc", help="read the RPC from this file instead of the image (a crop and its product's "
                        ".geom / RPC_*.XML: the crop's origin is applied)")


def add_rpc_pairs_argument(parser) -> None:
    """``--rpc IMAGE=RPC ...`` of a many-image command (:func:`gdal_gf4cal.crop.image_and_rpc`)."""
    parser.add_argument("--rpc", nargs="+", default=[], metavar="IMAGE=RPC",
                        help="IMAGE=RPC for an image whose RPC is a separate file (a crop and its product's .geom: "
                        "the crop's origin is applied)")


def print_warnings(rep, stream=None) -> None:
    """Print ``rep["notes"]`` and ``rep["warnings"]`` (lists of one-line str) as ``gf4cal: note: ...`` and
    ``gf4cal: warning: ...`` lines on stderr."""
    for n in (rep or {}).get("notes", []) if isinstance(rep, dict) else []:
        print(f"gf4cal: note: {n}", file=stream or sys.stderr)
    for w in (rep or {}).get("warnings", []) if isinstance(rep, dict) else getattr(rep, "warnings", []) or []:
        print(f"gf4cal: warning: {w}", file=stream or sys.stderr)


def _sigterm(signum, frame):  # pragma: no cover - exercised through a subprocess
    from ..outputs import request_interrupt
    request_interrupt()           # also stops the commit if the KeyboardInterrupt gets swallowed on the way
    raise KeyboardInterrupt("terminated")


def _is_disk_full(exc: BaseException, text: str) -> bool:
    """A write that failed for lack of space: ENOSPC/EFBIG from Python, or GDAL/OGR's words for them."""
    import errno
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
        return True
    low = text.lower()
    return "no space left" in low or "file too large" in low or "disk full" in low or (
        "write error" in low and isinstance(exc, RuntimeError))


def _print_caught(caught) -> None:
    """Each recorded Python warning once, as one ``gf4cal: warning:`` line (deprecations left out)."""
    seen = set()
    for w in caught:
        if issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning, ResourceWarning)):
            continue
        text = (str(w.message).strip().splitlines() or [w.category.__name__])[0]
        if text not in seen:
            seen.add(text)
            print(f"gf4cal: warning: {text}", file=sys.stderr)


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        status = _main(args)
    if status == 0 or _debug():
        _print_caught(caught)
    return status


def _main(args) -> int:
    previous = {}
    try:
        for sig in (signal.SIGTERM, signal.SIGINT):          # SIGTERM cleans up like Ctrl-C (outputs removed)
            previous[sig] = signal.signal(sig, _sigterm)
    except ValueError:                                       # not the main thread: leave signals alone
        pass
    try:
        with threads.blas_serial():       # GF4CAL_NUM_THREADS bounds BLAS too: the pool parallelises
            return int(args._run(args) or 0)
    except CancelledError:
        print("gf4cal: cancelled", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("gf4cal: interrupted; no output was kept", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 2
    except Exception as exc:     # every exception class becomes one line (GF4CAL_DEBUG=1: the traceback)
        if _debug():
            raise
        text = str(exc).strip()
        msg = text.splitlines()[0] if text else type(exc).__name__
        if _is_disk_full(exc, text):
            msg = ("the disk is full (or a file-size limit was reached) while writing the outputs; nothing was "
                   "kept: free space or choose another output folder, then rerun")
        elif not isinstance(exc, (Gf4calError, OSError, ValueError)):
            msg = f"{type(exc).__name__}: {msg} (unexpected; rerun with GF4CAL_DEBUG=1 and report it)"
        print(f"gf4cal: error: {msg}", file=sys.stderr)
        return 2
    except RecursionError as exc:  # pragma: no cover - a subclass of Exception; kept for clarity
        print(f"gf4cal: error: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
