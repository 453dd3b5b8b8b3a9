"""``gf4cal simulate`` / QGIS "Simulate scene": write a simulated scene with known truth (METHODS §10) into a
folder, all or nothing (the folder's new files are removed on failure or cancel)."""
from __future__ import annotations

import os

from ..outputs import OutputSet
from ..simulate import write_scene
from ..threads import blas_serial
from ._common import cancel_check, collect_warnings, finish_report


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def simulate_scene(sensor: str, out_dir, *, overwrite: bool = False, dem=None, reference=None, progress=None,
                   **options):
    """Run :func:`gdal_gf4cal.simulate.write_scene` into ``out_dir`` under the output policy.

    ``out_dir`` must not exist, be empty, or (``overwrite``) be replaced in place; it must not hold an input (``dem``,
    ``reference``). Returns the :class:`~gdal_gf4cal.simulate.SceneResult` with a ``warnings`` list attribute.
    """
    outs = OutputSet([dem, reference], overwrite=overwrite, cancelled=cancel_check(progress))
    outs.declare_folder("scene", out_dir)
    warns: list = []
    with outs, collect_warnings(warns):
        res = write_scene(sensor, os.fspath(out_dir), dem=dem, reference=reference, progress=progress, **options)
    res.warnings = finish_report({}, warns)["warnings"]
    return res
