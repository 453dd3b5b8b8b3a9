"""Estimation of the pan-MS model from cell observations (METHODS §9 eqs. 14-17): stepwise (linear, piecewise,
jitter) or in reuse mode, with per-step statistics."""
from __future__ import annotations

import copy
from typing import Optional

import numpy as np

from ..estimation import Estimate, LinearProblem, Snooping, robust_fit, weighted_lsq
from ..progress import report
from ..stats import axis_stats, share_within
from .breaks import default_breaks
from .design import _blocks, _piece_orders, _piecewise_design, _set_values, _term_layout, _values, linear_design
from .jitter import _describe_jitter, _solve_jitter
from .model import (AXES, GF7_LOOK_TIME_S, GF7_MS_IFOV_RAD, GF7_MS_LINE_TIME_S, P_THRESHOLD_PX, PanMSError,
                    PanMSModel)
from .spectrum import spectrum_peaks

REUSE_MAX_RMS_PX = 0.1         # reuse mode: refuse a fit worse than this and ...
REUSE_MAX_FLOOR_RATIO = 3.0     # ... this many times the cells' noise floor (another camera's model), or ...
REUSE_MAX_OUTLIER_SHARE = 0.25  # ... with more of its cells rejected as blunders


def _snapshot(model: PanMSModel, name: str, terms) -> dict:
    return {"name": name, "terms": tuple(terms), "linear": model.linear.copy(),
            "piecewise": model.piecewise.copy(), "jitter": copy.deepcopy(model.jitter)}


def step_residuals(model: PanMSModel, snap: dict, sample, line, d_sample, d_line):
    """Residuals ``nabla - model`` (MS px) of the cells after one step (a :func:`_snapshot` of the model)."""
    m = PanMSModel(ms_size=model.ms_size, breaks=model.breaks, linear=snap["linear"], piecewise=snap["piecewise"],
                   jitter=snap["jitter"])
    ps, pl = m.predict(sample, line, terms=snap["terms"])
    return np.asarray(d_sample) - ps, np.asarray(d_line) - pl


def _step_stats(model, snap, c, inlier, line_time_s):
    rs, rl = step_residuals(model, snap, c["sample"], c["line"], c["d_sample"], c["d_line"])
    u = inlier & np.isfinite(rs) & np.isfinite(rl)
    w = u.astype(float)
    return {"step": snap["name"], "terms": list(snap["terms"]), "n_cells": int(u.sum()),
            "sample": axis_stats(rs[u]), "line": axis_stats(rl[u]),
            "rms_sample_px": axis_stats(rs[u])["rms"], "rms_line_px": axis_stats(rl[u])["rms"],
            "p_le_0.25": share_within(rs[u], rl[u], P_THRESHOLD_PX),
            "spectrum_peaks": {"sample": spectrum_peaks(c["line"], rs, w, line_time_s=line_time_s),
                               "line": spectrum_peaks(c["line"], rl, w, line_time_s=line_time_s)}}



def _cell_arrays(cells) -> dict:
    need = ("sample", "line", "d_sample", "d_line")
    missing = [c for c in need if c not in cells]
    if missing:
        raise PanMSError(f"the cell table lacks the columns {', '.join(missing)}")
    out = {c: np.asarray(cells[c], dtype=float) for c in need}
    n = out["sample"].size
    for c in ("sigma_sample", "sigma_line"):
        v = np.asarray(cells[c], dtype=float) if c in cells else np.full(n, np.nan)
        out[c] = np.where(np.isfinite(v) & (v > 0), v, np.nan)
    usable = np.asarray(cells["usable"], dtype=bool) if "usable" in cells else np.ones(n, bool)
    out["usable"] = usable & np.isfinite(out["d_sample"]) & np.isfinite(out["d_line"])
    return out


def _weights(c) -> np.ndarray:
    sig = np.stack([c["sigma_sample"], c["sigma_line"]], axis=1)
    med = np.nanmedian(sig) if np.isfinite(sig).any() else 1.0
    sig = np.where(np.isfinite(sig), np.maximum(sig, 0.25 * med), med)
    return np.where(c["usable"][:, None], 1.0 / sig ** 2, 0.0)


def _robust_step(a, y, w, usable, blocks, frozen, values, hint) -> Estimate:
    """A robust estimate of the one robust driver (high-breakdown start + data snooping) over the usable cells;
    NaN offsets (cells left out) enter as 0 with weight 0."""
    problem = LinearProblem(a, np.where(np.isfinite(y), y, 0.0), w, blocks=blocks, frozen=frozen, values=values,
                            hint=hint)
    return robust_fit(problem, norm=Snooping(4.0), start="lts", candidates=usable, n_subsets=200)


def _resolve_breaks(breaks, n_sub_ccds, reuse, W: int, H: int):
    """``(reuse model or None, sorted breakpoints)``: the reuse model's when reusing (after checking it fits this
    image), else the ones given, else equal sub-CCDs; :class:`PanMSError` for edges outside the image."""
    if reuse is not None and not isinstance(reuse, PanMSModel):
        reuse = PanMSModel.from_json(reuse)
    if reuse is not None:
        reuse.compatible_with((W, H), breaks)
        breaks = list(reuse.breaks)
    if breaks is None:
        breaks = default_breaks(W, n_sub_ccds)
    breaks = sorted(float(b) for b in breaks)
    if any(not (0.0 < b < W) for b in breaks):
        raise PanMSError(f"sub-CCD breakpoints {breaks} must lie inside the MS image (0..{W} px)")
    return reuse, breaks


def _new_model(c, W: int, H: int, breaks, reuse, times) -> PanMSModel:
    """The empty model with its ``info`` (cells, times, noise floor); :class:`PanMSError` without a usable cell."""
    usable = c["usable"]
    n_use, n_all = int(usable.sum()), usable.size
    if n_use == 0:
        raise PanMSError(f"no usable cell: all {n_all} cells are cloud, water or texture-less; register a clearer "
                         "scene and reuse its model with --reuse MODEL.json")
    model = PanMSModel(ms_size=(W, H), breaks=tuple(breaks), mode="solve" if reuse is None else "reuse")
    model.info = {"n_cells": n_all, "n_usable": n_use, "line_time_s": times[0], "look_time_s": times[1],
                  "ifov_rad": times[2],
                  "noise_floor_px": {"sample": _floor(c["sigma_sample"][usable]),
                                     "line": _floor(c["sigma_line"][usable])}}
    return model


def _solve_reuse(model, reuse, c, a, y, w, snaps, progress) -> PanMSModel:
    """Reuse mode (eq. 17): the reused model's piecewise term frozen, the linear term solved robustly from the
    sparse cells; refused when it does not fit (:func:`_check_reuse_fit`)."""
    model.piecewise = reuse.piecewise.copy()
    est = _robust_step(a, y, w, c["usable"], _blocks(model.n_sub_ccds), ["piecewise"], _values(model),
                       " (reuse mode: the linear term from the sparse cells)")
    _set_values(model, est.x)
    model.info["reused_from"] = reuse.info.get("source", "")
    snaps.append(_snapshot(model, "linear (reuse: piecewise term of the reused model)", ("linear", "piecewise")))
    model = _finish(model, c, snaps, est.outlier, model.info["line_time_s"], progress)
    _check_reuse_fit(model)
    return model


def _blunders(a, y, w, usable, blocks, notes) -> np.ndarray:
    """Blunders first, on the model that fits (linear + piecewise, robust: high-breakdown start + snooping), so
    that the sub-CCD structure the linear step cannot model is not mistaken for blunders; none tested when the
    cells are too few (a note says so)."""
    n_use = int(usable.sum())
    if n_use >= a.shape[2] // 2 + 3:
        return _robust_step(a, y, w, usable, blocks, ["linear_datum"], np.zeros(a.shape[2]),
                            " (blunder detection)").outlier
    notes.append(f"{n_use} usable cells for {a.shape[2] // 2} parameters per axis: too few to test for blunders")
    return np.zeros(usable.size, bool)


def _solve_stepwise(model, c, a, y, w, sn, jitter, snaps, progress) -> PanMSModel:
    """Eqs. 14-16: blunders, then the linear term on all cells, the piecewise term on what remains (the linear
    datum frozen), the jitter term on what remains; the terms the usable cells cannot support are dropped
    (:func:`_term_layout`, with notes)."""
    usable, m, W = c["usable"], model.n_sub_ccds, model.ms_size[0]
    keep, notes = _term_layout(c["sample"], c["line"], usable, model.breaks, W)
    model.info["notes"] = notes
    model.info["piece_orders"] = _piece_orders(keep, m)
    a, blocks = a[:, :, keep], _blocks(m, keep)
    x_full = np.zeros(keep.size)

    def put(x):
        x_full[keep] = x
        _set_values(model, x_full)
    outlier = _blunders(a, y, w, usable, blocks, notes)
    yy = np.where(np.isfinite(y), y, 0.0)
    w_in = np.where((usable & ~outlier)[:, None], w, 0.0)
    # Step 1 (eq. 14): linear on all cells (usable, not blunders).
    n_lin = int(keep[:6].sum())
    est = weighted_lsq(a[:, :, :n_lin].reshape(-1, n_lin), yy.ravel(), w_in.ravel(), blocks=_blocks(0, keep[:6]),
                       hint=" (linear term)")
    put(np.r_[est.x, np.zeros(a.shape[2] - n_lin)])
    snaps.append(_snapshot(model, "linear", ("linear",)))
    report(progress, 0.3, "pan-MS: piecewise term")
    # Step 2 (eq. 15): piecewise on what remains; the linear datum (constant, s) stays frozen (the pieces'
    # constant and linear terms duplicate it), the l terms are refined with it.
    if any(b.name != "linear_datum" for b in blocks):
        est = weighted_lsq(a.reshape(-1, a.shape[2]), yy.ravel(), w_in.ravel(), blocks=blocks,
                           frozen=["linear_datum"], values=_values(model)[keep], hint=" (piecewise term)")
        put(est.x)
    snaps.append(_snapshot(model, "piecewise", ("linear", "piecewise")))
    # Step 3 (eq. 16): jitter on what remains.
    report(progress, 0.6, "pan-MS: jitter term")
    if str(jitter) != "none":
        n_fixed = None if str(jitter) == "auto" else int(jitter)
        _solve_jitter(model, c, a, y, w, usable & ~outlier, blocks, n_fixed, sn, keep)
        info = model.info
        _describe_jitter(model, info["line_time_s"], info["look_time_s"], info["ifov_rad"])
        snaps.append(_snapshot(model, "jitter", ("linear", "piecewise", "jitter")))
    return _finish(model, c, snaps, outlier, model.info["line_time_s"], progress)


def estimate(cells, *, ms_size, breaks=None, n_sub_ccds: int = 3, jitter="auto", reuse=None,
             line_time_s: float = GF7_MS_LINE_TIME_S, look_time_s: float = GF7_LOOK_TIME_S,
             ifov_rad: float = GF7_MS_IFOV_RAD, progress=None) -> PanMSModel:
    """Solve METHODS §9's pan-MS registration model from cell observations, stepwise (eqs. 14-16) or in reuse
    mode (eq. 17).

    Parameters
    ----------
    cells : DataFrame or mapping of arrays
        ``sample, line`` (MS cell centre, GDAL convention), ``d_sample, d_line`` (nabla, MS px), optional
        ``sigma_sample, sigma_line`` (weights ``1/sigma^2``) and ``usable`` (cells mostly cloud/water/texture-less
        are left out of the estimate but keep their residuals).
    ms_size : (width, height) of the MS image.
    breaks : list of MS samples of the sub-CCD edges; default ``n_sub_ccds`` equal pieces of the MS width.
    jitter : ``"auto"`` (components while significant, false-alarm probability < 1e-3, at most what the cell
        rows resolve), ``"none"`` or an int (that many per axis where the data resolve them, fewer with a note;
        more than the cell rows resolve, :func:`~gdal_gf4cal.panms.jitter.supported_sines`, is refused).
    reuse : :class:`PanMSModel` or path of its JSON: keep its piecewise term, solve only the linear term.
    line_time_s, look_time_s, ifov_rad : MS line period, pan-MS look-time difference and MS IFOV, to report the
        jitter in Hz and the attitude jitter it implies (gain ``2 |sin(pi f dt)|``).

    Returns
    -------
    PanMSModel
        ``steps``: per step RMS per axis about zero, P(<= 0.25 px) over usable cells, residual spectrum peaks.

    Raises
    ------
    PanMSError
        No usable cell, a reuse model of another camera, bad breakpoints, more jitter sines than the rows resolve.
    """
    c = _cell_arrays(cells)
    W, H = int(ms_size[0]), int(ms_size[1])
    reuse, breaks = _resolve_breaks(breaks, n_sub_ccds, reuse, W, H)
    model = _new_model(c, W, H, breaks, reuse, (line_time_s, look_time_s, ifov_rad))
    w = _weights(c)
    y = np.stack([c["d_sample"], c["d_line"]], axis=1)
    sn, ln = model.normalise(c["sample"], c["line"])
    a = np.concatenate([linear_design(sn, ln), _piecewise_design(c["sample"], breaks, W)], axis=2)
    snaps = [_snapshot(model, "before", ())]
    report(progress, 0.05, "pan-MS: linear term")
    if reuse is not None:
        return _solve_reuse(model, reuse, c, a, y, w, snaps, progress)
    return _solve_stepwise(model, c, a, y, w, sn, jitter, snaps, progress)


def _finish(model, c, snaps, outlier, line_time_s, progress):
    """Step statistics over the same cells (usable, not flagged as blunders by the last robust step)."""
    inlier = c["usable"] & ~outlier
    model.steps = [_step_stats(model, sn, c, inlier, line_time_s) for sn in snaps]
    model.info["n_outliers"] = int(np.sum(outlier & c["usable"]))
    model.cell_outlier = outlier
    model.snapshots = snaps
    report(progress, 1.0, "pan-MS: model solved")
    return model


def _check_reuse_fit(model) -> None:
    """Reuse mode (METHODS §9 eq. 17) refuses a model that does not fit: the sparse cells' RMS after the linear
    term must stay within ``REUSE_MAX_FLOOR_RATIO`` x their noise floor or below ``REUSE_MAX_RMS_PX``, with at
    most ``REUSE_MAX_OUTLIER_SHARE`` of them rejected as blunders (else the robust fit kept the half that fits,
    as on scene seed 14 / camera 21 with scene seed 11 / camera 9's model). A model of another camera of the
    same design (same size and layout, other sub-CCD truth) otherwise passes every layout
    check and leaves ~0.2 px with P(<= 0.25 px) ~ 55 %."""
    st, fl = model.steps[-1], model.info["noise_floor_px"]
    n_out, n_use = model.info["n_outliers"], model.info["n_usable"]
    if n_out > REUSE_MAX_OUTLIER_SHARE * n_use:
        raise PanMSError(f"the reuse model does not fit this scene: {n_out} of {n_use} cells rejected as blunders; "
                         "reuse only a model of the same camera, or register this scene without --reuse")
    for ax in AXES:
        rms, floor = st[f"rms_{ax}_px"], fl.get(ax)
        if rms > REUSE_MAX_RMS_PX and (floor is None or rms > REUSE_MAX_FLOOR_RATIO * floor):
            raise PanMSError(f"the reuse model does not fit this scene: {ax} RMS {rms:.3f} px after the linear "
                             f"term (cell noise {floor or float('nan'):.3f} px); reuse only a model of the same "
                             "camera, or register this scene without --reuse")


def _floor(sig) -> Optional[float]:
    sig = sig[np.isfinite(sig)]
    return float(np.sqrt(np.mean(sig ** 2))) if sig.size else None
