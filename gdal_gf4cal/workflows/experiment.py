"""``gf4cal experiment``: run one of the papers' experiments into a folder under the output policy."""
from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
from typing import Any, Dict, List

from .. import experiments
from ..errors import Gf4calError
from ..outputs import OutputSet
from ..threads import blas_serial
from ._common import cancel_check, collect_warnings, finish_report


def available() -> List[str]:
    """Names of the experiment modules in :mod:`gdal_gf4cal.experiments`."""
    return sorted(m.name for m in pkgutil.iter_modules(experiments.__path__) if not m.name.startswith("_"))


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def run_experiment(name: str, out_dir, *, overwrite: bool = False, progress=None, **options) -> Dict[str, Any]:
    """Run experiment ``name`` (``gdal_gf4cal.experiments.<name>.run``) into ``out_dir``; its report dict with
    ``warnings``. The folder must be new or empty unless ``overwrite``; files of a failed run are removed."""
    names = available()
    if name not in names:
        raise Gf4calError(f"unknown experiment {name!r}; choose one of: {', '.join(names)}")
    mod = importlib.import_module(f"gdal_gf4cal.experiments.{name}")
    accepted = inspect.signature(mod.run).parameters
    for key in options:
        if key not in accepted:
            raise Gf4calError(f"experiment {name!r} takes no {key} option; leave out --{key}")
    outs = OutputSet((), overwrite=overwrite, cancelled=cancel_check(progress))
    outs.declare_folder("experiment", out_dir)
    warns: list = []
    with outs, collect_warnings(warns):
        rep = mod.run(os.fspath(out_dir), progress=progress, **options)
    rep = rep if isinstance(rep, dict) else {}
    return finish_report(rep, warns)
