"""Accuracy of an RPC against GCPs (QGIS "Assess accuracy", METHODS §6); moved from :mod:`gdal_gf4cal.report`."""
from __future__ import annotations

import os
from typing import Optional, Tuple

import numpy as np

from .. import stats
from ..compensation import ground_offsets_m
from ..crop import image_rpc
from ..dem import DEM
from ..gcp import read_gcps, validate_gcps
from ..outputs import OutputSet, check_vector
from ..plausibility import check_gcps_against
from ..progress import report as _report
from ..report import plot_residuals, write_report_json, write_residuals_gpkg
from ..rpc import RPCModel
from ..threads import blas_serial
from ._common import declare_report_outputs, cancel_check, collect_warnings, finish_report, is_path
from .ortho import scene_footprint


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def assess_accuracy(source, gcps, *, dem=None, geoid=None, gcp_layer: Optional[str] = None,
                    gcp_columns: Optional[str] = None, gcp_pixel_convention: Optional[str] = None, residuals=None,
                    plot=None, report=None, image_size: Optional[Tuple[int, int]] = None, overwrite: bool = False,
                    progress=None, check_plausibility: bool = True, rpc=None) -> dict:
    """Accuracy of an RPC against GCPs (METHODS §6): residuals, per-axis and planar statistics, CE90, internal
    accuracy, per role; optionally written as a styled GeoPackage, a plot and ``report.json`` (all or none).

    Residuals are ``measured - predicted`` with ``predicted = rpc.project(lon, lat, h)`` (GDAL pixel convention).
    In the GeoPackage and plot they are the *before* residuals (the RPC as given, before any correction).

    Parameters
    ----------
    source : path or RPCModel
        Image with an RPC, RPC file, or a model.
    rpc : path, optional
        The RPC file of an image that carries none (a crop and its product's ``.geom``: the crop's origin is applied,
        :func:`gdal_gf4cal.crop.image_rpc`; ``notes`` say so); default the image's own RPC, else the RPC file named
        like it beside it.
    gcps : GCP table (DESIGN.md schema; :func:`gdal_gf4cal.gcp.validate_gcps` is applied) or a GCP file path
        (``gcp_layer``: its layer; ``gcp_columns``, ``gcp_pixel_convention``: see :func:`~gdal_gf4cal.gcp.read_gcps`).
    dem : DEM, path or height, optional
        Fills missing GCP heights (``geoid``: the DEM's geoid).
    residuals, plot, report : optional output paths (``.gpkg``, ``.png``, ``.json``).
    overwrite : replace existing outputs (never an input).
    check_plausibility : refuse GCPs that cannot belong to the image (outside it, far from the RPC's prediction,
        lon/lat swapped, wrong CRS, heights outside the RPC's range: :func:`~gdal_gf4cal.plausibility.
        check_gcps_against` over ``image_size`` or the RPC's); ``False`` for experts.

    Returns
    -------
    dict
        ``{"n", "all"|"control"|"check": {"n", "line", "sample", "planar", "ce90_m", "internal"}, "outputs",
        "warnings"}``; a role without points is absent. ``ce90_m`` converts residuals to ground metres through the
        RPC's ground Jacobian at each GCP; ``internal`` removes a rotation + translation first (needs >= 2 points).
    """
    src_name = None if isinstance(source, RPCModel) else os.fspath(source)
    outs = OutputSet([src_name, gcps if is_path(gcps) else None, dem if is_path(dem) else None,
                      rpc if is_path(rpc) else None],
                     overwrite=overwrite, cancelled=cancel_check(progress))
    declare_report_outputs(outs, residuals=residuals, plot=plot, report=report)
    warns: list = []
    with outs, collect_warnings(warns):
        rpc, note = (source, None) if isinstance(source, RPCModel) else image_rpc(source, rpc)
        dem_obj = DEM.from_user_input(dem, geoid=geoid)
        if is_path(gcps):
            table = read_gcps(gcps, dem=dem_obj, columns=gcp_columns, pixel_convention=gcp_pixel_convention,
                              **({"layer": gcp_layer} if gcp_layer else {}))
        else:
            table = validate_gcps(gcps, dem=dem_obj)
        if check_plausibility:
            with collect_warnings(warns):         # now: the report written below lists them
                check_gcps_against(rpc, table, image_size, dem=dem_obj)
        _report(progress, 0.2, "projecting the GCPs")
        table = _with_residuals(rpc, table)
        out: dict = {"source": src_name, "n": int(len(table)), "residuals": "measured - RPC(ground), px"}
        if note:
            out["notes"] = [note]
        out.update(_role_statistics(table))
        _report(progress, 0.6, "writing outputs")
        if residuals:
            footprint = None
            if image_size is not None:
                footprint = scene_footprint(rpc, image_size, dem_obj)         # on the DEM when given
            write_residuals_gpkg(table, outs.tmp("residuals"), footprint=footprint, before=("res_sample", "res_line"),
                                 after=None, title="RPC accuracy", cancelled=outs.cancelled)
            outs.set_check("residuals", check_vector({"gcps": len(table)}))
        if plot:
            plot_residuals(table, outs.tmp("plot"), before=("res_sample", "res_line"), after=None,
                           image_size=image_size, title="RPC residuals at the GCPs")
        out["outputs"] = outs.paths
        finish_report(out, warns)
        if report:
            write_report_json(out, outs.tmp("report"))
    finish_report(out, warns)
    _report(progress, 1.0, "done")
    return out


def _with_residuals(rpc, table):
    """A copy of ``table`` with the RPC's predictions (``pred_sample``, ``pred_line``), the residuals
    ``measured - predicted`` (``res_sample``, ``res_line``, px) and the same as ground offsets (``res_east_m``,
    ``res_north_m``) through the RPC's ground Jacobian."""
    lon, lat, h = (table[c].to_numpy(float) for c in ("lon", "lat", "h"))
    s_pred, l_pred = (np.asarray(v, float) for v in rpc.project(lon, lat, h))
    table = table.copy()
    table["pred_sample"], table["pred_line"] = s_pred, l_pred
    table["res_sample"] = table["sample"].to_numpy(float) - s_pred
    table["res_line"] = table["line"].to_numpy(float) - l_pred
    east, north = ground_offsets_m(rpc, lon, lat, h, table["res_sample"].to_numpy(),
                                   table["res_line"].to_numpy())
    table["res_east_m"], table["res_north_m"] = east, north
    return table


def _role_statistics(table) -> dict:
    """``{"all"|"control"|"check": {"n", "line", "sample", "planar", "ce90_m", "internal"}}``; a role is there only
    when some points but not all have it."""
    s_pred, l_pred = table["pred_sample"].to_numpy(), table["pred_line"].to_numpy()
    east, north = table["res_east_m"].to_numpy(), table["res_north_m"].to_numpy()
    roles = {"all": np.ones(len(table), bool)}
    for role in ("control", "check"):
        m = (table["role"] == role).to_numpy()
        if m.any() and not m.all():
            roles[role] = m
    out = {}
    for key, m in roles.items():
        rs, rl = table["res_sample"].to_numpy()[m], table["res_line"].to_numpy()[m]
        entry = stats.residual_report(rs, rl)
        entry["ce90_m"] = stats.ce90(east[m], north[m])
        if m.sum() >= 2:
            entry["internal"] = stats.internal_accuracy(table["sample"].to_numpy()[m],
                                                        table["line"].to_numpy()[m], s_pred[m], l_pred[m])
        out[key] = entry
    return out
