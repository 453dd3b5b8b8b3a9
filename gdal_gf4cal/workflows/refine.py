"""``gf4cal refine`` / QGIS "Refine RPC": read, estimate, apply, write, report (METHODS §4, §6).

Moved from :mod:`gdal_gf4cal.compensation` (which keeps the model, the fit and :func:`apply_compensation`);
every output goes through one :class:`~gdal_gf4cal.outputs.OutputSet`: all written, or none.
"""
from __future__ import annotations

import os
from typing import Any, Dict, Optional, Sequence

import numpy as np

from .. import progress as _progress
from ..compensation import (apply_compensation, fit_compensation, ground_jacobian, ground_offsets_m,
                            report_axis_stats)
from ..dem import DEM
from ..errors import GCPError
from ..gcp import read_gcps, validate_gcps
from ..gcp_formats import assign_roles, parse_columns
from ..geoid import resolve_geoid
from ..model_selection import select_model
from ..outputs import (OutputSet, check_not_a_shadowing_sidecar, check_raster, check_vector, rpc_stem,
                       same_file)
from ..plausibility import MAX_UNCERTAINTY_PX, check_gcps_against, check_precision, correction_precision
from ..report import plot_residuals, write_report_json, write_residuals_gpkg
from ..rpc_io import write_rpb, write_rpc_txt, write_rpc_vrt
from ..threads import blas_serial
from ._common import Scene, cancel_check, collect_warnings, declare_report_outputs, finish_report, is_path
from .ortho import check_ortho_options, scene_footprint, warp_ortho

# Old private names, kept for callers and tests that used them from compensation.py.
_same_file = same_file
_rpc_stem = rpc_stem
_check_not_a_shadowing_sidecar = check_not_a_shadowing_sidecar


def output_kind(path) -> str:
    """'rpb', 'rpc_txt' or 'vrt' from an output path (case-insensitive); GCPError for any other name."""
    low = os.path.basename(str(path)).lower()
    if low.endswith(".rpb"):
        return "rpb"
    if low.endswith("_rpc.txt") or low.endswith(".txt"):
        return "rpc_txt"
    if low.endswith(".vrt"):
        return "vrt"
    raise GCPError(f"output {path!r}: use a name ending in .RPB, _RPC.TXT or .vrt")


def _write_rpc_as(rpc, path: str, kind: str, image: Optional[str]) -> None:
    """Write ``rpc`` to ``path`` (a fresh temporary) in the form ``kind`` names."""
    if kind == "vrt":
        write_rpc_vrt(image, rpc, path, overwrite=True)
    elif kind == "rpb":
        write_rpb(rpc, path, overwrite=True)
    else:
        write_rpc_txt(rpc, path, overwrite=True)


def write_refined_rpc(rpc, out_path, *, image: Optional[str] = None, inputs: Sequence[str] = (),
                      overwrite: bool = False) -> str:
    """Write a refined RPC as ``.RPB``, ``_RPC.TXT`` or (with ``image``) a VRT over the untouched image (METHODS §4.2).

    Refuses to write over any of ``inputs`` (and over ``image``), to write a sidecar that GDAL would read as the RPC
    of one of them, and, unless ``overwrite``, over an existing file. Written through an :class:`OutputSet`.
    """
    out_path = os.fspath(out_path)
    kind = output_kind(out_path)
    if kind == "vrt" and not image:
        raise GCPError("a .vrt output needs an image input; for an RPC file write .RPB or _RPC.TXT")
    outs = OutputSet(list(inputs) + ([image] if image else []), overwrite=overwrite)
    tmp = outs.declare("rpc", out_path)
    with outs:
        _write_rpc_as(rpc, tmp, kind, image)
    return out_path


def check_refine_options(*, max_uncertainty_px: Optional[float] = None, gcp_columns: Optional[str] = None,
                         **_ignored) -> None:
    """Refuse option values that make no sense before any work (also once for a whole batch)."""
    if max_uncertainty_px is not None and not float(max_uncertainty_px) > 0:
        raise GCPError(f"max uncertainty {max_uncertainty_px} px makes no sense: give a positive number of pixels "
                       "(default 10)")
    if gcp_columns:
        parse_columns(gcp_columns)


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def refine_rpc(source, gcps, model="affine", *, out, order: Optional[int] = None,
               along: Optional[str] = None, ccd_axis: str = "sample", dem=None, geoid=None, gcp_crs=None,
               gcp_layer: Optional[str] = None, check_fraction: Optional[float] = None, seed: int = 0,
               leave_one_out: bool = False, robust: bool = True, outlier_threshold: float = 4.0,
               report: Optional[str] = None, residuals: Optional[str] = None, plot: Optional[str] = None,
               overwrite: bool = False, progress=None, ortho=None,
               ortho_options: Optional[Dict[str, Any]] = None, check_plausibility: bool = True,
               max_uncertainty_px: Optional[float] = None, gcp_columns: Optional[str] = None,
               gcp_pixel_convention: Optional[str] = None, rpc=None) -> Dict[str, Any]:
    """Refine the RPC of an image or sidecar with GCPs and write it (METHODS §4, §6); ``gf4cal refine``.

    Parameters
    ----------
    source : image with an RPC (tags, .RPB, _RPC.TXT, NITF, ...) or a standalone RPC file
    rpc : the RPC file of an image that carries none (a crop and its product's ``.geom`` / DIMAP ``RPC_*.XML``: the
        crop's origin is applied, :func:`gdal_gf4cal.crop.image_rpc`; report ``notes``); default the image's own
        RPC, else the RPC file named like it beside it
    gcps : path of a GCP file (CSV, GeoPackage/GeoJSON in any CRS, QGIS .points, raster with GCPs) or a table;
        ``gcp_layer`` names the layer of a multi-layer vector file; ``gcp_columns`` is the column map of a
        header-less CSV (``"id,sample,line,lon,lat,h"``) and ``gcp_pixel_convention`` (``"center"``/``"corner"``)
        the convention of the file's image coordinates (:func:`~gdal_gf4cal.gcp.read_gcps`; METHODS §6)
    model, order, along, ccd_axis, robust, outlier_threshold, leave_one_out : see
        :func:`~gdal_gf4cal.compensation.fit_compensation`; ``model="auto"`` chooses by leave-one-out error
        (:func:`~gdal_gf4cal.model_selection.select_model`; report ``model_selection``)
    dem : DEM path / :class:`~gdal_gf4cal.dem.DEM` / number; supplies missing GCP heights (``geoid`` converts
        geoid heights to ellipsoidal ones)
    check_fraction : if given, that share of the GCPs becomes check points (seeded with ``seed``, spread over the
        image); otherwise the file's roles are used (all control if it has none)
    out : ``.RPB``, ``_RPC.TXT`` or (image input only) ``.vrt`` over the untouched image; never an input
    report, residuals, plot : optional ``report.json``, residual GeoPackage and PNG
    overwrite : replace existing outputs (never an input); without it any existing output is refused before work
    ortho : also orthorectify the image with the refined RPC over ``dem`` into this GeoTIFF (``ortho_options``:
        ``crs``, ``res_m``, ``resampling`` of :func:`~gdal_gf4cal.workflows.ortho.orthorectify`); report ``ortho``
    check_plausibility : refuse GCPs that cannot belong to the image, use those measured outside it but inside the
        RPC's domain with a warning, compare heights with ``dem`` (feet, vertical datum)
        (:func:`~gdal_gf4cal.plausibility.check_gcps_against`); ``False`` for experts only
    max_uncertainty_px : refuse a correction whose propagated 1-sigma uncertainty over the image exceeds it
        (default :data:`~gdal_gf4cal.plausibility.MAX_UNCERTAINTY_PX`; report ``precision_px``, a warning above 1 px)

    Returns
    -------
    dict
        The report (also written to ``report``): ``model``, ``control``/``check`` with ``before``/``after``
        statistics, ``outliers``, ``apply`` (fold or refit and its error), ``warnings``, ``outputs``.
        All outputs are written together after everything was computed, or none is (failure, cancel, SIGTERM).
    """
    source = os.fspath(source)
    out = os.fspath(out)
    kind, scene, ortho_grid, outs = _prepare(
        source, out, gcps, dem, rpc, geoid, ortho, ortho_options, max_uncertainty_px=max_uncertainty_px,
        gcp_columns=gcp_columns, residuals=residuals, plot=plot, report=report, overwrite=overwrite, progress=progress)
    image_size = scene.size                   # None for a standalone RPC file
    warns: list = []
    with outs, collect_warnings(warns):
        _progress.report(progress, 0.0, "reading the RPC and GCPs")
        rpc, crop_note, dem_obj, table = _read_inputs(
            scene, rpc, gcps, dem, geoid, image_size, warns, check_plausibility=check_plausibility,
            check_fraction=check_fraction, seed=seed, layer=gcp_layer, crs=gcp_crs, columns=gcp_columns,
            pixel_convention=gcp_pixel_convention)
        _progress.report(progress, 0.1, "estimating the compensation")
        selection, result, precision = _fit(rpc, table, model, dem_obj, image_size, max_uncertainty_px, warns,
                                            order=order, along=along, ccd_axis=ccd_axis, robust=robust,
                                            outlier_threshold=outlier_threshold, leave_one_out=leave_one_out)
        _progress.report(progress, 0.2, "applying the compensation")
        applied = apply_compensation(rpc, result, image_size=image_size,
                                     progress=_progress.scaled(progress, 0.2, 0.9))
        rep = _refine_report(source, gcps, out, rpc, result, applied, precision, selection, crop_note, leave_one_out)
        _progress.report(progress, 0.9, "writing outputs")
        _write_rpc_as(applied.rpc, outs.tmp("rpc"), kind, source if kind == "vrt" else None)
        if ortho is not None:
            rep["ortho"] = _write_ortho(outs, source, image_size, applied.rpc, dem, ortho_grid, ortho_options,
                                        _progress.scaled(progress, 0.9, 0.98))
        _write_residual_outputs(outs, rpc, applied.rpc, result, image_size, dem_obj, residuals, plot)
        rep["outputs"] = outs.paths
        finish_report(rep, warns)
        if report:
            write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep


def _prepare(source: str, out: str, gcps, dem, rpc, geoid, ortho, ortho_options, *, max_uncertainty_px,
             gcp_columns, **declare):
    """Before any work: ``(kind, scene, ortho_grid, outs)``, the output's kind, the opened input
    (:class:`~gdal_gf4cal.workflows._common.Scene`), the geoid grid of the ortho and the run's OutputSet;
    impossible outputs and options refused."""
    kind = output_kind(out)
    check_refine_options(max_uncertainty_px=max_uncertainty_px, gcp_columns=gcp_columns)
    scene = Scene.open(source)
    image_size, inputs = scene.size, list(scene.files)
    inputs += [os.fspath(x) for x in (gcps, dem, rpc) if is_path(x)]
    _check_outputs(source, kind, image_size, declare["residuals"])
    ortho_grid = None if ortho is None else _ortho_preflight(image_size, dem, geoid, ortho_options or {})
    return kind, scene, ortho_grid, _declare_outputs(inputs, out, ortho=ortho, **declare)


def _check_outputs(source: str, kind: str, image_size, residuals) -> None:
    """Refuse a .vrt output without an image and residuals not written as .gpkg."""
    if kind == "vrt" and image_size is None:
        raise GCPError(f"{source} is not an image: write the refined RPC as .RPB or _RPC.TXT, or give the image "
                       "to get a .vrt")
    if residuals and not os.fspath(residuals).lower().endswith(".gpkg"):
        raise GCPError(f"residuals are written as a GeoPackage: give a .gpkg path, not {os.fspath(residuals)!r}")


def _read_inputs(scene: Scene, rpc, gcps, dem, geoid, image_size, warns: list, *, check_plausibility: bool,
                 check_fraction, seed: int, **reader):
    """``(rpc, crop_note, dem, table)``: the RPC, the DEM and the GCP table with its roles, the table checked
    against the RPC and the DEM (its warnings into ``warns`` at once) unless ``check_plausibility`` is off."""
    scene = scene.with_rpc(rpc)
    rpc, crop_note = scene.rpc, scene.note
    dem_obj = DEM.from_user_input(dem, geoid=geoid)
    table = _read_table(gcps, dem_obj, scene.path if image_size is not None else None, **reader)
    table = assign_roles(table, check_fraction, seed=seed)
    if check_plausibility:
        with collect_warnings(warns):         # now: the report written below lists them
            check_gcps_against(rpc, table, image_size, dem=dem_obj)
    return rpc, crop_note, dem_obj, table


def _declare_outputs(inputs, out: str, *, ortho, residuals, plot, report, overwrite: bool, progress) -> OutputSet:
    """The OutputSet of a refine run: the RPC, the ortho, the residual GeoPackage, plot and report."""
    outs = OutputSet(inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    outs.declare("rpc", out)
    if ortho is not None:
        outs.declare("ortho", ortho, check=check_raster())
    declare_report_outputs(outs, residuals=residuals, plot=plot, report=report)
    return outs


def _fit(rpc, table, model, dem_obj, image_size, max_uncertainty_px: Optional[float], warns: list, *,
         robust: bool, outlier_threshold: float, **options):
    """``(selection, result, precision)``: the compensation of ``model`` (``"auto"``: the model chosen by
    leave-one-out error with a parsimony rule, ``selection`` its report; else None) and its propagated precision
    over the image (refused above ``max_uncertainty_px``, a warning into ``warns`` above 1 px)."""
    selection = None
    if str(model) == "auto":
        selection = select_model(rpc, table, dem=dem_obj, robust=robust, outlier_threshold=outlier_threshold)
        model = selection.chosen
    result = fit_compensation(rpc, table, model, dem=dem_obj, robust=robust, outlier_threshold=outlier_threshold,
                              **options)
    precision = correction_precision(result, image_size or rpc.image_size)
    warns.extend(check_precision(precision, result.model.label, max_uncertainty_px=MAX_UNCERTAINTY_PX
                                 if max_uncertainty_px is None else float(max_uncertainty_px)))
    return selection, result, precision


def _write_ortho(outs: OutputSet, source: str, image_size, new_rpc, dem, ortho_grid, ortho_options, progress):
    """Orthorectify the image with the refined RPC over the DEM file into the OutputSet's temporary; its report."""
    dem_path = dem.path if getattr(dem, "path", None) else os.fspath(dem)
    return warp_ortho(source, image_size, new_rpc, dem_path, ortho_grid, outs.tmp("ortho"), progress=progress,
                      **(ortho_options or {}))


def _read_table(gcps, dem_obj, image: Optional[str], *, layer, crs, columns, pixel_convention):
    """The GCP table of a file (:func:`~gdal_gf4cal.gcp.read_gcps`) or a table given (validated)."""
    if not is_path(gcps):
        return validate_gcps(gcps, dem=dem_obj)
    kw = {"layer": layer} if layer else {}
    return read_gcps(os.fspath(gcps), dem=dem_obj, crs=crs, columns=columns, pixel_convention=pixel_convention,
                     image=image, **kw)


def _refine_report(source: str, gcps, out: str, rpc, result, applied, precision, selection, crop_note,
                   leave_one_out: bool) -> Dict[str, Any]:
    """The refine report: its files, the compensation's figures, the crop note, how it was applied, its
    precision, the model selection and the leave-one-out statistics of the control points when asked for."""
    rep: Dict[str, Any] = {"input": source, "gcps": os.fspath(gcps) if is_path(gcps) else None, "output": out}
    rep.update(result.to_dict(rpc))
    if crop_note:
        rep["notes"] = [crop_note] + list(rep.get("notes", []))
    rep["apply"] = applied.to_dict()
    rep["precision_px"] = precision
    if selection is not None:
        rep["model_selection"] = selection.to_dict()
    if leave_one_out:
        tab = result.gcps
        sel = (tab["role"] == "control").to_numpy() & ~tab["outlier"].to_numpy(bool)
        rep["leave_one_out"] = {"n": int(sel.sum()),
                                "line": report_axis_stats(tab["res_line_loo"].to_numpy(float)[sel]),
                                "sample": report_axis_stats(tab["res_sample_loo"].to_numpy(float)[sel])}
    return rep


def _write_residual_outputs(outs, rpc, new_rpc, result, image_size, dem_obj, residuals, plot) -> None:
    """The residual GeoPackage (arrows as ground offsets through the original RPC, footprint of the new one on
    the DEM) and the residual plot, into the OutputSet's temporaries, when asked for."""
    title = f"GCP residuals, {result.model.label}"
    if residuals:
        fp = scene_footprint(new_rpc, image_size or rpc.image_size, dem_obj)     # on the DEM, as the ortho
        write_residuals_gpkg(_with_ground_offsets(rpc, result.gcps), outs.tmp("residuals"), footprint=fp,
                             title=title, cancelled=outs.cancelled)   # a cancel mid-write stops it
        outs.set_check("residuals", check_vector({"gcps": len(result.gcps)}))
    if plot:
        plot_residuals(result.gcps, outs.tmp("plot"), image_size=image_size, title=title)


def _ortho_preflight(image_size, dem, geoid, ortho_options):
    """Refuse ``ortho=`` without an image or a DEM file, bad ortho options, or a geoid that cannot be applied
    (before any work); returns the geoid grid to apply (None: heights used as they are)."""
    if image_size is None:
        raise GCPError("an ortho needs the image itself, not a standalone RPC file: give the image")
    check_ortho_options(ortho_options.get("resampling", "bilinear"), ortho_options.get("res_m"))
    if getattr(dem, "path", None):              # an opened DEM: its own geoid choice
        return resolve_geoid(dem.geoid_applied or "none", dem.path)
    if not is_path(dem) or _is_number(dem):
        raise GCPError("an ortho needs a DEM file (dem=, --dem) covering the scene")
    return resolve_geoid(geoid, os.fspath(dem))


def _is_number(x) -> bool:
    try:
        float(os.fspath(x))
        return True
    except ValueError:
        return False


def _with_ground_offsets(rpc, tab):
    """``tab`` with the residuals as ground offsets in metres through the RPC (METHODS §6): ``res_east_m_*``,
    ``res_north_m_*``, ``res_m_*`` for before/after (the GeoPackage's arrows are drawn from them)."""
    tab = tab.copy(deep=False)      # new columns only: the 1e6-row table is not duplicated
    lon, lat, h = (tab[c].to_numpy(float) for c in ("lon", "lat", "h"))
    jac = None                      # the same points before and after: one Jacobian
    for epoch in ("before", "after"):
        cs, cl = f"res_sample_{epoch}", f"res_line_{epoch}"
        if cs in tab.columns and cl in tab.columns:
            jac = ground_jacobian(rpc, lon, lat, h) if jac is None else jac
            e, n = ground_offsets_m(rpc, lon, lat, h, tab[cs].to_numpy(float), tab[cl].to_numpy(float),
                                    jacobian=jac)
            tab[f"res_east_m_{epoch}"], tab[f"res_north_m_{epoch}"] = e, n
            tab[f"res_m_{epoch}"] = np.hypot(e, n)
    return tab
