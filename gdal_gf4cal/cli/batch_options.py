"""Shared ``--dask`` / ``--batch`` options of the batch forms of the commands (issue 14); not a sub-command."""
from __future__ import annotations

import sys

from ..executors import get_executor
from ..progress import TextProgressBar


def add_batch_options(parser, flag: bool = True) -> None:
    """Add ``--dask SPEC`` and (``flag``) ``--batch`` to a sub-command parser."""
    parser.add_argument("--dask", metavar="SPEC", help="run on Dask: local[:N] (a local cluster of N worker "
                        "processes), tcp://HOST:PORT (a running `dask scheduler`); also serial or threads[:N]")
    if flag:
        parser.add_argument("--batch", action="store_true", help="batch form: one output per scene in the --out "
                            "folder, batch_summary.csv/.json, failing scenes reported, rerun skips finished scenes")


def run_batch_command(args, job) -> int:
    """Run ``job(executor, progress)`` (a :func:`gdal_gf4cal.batch.run_batch` call) on the ``--dask`` executor
    and print the summary; exit 0 when every scene succeeded (or was already done), 1 when some failed."""
    with get_executor(args.dask) as ex:
        rep = job(ex, TextProgressBar())
    for r in rep["scenes"]:
        if r["status"] == "failed":
            print(f"gf4cal: {r['scene']}: {r['error']}", file=sys.stderr)
    c = rep["counts"]
    print(f"{c['ok']} scenes done, {c['failed']} failed, {c['skipped']} already done; summary: "
          f"{rep['summary']['csv']}")
    return 1 if c["failed"] else 0
