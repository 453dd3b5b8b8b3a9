"""``gf4cal refine`` / QGIS "Refine RPC": read, estimate, apply, write, report (METHODS §4, §6).

Moved from :mod:`gdal_gf4cal.compensation` (which keeps the model, the fit and :func:`apply_compensation`);
every output goes through one :class:`~gdal_gf4cal.outputs.OutputSet`: all written, or none.
"""
from __future__ import annotations

import os
from typing import Any, Dict, Optional, Sequence

from ..errors import GCPError
from ..crop import image_rpc
from ..outputs import OutputSet, check_not_a_shadowing_sidecar, check_vector, rpc_stem, same_file
from ..dem import DEM
from ._common import declare_report_outputs, _open_image, cancel_check, collect_warnings, finish_report, is_path

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
        from ..rpc_io import write_rpc_vrt
        write_rpc_vrt(image, rpc, path, overwrite=True)
    elif kind == "rpb":
        from ..rpc_io import write_rpb
        write_rpb(rpc, path, overwrite=True)
    else:
        from ..rpc_io import write_rpc_txt
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
        from ..gcp_formats import parse_columns
        parse_columns(gcp_columns)


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
    from .. import progress as _progress
    from ..compensation import _axis_stats, apply_compensation, fit_compensation
    from ..gcp import read_gcps
    from ..gcp_formats import assign_roles

    source = os.fspath(source)
    out = os.fspath(out)
    kind = output_kind(out)
    check_refine_options(max_uncertainty_px=max_uncertainty_px, gcp_columns=gcp_columns)
    image_size, inputs = _open_image(source)
    inputs += [os.fspath(x) for x in (gcps, dem, rpc) if is_path(x)]
    if kind == "vrt" and image_size is None:
        raise GCPError(f"{source} is not an image: write the refined RPC as .RPB or _RPC.TXT, or give the image "
                       "to get a .vrt")
    if residuals and not os.fspath(residuals).lower().endswith(".gpkg"):
        raise GCPError(f"residuals are written as a GeoPackage: give a .gpkg path, not {os.fspath(residuals)!r}")
    if ortho is not None:
        ortho_grid = _ortho_preflight(image_size, dem, geoid, ortho_options or {})
    outs = OutputSet(inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    outs.declare("rpc", out)
    if ortho is not None:
        from ..outputs import check_raster
        outs.declare("ortho", ortho, check=check_raster())
    declare_report_outputs(outs, residuals=residuals, plot=plot, report=report)
    warns: list = []
    with outs, collect_warnings(warns):
        _progress.report(progress, 0.0, "reading the RPC and GCPs")
        rpc, crop_note = image_rpc(source, rpc)
        dem_obj = DEM.from_user_input(dem, geoid=geoid)
        if is_path(gcps):
            kw = {"layer": gcp_layer} if gcp_layer else {}
            table = read_gcps(os.fspath(gcps), dem=dem_obj, crs=gcp_crs, columns=gcp_columns,
                              pixel_convention=gcp_pixel_convention,
                              image=source if image_size is not None else None, **kw)
        else:
            from ..gcp import validate_gcps
            table = validate_gcps(gcps, dem=dem_obj)
        table = assign_roles(table, check_fraction, seed=seed)
        from ..plausibility import MAX_UNCERTAINTY_PX, check_gcps_against, check_precision, correction_precision
        if check_plausibility:
            with collect_warnings(warns):         # now: the report written below lists them
                check_gcps_against(rpc, table, image_size, dem=dem_obj)
        _progress.report(progress, 0.1, "estimating the compensation")
        selection = None
        if str(model) == "auto":              # --model auto: leave-one-out error with a parsimony rule
            from ..model_selection import select_model
            selection = select_model(rpc, table, dem=dem_obj, robust=robust, outlier_threshold=outlier_threshold)
            model = selection.chosen
        result = fit_compensation(rpc, table, model, order=order, along=along, ccd_axis=ccd_axis, dem=dem_obj,
                                  robust=robust, outlier_threshold=outlier_threshold, leave_one_out=leave_one_out)
        precision = correction_precision(result, image_size or rpc.image_size)
        warns.extend(check_precision(precision, result.model.label, max_uncertainty_px=MAX_UNCERTAINTY_PX
                                     if max_uncertainty_px is None else float(max_uncertainty_px)))
        _progress.report(progress, 0.2, "applying the compensation")
        applied = apply_compensation(rpc, result, image_size=image_size,
                                     progress=_progress.scaled(progress, 0.2, 0.9))
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
                                    "line": _axis_stats(tab["res_line_loo"].to_numpy(float)[sel]),
                                    "sample": _axis_stats(tab["res_sample_loo"].to_numpy(float)[sel])}
        _progress.report(progress, 0.9, "writing outputs")
        _write_rpc_as(applied.rpc, outs.tmp("rpc"), kind, source if kind == "vrt" else None)
        if ortho is not None:
            from .ortho import warp_ortho
            dem_path = dem.path if getattr(dem, "path", None) else os.fspath(dem)
            rep["ortho"] = warp_ortho(source, image_size, applied.rpc, dem_path, ortho_grid, outs.tmp("ortho"),
                                      progress=_progress.scaled(progress, 0.9, 0.98), **(ortho_options or {}))
        title = f"GCP residuals, {result.model.label}"
        if residuals:
            from ..report import write_residuals_gpkg
            from .ortho import scene_footprint
            fp = scene_footprint(applied.rpc, image_size or rpc.image_size, dem_obj)     # on the DEM, as the ortho
            write_residuals_gpkg(_with_ground_offsets(rpc, result.gcps), outs.tmp("residuals"), footprint=fp,
                                 title=title, cancelled=outs.cancelled)   # a cancel mid-write stops it
            outs.set_check("residuals", check_vector({"gcps": len(result.gcps)}))
        if plot:
            from ..report import plot_residuals
            plot_residuals(result.gcps, outs.tmp("plot"), image_size=image_size, title=title)
        rep["outputs"] = outs.paths
        finish_report(rep, warns)
        if report:
            from ..report import write_report_json
            write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep


def _ortho_preflight(image_size, dem, geoid, ortho_options):
    """Refuse ``ortho=`` without an image or a DEM file, bad ortho options, or a geoid that cannot be applied
    (before any work); returns the geoid grid to apply (None: heights used as they are)."""
    from ..geoid import resolve_geoid
    from .ortho import check_ortho_options
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
    import numpy as np
    from ..compensation import ground_jacobian, ground_offsets_m
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
