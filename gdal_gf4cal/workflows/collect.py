"""``gf4cal collect-gcps`` / QGIS "Collect GCPs": match a raw image against a reference orthophoto + DEM and write
the GCP table (issue 7); the file-level part of :mod:`gdal_gf4cal.matching.collect`."""
from __future__ import annotations

import os
from typing import Any, Dict

from ..crop import image_rpc
from ..dem import DEM
from ..errors import Gf4calError
from ..gcp import write_gcps
from ..matching import collect_gcps
from ..matching.collect import coarse_reference_hint
from ..outputs import OutputSet, check_vector
from ..threads import blas_serial
from ._common import cancel_check, collect_warnings, finish_report

_EXTS = (".gpkg", ".csv", ".geojson", ".json")


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def collect_gcps_file(image, reference, dem, out, *, rpc=None, geoid=None, keep_outliers: bool = False,
                      overwrite: bool = False, progress=None, **options) -> Dict[str, Any]:
    """Collect GCPs on ``image`` (its RPC, or the RPC file ``rpc``) against ``reference`` + ``dem`` and write them
    to ``out`` (``.gpkg``, ``.csv`` or ``.geojson``); ``options`` go to :func:`gdal_gf4cal.matching.collect_gcps`.

    ``dem`` is a DEM path or a constant height. The table is written only when matching succeeded, and never over
    an input or (without ``overwrite``) an existing file. Returns ``{"windows", "spacing_px" (the grid step used),
    "n_gcps", "n_outliers", "output", "gcps" (the GeoDataFrame, all rows), "table" (the rows written), "warnings"}``.
    """
    out = os.fspath(out)
    if os.path.splitext(out)[1].lower() not in _EXTS:
        raise Gf4calError(f"output {out!r}: use a name ending in .gpkg, .csv or .geojson")
    if not os.path.exists(os.fspath(image)):
        raise Gf4calError(f"image not found: {image}")
    outs = OutputSet([image, reference, dem if isinstance(dem, (str, os.PathLike)) else None, rpc],
                     overwrite=overwrite, cancelled=cancel_check(progress))
    outs.declare("gcps", out, check=None if out.lower().endswith(".csv") else check_vector())
    warns: list = []
    with outs, collect_warnings(warns):
        model, note = image_rpc(image, rpc)
        dem_obj = DEM.from_user_input(dem, geoid=geoid)
        gcps = collect_gcps(os.fspath(image), model, os.fspath(reference), dem_obj, progress=progress, **options)
        w = gcps.attrs["windows"]
        table = gcps if keep_outliers else gcps[~gcps["outlier"].to_numpy(bool)]
        if len(table) == 0:
            hint = coarse_reference_hint(gcps.attrs["reference_coarseness"], gcps.attrs["window_px"])
            raise Gf4calError(f"no GCP found in {w['total']} windows ({w['featureless']} featureless, "
                              f"{w['weak_correlation']} weak, {w['nodata'] + w['outside_image']} without data); "
                              + (hint or "check that the reference and DEM cover the image, or raise --search"))
        write_gcps(table, outs.tmp("gcps"))
        if not out.lower().endswith(".csv"):
            outs.set_check("gcps", check_vector({"gcps": len(table)} if out.lower().endswith(".gpkg") else None))
    rep = {"command": "collect-gcps", "windows": dict(w), "spacing_px": gcps.attrs["spacing_px"],
           "n_gcps": int(len(table)), "n_outliers": int(gcps["outlier"].to_numpy(bool).sum()), "output": out,
           "outputs": {"gcps": out}, "gcps": gcps, "table": table}
    if note:
        rep["notes"] = [note]
    return finish_report(rep, warns)
