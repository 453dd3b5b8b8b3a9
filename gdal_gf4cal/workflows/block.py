"""``gf4cal block-adjust`` / QGIS ``gf4cal:blockadjust``: multi-CCD / band-to-band block calibration of one group
from its RPC images (METHODS §8; engine :mod:`gdal_gf4cal.block`). All outputs together or none.

Images are named by a **key**: the file name without extension when those are unique, else the image's folder name
(simulated groups: ``ccd1/scene.tif`` -> ``ccd1``). The observation files' ``image`` column names images by key,
file name or path. Outputs in ``out``: ``<key>.RPB`` per image (refit, METHODS §3, error reported),
``calibration.json`` (the group's exterior and every image's interior, for ``apply-calibration``), ``report.json``,
``residuals.gpkg`` (layers ``<key>_gcps`` / ``<key>_residual_vectors`` per image and ``seams``) and ``seams.png``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Sequence, Union

import numpy as np

from .. import progress as _progress
from ..block import (BlockError, adjust_block, calibration_dict, corrected_model, derive_layout, pair_bands,
                     prediction_std, seam_offsets, write_calibration)
from ..crop import image_and_rpc, image_rpc
from ..dem import DEM
from ..errors import GCPError
from ..matching import collect_gcps, match_ties
from ..matching.raw import overlap_region
from ..observations import from_gcps, read_observations
from ..outputs import OutputSet, check_vector, scene_stem
from ..plausibility import STRAY_FRACTION, check_gcps_against, check_measured_inside
from ..report import plot_seams, write_points_layer, write_report_json, write_residuals_gpkg
from ..rpc_fit import fit_rpc_from_model
from ..rpc_io import write_rpb
from ..stats import accuracy_by_role
from ..threads import blas_serial
from ._common import _open_image, cancel_check, collect_warnings, finish_report

__all__ = ["block_adjust", "check_observations", "image_keys", "parse_bands_of", "summary_lines"]


def image_keys(paths: Sequence) -> List[str]:
    """Keys of images (module docstring): file stems when unique, else folder names; unique or an error."""
    stems = [scene_stem(p) for p in paths]
    if len(set(s.casefold() for s in stems)) == len(stems):
        return stems
    folders = [os.path.basename(os.path.dirname(os.path.abspath(os.fspath(p)))) for p in paths]
    if len(set(f.casefold() for f in folders)) == len(folders):
        return folders
    raise BlockError("two images have the same file name and folder name; give each image of the group a distinct "
                     "name")


def _resolve(name: str, paths: Sequence[str], keys: Sequence[str], what: str) -> str:
    """The key of the image ``name`` (a key, file name, path or stem)."""
    name = str(name).strip()
    low = name.casefold()
    for p, k in zip(paths, keys):
        if low in (k.casefold(), os.path.basename(p).casefold(), scene_stem(p).casefold()) and \
                sum(low in (kk.casefold(), os.path.basename(pp).casefold()) for pp, kk in zip(paths, keys)) <= 1:
            return k
        if os.path.abspath(name) == os.path.abspath(p):
            return k
    raise BlockError(f"{what} names image {name!r}, which is not among the images given "
                     f"({', '.join(keys[:6])}{', ...' if len(keys) > 6 else ''}); give that image or fix the name")


#: How messages name the bands-of option; the QGIS provider words ``(--bands-of)`` as ``(BANDS_OF)``.
BANDS_OF = "bands of (--bands-of)"


#: How messages name the RPC pairs option (QGIS: ``(RPCS)``).
RPC_PAIRS = "RPC pairs (--rpc)"


def parse_rpc_pairs(items: Union[None, Mapping[str, str], Sequence[str]]) -> Dict[str, str]:
    """``["IMAGE=RPC", ...]`` (CLI/QGIS) or a mapping -> ``{image: RPC file}``."""
    if not items:
        return {}
    if isinstance(items, Mapping):
        return {str(a): os.fspath(b) for a, b in items.items()}
    pairs = {}
    for entry in items:
        image, rpc = image_and_rpc(entry)
        if rpc is None or not image or not rpc:
            raise BlockError(f"{RPC_PAIRS}: {entry!r} is not IMAGE=RPC; give each image whose RPC is a separate "
                             "file with that file, e.g. left.tif=left.geom")
        pairs[image] = rpc
    return pairs


def parse_bands_of(items: Union[None, Mapping[str, str], Sequence[str]]) -> Dict[str, str]:
    """``["IMAGE=REFIMAGE", ...]`` (CLI/QGIS) or a mapping -> ``{band image: reference-band image}``."""
    if not items:
        return {}
    if isinstance(items, Mapping):
        return {str(k): str(v) for k, v in items.items()}
    out = {}
    for it in items:
        if "=" not in str(it):
            raise BlockError(f"bands of (--bands-of) {it!r}: write IMAGE=REFIMAGE (a band image and the reference-band image of "
                             "its CCD)")
        a, b = str(it).split("=", 1)
        out[a.strip()] = b.strip()
    return out


def _read_obs(paths: Sequence[str], keys: Sequence[str], files: Sequence, dem, gcp_files=(), warns=None) -> Any:
    """Read and merge the observation files, image names resolved to keys. Tie rows naming an image that is not
    given are an error; GCP rows of such images (a GCP file of more images than the block) are dropped, with a
    warning."""
    tables = []
    for f in files:
        t = read_observations(f, need_height=False, dem=dem)
        where = f"the observation file {os.path.basename(os.fspath(f))}"
        ids = {}
        left_out = []
        for i in t["image_id"].unique():
            try:
                ids[i] = _resolve(i, paths, keys, where)
            except BlockError:
                rows = t["image_id"] == i
                if f not in gcp_files or (t.loc[rows, "kind"] == "tie").any():
                    raise
                left_out.append(str(i))
        if left_out and warns is not None:
            warns.append(f"{where}: GCPs of {len(left_out)} image(s) not given left out ({', '.join(left_out[:4])}"
                         f"{', ...' if len(left_out) > 4 else ''})")
        t = t[t["image_id"].isin(list(ids))].copy()
        t["image_id"] = t["image_id"].map(ids)
        tables.append(t)
    if not tables:
        return None
    import pandas as pd          # where used: at module top it slows every CLI start-up
    tab = pd.concat(tables, ignore_index=True)
    return tab.drop_duplicates(["point_id", "image_id"]).reset_index(drop=True)


#: The steps of a run and their share of the progress bar (measured on the simulated 20-image group, 512 x 256 px
#: per CCD: reading 3 s, adjustment 3 s, refits 6 s, seams 1 s, residuals.gpkg 15 s and seams.png 6 s).
STEPS = {"read": ("reading the images and the observations", 0.08),
         "ortho": ("collecting GCPs from the reference ortho", 0.2),
         "match": ("matching tie points", 0.2),
         "adjust": ("adjusting the block", 0.15),
         "refit": ("refitting the RPCs", 0.25),
         "seams": ("measuring the seams", 0.04),
         "write": ("writing residuals.gpkg, seams.png and report.json", 0.48)}


class _Steps:
    """Progress of a run: each step named with its number ("step 4/6 adjusting the block: ...") on its share of
    the bar (:data:`STEPS`), the steps the run does only."""

    def __init__(self, progress, names: Sequence[str]):
        self.progress, self.names = progress, list(names)
        total = sum(STEPS[n][1] for n in self.names)
        self.start: Dict[str, float] = {}
        pos = 0.0
        for n in self.names:
            self.start[n] = pos / total
            pos += STEPS[n][1]
        self.stop = {n: self.start[n] + STEPS[n][1] / total for n in self.names}

    def __call__(self, name: str, detail: str = ""):
        """Report the start of step ``name``; returns the step's own progress callback (messages prefixed)."""
        prefix = f"step {self.names.index(name) + 1}/{len(self.names)} {STEPS[name][0]}"
        _progress.report(self.progress, self.start[name], prefix + (f": {detail}" if detail else ""))
        sub = _progress.scaled(self.progress, self.start[name], self.stop[name])
        if sub is None:
            return None
        return lambda f, m="": sub(f, f"{prefix}: {m}" if m else prefix)


@dataclass
class _Group:
    """The opened group: keys, paths, RPCs, image sizes, layout, DEM, the input files and notes."""

    paths: List[str]
    keys: List[str]
    models: Dict[str, Any]
    sizes: Dict[str, Any]
    inputs: List[str]
    dem: Any = None
    layout: Any = None
    notes: List[str] = field(default_factory=list)


def _check_request(paths, solver) -> None:
    if len(paths) < 2:
        raise BlockError("a block needs the images of at least two CCDs; give every CCD image of the group")
    if solver not in ("simultaneous", "alternating"):
        raise BlockError(f"solver {solver!r} unknown; choose simultaneous or alternating")


def _check_observations_given(gcps, ties, match_ties, reference_ortho) -> None:
    if not (gcps or reference_ortho):
        raise BlockError("no control: give GCPs (--gcps) or a reference ortho (--reference-ortho) to fix the datum")
    if not (ties or match_ties):
        raise BlockError("no tie points: give --ties or --match-ties to tie the CCDs and bands together")


def _open_group(paths, rpcs, bands_of, reference_ccd, dem, geoid) -> _Group:
    """Keys, RPCs (crops through their product's RPC), sizes and the layout: ``bands_of`` when given, else derived
    from the RPCs (:func:`~gdal_gf4cal.block.pair_bands`); separate views are refused
    (:class:`~gdal_gf4cal.block.SeparateViewsError`)."""
    keys = image_keys(paths)
    rpc_of = {_resolve(a, paths, keys, RPC_PAIRS): b for a, b in parse_rpc_pairs(rpcs).items()}
    grp = _Group(paths, keys, {}, {}, list(rpc_of.values()))
    for p, k in zip(paths, keys):
        grp.sizes[k], files = _open_image(p)
        grp.inputs += files
        grp.models[k], note = image_rpc(p, rpc_of.get(k))
        grp.notes += [f"{k}: {note}"] if note else []
    sizes = {k: s for k, s in grp.sizes.items() if s}
    bmap = {_resolve(a, paths, keys, BANDS_OF): _resolve(b, paths, keys, BANDS_OF)
            for a, b in parse_bands_of(bands_of).items()}
    if bmap:
        order = [k for k in keys if k not in bmap]
    else:
        order, bmap = pair_bands(grp.models, keys, sizes=sizes)
    ref_ccd = _resolve(reference_ccd, paths, keys, "--reference-ccd") if reference_ccd else None
    grp.layout = derive_layout(grp.models, order, bands_of=bmap, sizes=sizes, reference_ccd=ref_ccd)
    grp.dem = DEM.from_user_input(dem, geoid=geoid)
    return grp


def _declare_outputs(grp: _Group, out, overwrite: bool, progress) -> OutputSet:
    outd = os.fspath(out)
    outs = OutputSet(grp.inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    for k in grp.keys:
        outs.declare(f"rpb:{k}", os.path.join(outd, f"{k}.RPB"))
    outs.declare("calibration", os.path.join(outd, "calibration.json"))
    outs.declare("report", os.path.join(outd, "report.json"))
    outs.declare("residuals", os.path.join(outd, "residuals.gpkg"), check=check_vector())
    outs.declare("seams_plot", os.path.join(outd, "seams.png"))
    return outs


def _more_observations(grp: _Group, tab, reference_ortho, match_ties: bool, steps: _Steps):
    """``tab`` with the GCPs collected from the reference ortho and the matched tie points."""
    extra = []
    if reference_ortho:
        extra.append(_collect_from_ortho(grp.paths, grp.keys, grp.layout.order, grp.models, reference_ortho,
                                         grp.dem, steps("ortho")))
    if match_ties:
        extra.append(_match_ties(grp.paths, grp.keys, grp.layout, grp.models, grp.dem, steps("match")))
    if not extra:
        return tab
    import pandas as pd          # where used: at module top it slows every CLI start-up
    tab = pd.concat(([tab] if tab is not None else []) + extra, ignore_index=True)
    return tab.drop_duplicates(["point_id", "image_id"]).reset_index(drop=True)


def _refit(grp: _Group, est, outs: OutputSet, progress) -> Dict[str, Any]:
    """Per image: the corrected model's RPC refit and written (``rpb:<key>``), its report entry (precision, RPC
    fit, GCP and tie residuals); one progress message per image."""
    images_rep: Dict[str, Any] = {}
    n = len(grp.keys)
    _progress.report(progress, 0.0, "the precision of every image (the earlier stages' errors propagated)")
    est.complete_covariance()
    for i, (p, k) in enumerate(zip(grp.paths, grp.keys)):
        _progress.report(progress, 0.2 + 0.8 * i / n, f"{k} ({i + 1} of {n})")
        lay = grp.layout.images[k]
        new_rpc, fit = fit_rpc_from_model(corrected_model(est, k, grp.models[k]), size=lay.size,
                                          height_range=tuple(grp.models[k].height_range))
        write_rpb(new_rpc, outs.tmp(f"rpb:{k}"), overwrite=True)
        rows = est.table[est.table["image_id"] == k]
        g, t = rows[rows["kind"] == "gcp"], rows[rows["kind"] == "tie"]
        W, H = lay.size
        S, L = (a.ravel() for a in np.meshgrid(np.linspace(0.5, W - 0.5, 11), np.linspace(0.5, H - 0.5, 11)))
        fs, fl = prediction_std(est, k, S, L)
        images_rep[k] = {"image": p, "rpb": outs.path(f"rpb:{k}"), "ccd": lay.ccd,
                         "precision_px": float(np.sqrt(np.mean(fs ** 2 + fl ** 2))),
                         "reference_band_image": lay.reference, "rpc_fit": fit.to_dict(),
                         "gcps": accuracy_by_role(g) if len(g) else None,
                         "ties": accuracy_by_role(t.assign(role="control"), roles=("control",))["control"]
                         if len(t) else None}
    return images_rep


def _report(grp: _Group, est, solver: str, images_rep, seams) -> Dict[str, Any]:
    layout = grp.layout
    rep: Dict[str, Any] = {
        "command": "block-adjust", "method": "METHODS §8 block calibration in RPC space",
        "solver": solver, "layout": layout.to_dict(), "estimate": est.to_dict(), "stages": est.stages,
        "exterior": {n: float(v) for n, v in zip(est.names[:5], est.x[:5])},
        "images": images_rep,
        "seams": [{k: v for k, v in s.items() if k != "points"} for s in seams],
        "band_to_band": _band_to_band(est.table, layout),
        "n_outliers": int(np.count_nonzero(est.outlier)),
        "outliers": [{"point_id": str(r.point_id), "image": str(r.image_id), "kind": str(r.kind)}
                     for r in est.table[est.table["outlier"]].itertuples()][:1000]}
    if est.comparison is not None:
        rep["solver_comparison"] = {
            solver: {"iterations": [s["iterations"] for s in est.stages],
                     "converged": [s["converged"] for s in est.stages],
                     "sigma0": float(est.sigma0)},
            est.comparison["solver"]: {"iterations": [s["iterations"] for s in est.comparison["stages"]],
                                       "converged": [s["converged"] for s in est.comparison["stages"]]},
            "max_prediction_difference_px": _max_difference(est.table, est.comparison["table"])}
    rep["warnings"] = list(est.warnings)
    if grp.notes:
        rep["notes"] = list(grp.notes)
    return rep


def _write_residuals(gp: str, est, keys, seams, progress) -> None:
    """residuals.gpkg: per image its GCPs (and tie rays), then the ``seams`` layer."""
    for i, k in enumerate(keys):
        _progress.report(progress, i / (len(keys) + 1), f"residuals.gpkg: {k} ({i + 1} of {len(keys)})")
        rows = est.table[est.table["image_id"] == k].rename(columns={"point_id": "id"})
        rows = rows[np.isfinite(rows["lon"].to_numpy(float))]
        if len(rows) == 0:
            continue
        write_residuals_gpkg(rows.drop(columns=[c for c in ("image_id",) if c in rows.columns]), gp,
                             layer_prefix=f"{k}_", append=True, overwrite=True, title=f"{k} residuals")
    sp = [s for s in seams if s.get("points")]
    if not sp:
        return
    _progress.report(progress, len(keys) / (len(keys) + 1), "residuals.gpkg: the seams layer")
    cols: Dict[str, Any] = {"pair": np.concatenate([np.full(len(s["points"]["point_id"]),
                                                            f"{s['pair'][0]}|{s['pair'][1]}", dtype=object)
                                                    for s in sp])}
    for c in ("point_id", "line_b", "ds_before", "dl_before", "ds_after", "dl_after"):
        cols[c] = np.concatenate([np.asarray(s["points"][c]) for s in sp])
    cols["point_id"] = cols["point_id"].astype(str).astype(object)
    cols["offset_px_before"] = np.hypot(cols["ds_before"], cols["dl_before"])
    cols["offset_px_after"] = np.hypot(cols["ds_after"], cols["dl_after"])
    write_points_layer(gp, "seams", cols, np.concatenate([s["points"]["lon"] for s in sp]),
                       np.concatenate([s["points"]["lat"] for s in sp]),
                       description="one feature per overlap tie point: offset (px of the right image) of "
                                   "its measurement from the left image's prediction, before and after")


def _write_outputs(outs: OutputSet, grp: _Group, est, seams, rep, progress) -> None:
    write_calibration(calibration_dict(est), outs.tmp("calibration"))
    _write_residuals(outs.tmp("residuals"), est, grp.keys, seams, _progress.scaled(progress, 0.0, 0.7))
    _progress.report(progress, 0.7, "seams.png")
    rms = {k: (_planar_rms(est.table, k, "before"), _planar_rms(est.table, k, "after")) for k in grp.keys}
    plot_seams(seams, outs.tmp("seams_plot"), residual_rms=rms)
    rep["outputs"] = outs.paths
    _progress.report(progress, 0.95, "report.json")
    write_report_json(rep, outs.tmp("report"))


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def block_adjust(images: Sequence, *, dem, out, geoid=None, gcps=None, ties=None, match_ties: bool = False,
                 reference_ortho=None, bands_of=None, solver: str = "simultaneous", reference_ccd=None,
                 overwrite: bool = False, progress=None, check_plausibility: bool = True,
                 rpcs=None) -> Dict[str, Any]:
    """Block calibration of one group (METHODS §8) from files; see the module docstring for names and outputs.

    Parameters
    ----------
    images : image paths (RPC embedded or as a sidecar). The reference-band CCD images come **in their order
        across track** (adjacent ones must overlap); the other bands' images anywhere after their CCD's
        reference-band image.
    rpcs : ``["IMAGE=RPC", ...]`` (CLI ``--rpc``) or ``{image: rpc file}``: the RPC file of an image that carries
        none (a crop and its product's ``.geom``: the crop's origin is applied, :func:`gdal_gf4cal.crop.image_rpc`;
        the report's ``notes`` say so); other images: their own RPC, else the RPC file named like them beside them.
    dem : DEM path or number (tie-point heights); ``geoid``: its vertical datum (``auto``/``none``/``egm96``/...).
    gcps, ties : observation files (CSV/GeoPackage, long format: ``point_id, image, sample, line`` [``lon, lat, h``,
        ``role``, ``sigma``]); a single file may hold both (rows are de-duplicated).
    match_ties : tie points by raw-to-raw matching (adjacent CCDs and each band against its reference band).
    reference_ortho : an orthophoto to collect GCPs from for every reference-band image.
    bands_of : ``{band image: reference-band image}`` or ``["IMAGE=REFIMAGE", ...]``; default: derived from the
        RPCs (:func:`~gdal_gf4cal.block.pair_bands`: an image whose footprint coincides with an earlier one's is
        another band of that CCD). Separate views (stereo, other passes) are refused
        (:class:`~gdal_gf4cal.block.SeparateViewsError`, pointing to ``bundle-adjust``).
    solver : ``simultaneous`` or ``alternating``; ``alternating`` also runs the simultaneous solve and compares
        them in the report (``solver_comparison``).
    reference_ccd : the CCD image fixing the datum (default: the middle reference-band CCD).
    check_plausibility : every observation checked against its image as ``refine`` does (:func:`check_observations`:
        GCPs and tie measurements beyond the RPC's domain, GCP heights in feet or on another datum than the DEM's,
        GCPs far from their RPC prediction are refused before any work); ``False`` for experts only.

    Returns
    -------
    dict: the report written as ``report.json`` (+ ``outputs``, ``warnings``).
    """
    paths = [os.fspath(p) for p in images]
    _check_request(paths, solver)
    steps = _Steps(progress, ["read"] + (["ortho"] if reference_ortho else []) + (["match"] if match_ties else [])
                   + ["adjust", "refit", "seams", "write"])
    steps("read")
    grp = _open_group(paths, rpcs, bands_of, reference_ccd, dem, geoid)
    _check_observations_given(gcps, ties, match_ties, reference_ortho)
    obs_files = list(dict.fromkeys(os.fspath(f) for f in (gcps, ties) if f))
    grp.inputs += obs_files + [os.fspath(f) for f in (dem, reference_ortho) if isinstance(f, (str, os.PathLike))]
    warns: List[str] = []
    tab = _read_obs(paths, grp.keys, obs_files, grp.dem, gcp_files=[os.fspath(gcps)] if gcps else [], warns=warns)
    if check_plausibility and tab is not None:
        with collect_warnings(warns):
            check_observations(tab, grp.models, grp.sizes, grp.dem)
    outs = _declare_outputs(grp, out, overwrite, progress)          # every output declared before any work
    with outs, collect_warnings(warns):
        tab = _more_observations(grp, tab, reference_ortho, match_ties, steps)
        est = adjust_block(tab, grp.models, grp.dem, layout=grp.layout, solver=solver,
                           compare=(solver == "alternating"), progress=steps("adjust"))
        images_rep = _refit(grp, est, outs, steps("refit"))
        steps("seams")
        corrected = {k: corrected_model(est, k, grp.models[k]) for k in grp.keys}
        seams = seam_offsets(est.table, grp.models, corrected, grp.dem,
                             list(grp.layout.adjacent_pairs()) + _band_pairs(grp.layout, est.table))
        rep = finish_report(_report(grp, est, solver, images_rep, seams), warns)
        _write_outputs(outs, grp, est, seams, rep, steps("write"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep


def summary_lines(rep: Mapping[str, Any]) -> List[str]:
    """What ``gf4cal block-adjust`` prints and the QGIS log ends with: per stage its iterations and convergence,
    per seam its offsets, per band image its registration, the solver comparison."""
    lines = []
    for st in rep["stages"]:
        lines.append(f"{st['stage']} stage ({st['solver']}): {st['iterations']} iterations, "
                     f"{'converged' if st['converged'] else 'NOT converged'}, {st['n_tie_points']} tie points, "
                     f"reduced system {st['reduced_system_size']} unknowns, {st['n_rejected']} observations "
                     "rejected")
    for s in rep["seams"]:
        if s.get("n"):
            lines.append(f"seam {s['pair'][0]} | {s['pair'][1]}: mean offset {s['before']['mean_px']:.3f} px "
                         f"before, {s['after']['mean_px']:.3f} px after; largest along the overlap "
                         f"{s['before']['seam_max_px']:.3f} -> {s['after']['seam_max_px']:.3f} px "
                         f"({s['n']} tie points)")
    for k, v in rep["band_to_band"].items():
        if v["rms_px_after"] is not None:
            lines.append(f"band {k} vs {v['reference']}: tie RMS {v['rms_px_before']:.3f} -> "
                         f"{v['rms_px_after']:.3f} px")
    if "solver_comparison" in rep:
        c = rep["solver_comparison"]
        lines.append("solvers: " + "; ".join(f"{k} {v['iterations']} iterations" for k, v in c.items()
                                             if isinstance(v, dict))
                     + f"; largest prediction difference {c['max_prediction_difference_px']:.3g} px")
    return lines


def check_observations(tab, models: Mapping[str, Any], sizes: Mapping[str, Any], dem=None) -> None:
    """Every observation against its image, as ``refine`` checks GCPs (:mod:`gdal_gf4cal.plausibility`; issue 19):
    per image its GCP rows (:func:`~gdal_gf4cal.plausibility.check_gcps_against`, heights against ``dem``) and its
    tie measurements (:func:`~gdal_gf4cal.plausibility.check_measured_inside`). A refusal (GCPError) names the
    image and the override; points outside an image but inside its RPC's domain are used, with a warning."""
    rows = tab.rename(columns={"point_id": "id"})
    for k, t in rows.groupby("image_id", sort=False):
        gcp = (t["kind"] == "gcp").to_numpy()
        try:
            if gcp.any():
                check_gcps_against(models[k], t[gcp], sizes.get(k), dem=dem, what=f"GCPs of {k}")
            if (~gcp).any():
                check_measured_inside(models[k], t[~gcp], sizes.get(k), what=f"tie points of {k}",
                                      stray_fraction=STRAY_FRACTION)
        except BlockError:
            raise
        except GCPError as exc:
            raise BlockError(f"{k}: {exc}") from None


def _planar_rms(table, k, when) -> float:
    r = table[(table["image_id"] == k) & ~table["outlier"]]
    v = np.hypot(r[f"res_sample_{when}"].to_numpy(float), r[f"res_line_{when}"].to_numpy(float))
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")


def _max_difference(a, b) -> float:
    d = np.hypot(a["pred_sample_after"].to_numpy(float) - b["pred_sample_after"].to_numpy(float),
                 a["pred_line_after"].to_numpy(float) - b["pred_line_after"].to_numpy(float))
    return float(np.nanmax(d)) if np.isfinite(d).any() else float("nan")


def _band_pairs(layout, table) -> list:
    """Adjacent-CCD pairs of the other bands: band images whose reference images are adjacent and that share ties."""
    adj = set(layout.adjacent_pairs())
    ties = table[table["kind"] == "tie"]
    pts = ties.groupby("image_id")["point_id"].apply(set).to_dict()
    out = []
    bands = layout.band_images
    for a in bands:
        for b in bands:
            ra, rb = layout.images[a].reference, layout.images[b].reference
            if (ra, rb) in adj and pts.get(a, set()) & pts.get(b, set()):
                out.append((a, b))
    return out


def _band_to_band(table, layout) -> Dict[str, Any]:
    """Band-to-band registration: per band image, residual RMS of its tie rays shared with its reference image."""
    out = {}
    ties = table[(table["kind"] == "tie") & ~table["outlier"]]
    for b in layout.band_images:
        ref = layout.images[b].reference
        pb = set(ties.loc[ties["image_id"] == ref, "point_id"])
        r = ties[(ties["image_id"] == b) & ties["point_id"].isin(pb)]
        ent = {"reference": ref, "n": int(len(r))}
        for when in ("before", "after"):
            v = np.hypot(r[f"res_sample_{when}"].to_numpy(float), r[f"res_line_{when}"].to_numpy(float))
            v = v[np.isfinite(v)]
            ent[f"rms_px_{when}"] = float(np.sqrt(np.mean(v ** 2))) if v.size else None
        out[b] = ent
    return out


def _collect_from_ortho(paths, keys, order, models, reference, dem, progress):
    """GCPs collected against an orthophoto for every reference-band image (issue 7's matcher)."""
    tabs = []
    for i, k in enumerate(order):
        p = paths[keys.index(k)]
        W, H = _open_image(p)[0] or (512, 512)
        # dense enough for a cubic per CCD: about 8 x 8 windows per image (the matcher's default 256 px is for a
        # 6-parameter bias of a whole scene)
        spacing = int(max(32, min(256, min(W, H) // 8)))
        g = collect_gcps(p, models[k], os.fspath(reference), dem, spacing_px=spacing,
                         window_px=int(min(64, 2 * spacing)), progress=None)
        g = g[~g["outlier"].to_numpy(bool)] if "outlier" in g.columns else g
        g = g.assign(id=[f"O{k}_{j}" for j in g["id"]])
        tabs.append(from_gcps(g[["id", "lon", "lat", "h", "sample", "line", "role", "sigma"]], k))
        if progress:
            progress((i + 1) / len(order), f"GCPs of {k} from the reference ortho")
    import pandas as pd          # where used: at module top it slows every CLI start-up
    return pd.concat(tabs, ignore_index=True)


#: Overlap strips narrower than this (px) are matched with 16 px windows and a 6 px search.
NARROW_STRIP_PX = 64
#: Matching windows aimed at per image pair (the grid spacing follows the overlap's area, 8 to 64 px).
TIES_PER_PAIR = 200


def _match_ties(paths, keys, layout, models, dem, progress):
    """Tie points by raw-to-raw matching (adjacent CCDs; every band against its reference band)."""
    pairs = list(layout.adjacent_pairs()) + [(layout.images[b].reference, b) for b in layout.band_images]
    tabs = []
    for i, (a, b) in enumerate(pairs):
        pa, pb = paths[keys.index(a)], paths[keys.index(b)]
        # An MS overlap strip is ~50 px wide (200 pan px / 4): narrower than the default window plus its search
        # range, so narrow strips are matched with small windows; the spacing gives ~TIES_PER_PAIR windows.
        box, _ = overlap_region(pa, models[a], pb, models[b], dem, step_px=NARROW_STRIP_PX // 4)
        w, h = box[2] - box[0] - NARROW_STRIP_PX // 2, box[3] - box[1] - NARROW_STRIP_PX // 2
        kw: Dict[str, Any] = {"spacing_px": int(np.clip(np.sqrt(max(w, 1.0) * max(h, 1.0) / TIES_PER_PAIR), 8, 64))}
        if min(w, h) < NARROW_STRIP_PX:
            kw.update(window_px=16, search_px=6)
        t = match_ties(pa, models[a], pb, models[b], dem, ids=(a, b), **kw)
        if t is not None and len(t):
            t = t.copy()
            t["point_id"] = [f"M{i}_{p}" for p in t["point_id"]]
            tabs.append(t)
        if progress:
            progress((i + 1) / len(pairs), f"matched {a} and {b}")
    if not tabs:
        raise BlockError("raw-to-raw matching found no tie points; check the images overlap and have texture, or "
                         "give --ties")
    import pandas as pd          # where used: at module top it slows every CLI start-up
    return pd.concat(tabs, ignore_index=True)
