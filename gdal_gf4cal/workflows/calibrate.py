"""``gf4cal calibrate-lookangle`` / QGIS "Calibrate look angles": the file job of METHODS §5 (seed 000).

Moved from :mod:`gdal_gf4cal.lookangle` (which keeps the estimation). All outputs are written together or none.
"""
from __future__ import annotations

import os
from typing import Any, Dict

from .. import progress as _progress
from ..camera import LookAngleModel
from ..crop import product_rpc
from ..dem import DEM
from ..errors import Gf4calError
from ..gcp import read_gcps, validate_gcps
from ..lookangle import MAX_CONDITION, calibrate_lookangle, compare_lookangle, recalibrate_rpc
from ..outputs import OutputSet, check_vector, scene_stem
from ..plausibility import check_gcps_against
from ..report import footprint_from_rpc, plot_residuals, write_report_json, write_residuals_gpkg
from ..rpc_io import write_rpb, write_rpc_vrt
from ..threads import blas_serial
from ._common import cancel_check, collect_warnings, finish_report, is_path


def _check_outputs(paths, inputs, overwrite: bool) -> None:
    """Refuse before anything is written: an output that is an input, two outputs that are one file, or an
    existing output without ``overwrite`` (the checks of :class:`OutputSet`)."""
    outs = OutputSet(inputs, overwrite=overwrite)
    for i, p in enumerate(paths):
        outs.declare(f"output {i + 1}", p)


def _read_gcp_table(gcps_path, dem_obj, *, layer=None, columns=None, pixel_convention=None):
    """The GCP table from a file (:func:`~gdal_gf4cal.gcp.read_gcps`), or a table already read (QGIS: the layer's
    reader) validated."""
    if is_path(gcps_path):
        return read_gcps(gcps_path, dem=dem_obj, columns=columns, pixel_convention=pixel_convention,
                         **({"layer": layer} if layer else {}))
    return validate_gcps(gcps_path, dem=dem_obj)


def _write_outputs(outs, res, new_rpc, rpc, image, stem: str) -> None:
    """The camera file, the recalibrated RPC (and the VRT over the image), the residual layer and plot, into the
    OutputSet's temporary paths."""
    res.camera.to_json(outs.tmp("camera"))
    write_rpb(new_rpc, outs.tmp("rpb"), overwrite=True)
    if image is not None:
        write_rpc_vrt(image, new_rpc, outs.tmp("vrt"), overwrite=True)
    size = tuple(res.current.size)
    try:
        footprint = footprint_from_rpc(rpc, size, h=rpc.height_off)
    except Exception:  # a footprint is a convenience layer; the residuals matter
        footprint = None
    write_residuals_gpkg(res.gcps, outs.tmp("residuals_gpkg"), footprint=footprint, overwrite=True,
                         title="Look-angle calibration residuals", cancelled=outs.cancelled)
    outs.set_check("residuals_gpkg", check_vector({"gcps": len(res.gcps)}))
    plot_residuals(res.gcps, outs.tmp("residuals_png"), image_size=size,
                   title=f"{stem}: GCP residuals before / after look-angle calibration")


def _inputs_entry(rpc_path, gcps_path, camera_path, image, dem) -> Dict[str, Any]:
    """The report's ``inputs``: the paths as given (None for a GCP table already read, text for a DEM object)."""
    return {"rpc": os.fspath(rpc_path), "gcps": os.fspath(gcps_path) if is_path(gcps_path) else None,
            "camera": os.fspath(camera_path), "image": None if image is None else os.fspath(image),
            "dem": dem if dem is None or isinstance(dem, (str, int, float)) else os.fspath(dem)
            if isinstance(dem, os.PathLike) else str(dem)}


def _output_set(rpc_path, gcps_path, camera_path, image, dem, out: str, stem: str, overwrite: bool,
                progress) -> OutputSet:
    """The outputs declared under ``out`` (all written together or none)."""
    names = {"camera": "camera_new.json", "rpb": f"{stem}.RPB", "residuals_gpkg": "residuals.gpkg",
             "residuals_png": "residuals.png", "report": "report.json"}
    if image is not None:
        names["vrt"] = f"{stem}.vrt"
    outs = OutputSet([rpc_path, gcps_path if is_path(gcps_path) else None, camera_path, image, dem],
                     overwrite=overwrite, cancelled=cancel_check(progress))
    for key, name in names.items():
        outs.declare(key, os.path.join(out, name), check=check_vector() if key == "residuals_gpkg" else None)
    return outs


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def calibrate_lookangle_files(rpc_path, gcps_path, camera_path, out_dir, *, image=None, dem=None, geoid=None,
                              gcp_layer=None, gcp_columns=None, gcp_pixel_convention=None, robust: bool = True,
                              max_condition=None, overwrite: bool = False, progress=None,
                              check_plausibility: bool = True) -> Dict[str, Any]:
    """File workflow of ``gf4cal calibrate-lookangle`` (METHODS §5): calibrate, recalibrate the RPC, write outputs.

    Writes into ``out_dir``: ``camera_new.json``, ``<scene>.RPB`` (the recalibrated RPC), ``<image>.vrt`` over the
    untouched ``image`` when given, ``residuals.gpkg`` (GCPs with residuals before / after, outlier flags and
    residual vectors), ``residuals.png`` and ``report.json``; all together after everything was computed, or
    none (a refused input, a failure, a cancel). Returns the report dict (with ``outputs`` and ``warnings``).
    GCPs that cannot belong to the image are refused first (:func:`~gdal_gf4cal.plausibility.check_gcps_against`
    over the camera's size; ``check_plausibility=False`` for experts). ``gcp_columns`` / ``gcp_pixel_convention``:
    column map of a header-less CSV and the convention of the file's image coordinates
    (:func:`~gdal_gf4cal.gcp.read_gcps`). ``image`` a crop that states its origin in the product and ``rpc_path``
    the product's RPC: the camera's pixels are the product's, so the GCPs (measured in the crop) are moved to the
    product's pixels (as are the residuals written), and the recalibrated RPC is moved back to the crop
    (:func:`gdal_gf4cal.crop.product_rpc`; the report's ``notes`` say so).
    """
    if max_condition is not None and not (float(max_condition) >= 1.0):
        raise Gf4calError(f"max_condition {max_condition} makes no sense: a condition number is >= 1; give e.g. 1e6 "
                          "or leave it out")
    stem = scene_stem(image if image is not None else rpc_path)
    outs = _output_set(rpc_path, gcps_path, camera_path, image, dem, os.fspath(out_dir), stem, overwrite, progress)
    warns: list = []
    with outs, collect_warnings(warns):
        # the camera's pixels are the product's: a crop's GCPs are moved there, its new RPC moved back
        rpc, origin, note = product_rpc(image, rpc_path) if image is not None else product_rpc(rpc_path)
        current = LookAngleModel.from_json(camera_path)
        dem_obj = DEM.from_user_input(dem, geoid=geoid)
        gcps = _read_gcp_table(gcps_path, dem_obj, layer=gcp_layer, columns=gcp_columns,
                               pixel_convention=gcp_pixel_convention)
        if origin != (0.0, 0.0):
            gcps = gcps.assign(sample=gcps["sample"] + origin[0], line=gcps["line"] + origin[1])
        if check_plausibility:
            with collect_warnings(warns):         # now: the report written below lists them
                check_gcps_against(rpc, gcps, tuple(current.size), dem=dem_obj)
        res = calibrate_lookangle(rpc, gcps, current, robust=robust,
                                  max_condition=MAX_CONDITION if max_condition is None else max_condition,
                                  progress=_progress.scaled(progress, 0.0, 0.4))
        new_rpc, fit_report = recalibrate_rpc(rpc, current, res.camera, progress=_progress.scaled(progress, 0.4, 0.85))
        if origin != (0.0, 0.0):
            new_rpc = new_rpc.with_image_affine(-origin[0], -origin[1])
        _progress.report(progress, 0.85, "writing outputs")
        _write_outputs(outs, res, new_rpc, rpc, image, stem)
        rep = {"command": "calibrate-lookangle", "inputs": _inputs_entry(rpc_path, gcps_path, camera_path, image, dem),
               "calibration": res.to_dict(), "camera_change_px": compare_lookangle(res.camera, current),
               "recalibrated_rpc": fit_report.to_dict(), "outputs": outs.paths}
        if note:
            rep["notes"] = [note]
        finish_report(rep, warns)
        write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep
