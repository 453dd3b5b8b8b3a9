"""Accuracy statistics (METHODS §6).

Per axis: ``mean``, ``rms`` = sqrt(mean(x²)), ``std`` = standard deviation about the mean (population, so
rms² = mean² + std²; the papers' "RMSE", e.g. seed 000's Table 3: mean 2.52, RMS 9.90, RMSE 9.57; named ``std``
so that it is not read as an error), ``max`` = max |x|.
Planar: CE90 (90th percentile of radial error), LE90 for height, share of points within a threshold.
Internal (relative) accuracy: remove a rotation + translation fitted on the points (seed 000 eq. 8).
Residuals are always ``measured - predicted``.

One accuracy-report shape (:func:`accuracy_by_role`), used by every estimator's report::

    {control|check: {n_outliers, before|after: {n, sample|line: {mean, rms, std, max}, planar: {n, rms, mean,
     max, ce90}, ce90_m}}}

Column names of residual tables: ``res_{sample,line}_{before,after}`` (measured - predicted, px) and
``pred_{sample,line}_{before,after}``: *before* is the model as given (the RPC), *after* the estimated one.
A bare ``pred_sample`` (look-angle table, RPC accuracy report) always means the prediction of the model the
table reports on, i.e. *after* for an estimate, the RPC for an accuracy assessment; new code writes the
explicit ``_before`` / ``_after`` names.
"""
from __future__ import annotations

from typing import Dict, NamedTuple, Optional, Tuple

import numpy as np

from .errors import DegenerateGeometryError
from .geodesy import radii_of_curvature


def axis_stats(residuals) -> Dict[str, float]:
    """``{n, mean, rms, std, max}`` of one axis of residuals (NaN ignored; all NaN when empty)."""
    r = np.asarray(residuals, dtype=float).ravel()
    r = r[np.isfinite(r)]
    if r.size == 0:
        return {"n": 0, "mean": float("nan"), "rms": float("nan"), "std": float("nan"), "max": float("nan")}
    mean = float(np.mean(r))
    return {"n": int(r.size), "mean": mean, "rms": float(np.sqrt(np.mean(r * r))),
            "std": float(np.sqrt(np.mean((r - mean) ** 2))), "max": float(np.max(np.abs(r)))}


def planar_stats(res_sample, res_line) -> Dict[str, float]:
    """Planar (radial) statistics in the residuals' unit: ``rms``, ``mean``, ``max``, ``p90`` (CE90)."""
    r = np.hypot(np.asarray(res_sample, dtype=float), np.asarray(res_line, dtype=float)).ravel()
    r = r[np.isfinite(r)]
    if r.size == 0:
        return {"n": 0, "rms": float("nan"), "mean": float("nan"), "max": float("nan"), "ce90": float("nan")}
    return {"n": int(r.size), "rms": float(np.sqrt(np.mean(r * r))), "mean": float(np.mean(r)),
            "max": float(np.max(r)), "ce90": float(np.percentile(r, 90))}


def ce90(dx, dy=None) -> float:
    """CE90: 90th percentile of the planar error ``hypot(dx, dy)`` (or of ``dx`` if it is already radial)."""
    r = np.abs(np.asarray(dx, dtype=float)) if dy is None else np.hypot(np.asarray(dx, float), np.asarray(dy, float))
    r = r[np.isfinite(r)]
    return float(np.percentile(r, 90)) if r.size else float("nan")


def le90(dh) -> float:
    """LE90: 90th percentile of the absolute height error."""
    return ce90(dh)


def share_within(res_sample, res_line, threshold_px: float) -> float:
    """Share of points whose planar residual is <= ``threshold_px`` (seed 004's P(<= 0.25 px))."""
    r = np.hypot(np.asarray(res_sample, dtype=float), np.asarray(res_line, dtype=float)).ravel()
    r = r[np.isfinite(r)]
    return float(np.mean(r <= threshold_px)) if r.size else float("nan")


def residual_report(res_sample, res_line, *, ground_m_per_px: Optional[float] = None) -> Dict[str, object]:
    """Per-axis (``line``, ``sample``) stats and ``planar`` stats; ``ce90_m`` when a GSD is given (METHODS §6).

    A point counts only where both residuals are finite, so every block describes the same ``n`` points.
    """
    rs, rl = np.broadcast_arrays(np.asarray(res_sample, dtype=float).ravel(), np.asarray(res_line, dtype=float).ravel())
    both = np.isfinite(rs) & np.isfinite(rl)
    res_sample, res_line = rs[both], rl[both]
    report = {"n": int(np.count_nonzero(both)),
              "line": axis_stats(res_line), "sample": axis_stats(res_sample),
              "planar": planar_stats(res_sample, res_line)}
    if ground_m_per_px is not None:
        report["ce90_m"] = report["planar"]["ce90"] * float(ground_m_per_px)
    return report


#: The name DESIGN.md gives the per-axis + planar report (METHODS §6).
accuracy_report = residual_report


def _none_if_nan(x):
    x = float(x)
    return x if np.isfinite(x) else None


def model_jacobian(model, lon, lat, h) -> np.ndarray:
    """``d(sample, line)/d(lon, lat, h)`` (..., 2, 3) from ``model.project_jacobian`` or central differences."""
    if hasattr(model, "project_jacobian"):
        return np.asarray(model.project_jacobian(lon, lat, h), dtype=float)
    steps = (1e-6, 1e-6, 1.0)
    cols = []
    for k, st in enumerate(steps):
        args_p = [lon, lat, h]
        args_m = [lon, lat, h]
        args_p[k] = args_p[k] + st
        args_m[k] = args_m[k] - st
        sp, lp = model.project(*args_p)
        sm, lm = model.project(*args_m)
        cols.append(np.stack([(np.asarray(sp) - sm) / (2 * st), (np.asarray(lp) - lm) / (2 * st)], axis=-1))
    return np.stack(cols, axis=-1)


def ground_jacobian(rpc, lon, lat, h) -> np.ndarray:
    """``d(sample, line)/d(lon, lat)`` (..., 2, 2) at fixed height, as :func:`ground_offsets_m` uses it."""
    return model_jacobian(rpc, np.asarray(lon, float), np.asarray(lat, float), np.asarray(h, float))[..., :2]


def ground_offsets_m(rpc, lon, lat, h, dsample, dline, *, jacobian=None) -> Tuple[np.ndarray, np.ndarray]:
    """East/north ground offsets (m) equivalent to image offsets ``(dsample, dline)`` (px) at ``(lon, lat, h)``.

    Uses the RPC ground Jacobian ``d(s, l)/d(lon, lat)`` at fixed height; for CE90 of image residuals (METHODS §6).
    ``jacobian``: that Jacobian at these points when already known (:func:`ground_jacobian`), e.g. for the
    before and after residuals of the same points.
    """
    lon, lat, h = (np.asarray(a, dtype=float) for a in (lon, lat, h))
    jac = ground_jacobian(rpc, lon, lat, h) if jacobian is None else jacobian
    rhs = np.stack([np.asarray(dsample, float), np.asarray(dline, float)], axis=-1)[..., None]
    with np.errstate(all="ignore"):
        dll = np.linalg.solve(jac, rhs)[..., 0]
    phi = np.radians(lat)
    rn, rm = radii_of_curvature(lat)
    east = np.radians(dll[..., 0]) * (rn + h) * np.cos(phi)
    north = np.radians(dll[..., 1]) * (rm + h)
    return east, north


def _ground_offsets_of(table, rpc):
    """``ground_offsets(mask, res_sample, res_line)`` of :func:`accuracy_by_role` through ``rpc``'s ground Jacobian
    at the table's ``lon, lat, h`` (computed once per row selection: before and after share it)."""
    lon, lat, h = (table[c].to_numpy(float) for c in ("lon", "lat", "h"))
    jac: dict = {}

    def ground(sel, rs, rl):
        key = sel.tobytes()
        if key not in jac:
            jac.clear()
            jac[key] = ground_jacobian(rpc, lon[sel], lat[sel], h[sel])
        return ground_offsets_m(rpc, lon[sel], lat[sel], h[sel], rs, rl, jacobian=jac[key])
    return ground


def accuracy_by_role(table, rpc=None, *, ground_offsets=None, ground_m_per_px: Optional[float] = None,
                     roles=("control", "check")) -> Dict[str, object]:
    """The one accuracy report per role, before and after an estimate (METHODS §6); see the module docstring.

    Parameters
    ----------
    table : DataFrame
        Columns ``role``, ``outlier`` (bool; flagged points are left out of both before and after, and counted
        in ``n_outliers``) and ``res_{sample,line}_{before,after}`` (px; a missing ``after`` pair is skipped).
    rpc : sensor model, optional
        ``ce90_m`` of the image residuals taken to the ground through its ground Jacobian (:func:`ground_offsets_m`)
        at the table's ``lon, lat, h``.
    ground_offsets : callable, optional
        Or ``ground_offsets(mask, res_sample, res_line) -> (east_m, north_m)`` for the rows ``mask``.
    ground_m_per_px : float, optional
        Otherwise a ground scale (GSD) for ``ce90_m``; with neither ``ce90_m`` is None.
    """
    if rpc is not None and ground_offsets is None:
        ground_offsets = _ground_offsets_of(table, rpc)
    role = table["role"].astype(str).to_numpy()
    outl = table["outlier"].to_numpy(bool) if "outlier" in table.columns else np.zeros(len(table), bool)
    out: Dict[str, object] = {}
    for name in roles:
        sel = (role == name) & ~outl
        entry: Dict[str, object] = {"n_outliers": int(((role == name) & outl).sum())}
        for when in ("before", "after"):
            if f"res_sample_{when}" not in table.columns:
                continue
            rs = table[f"res_sample_{when}"].to_numpy(float)[sel]
            rl = table[f"res_line_{when}"].to_numpy(float)[sel]
            st: Dict[str, object] = {"n": int(sel.sum()),
                                     "line": {k: _none_if_nan(v) for k, v in axis_stats(rl).items() if k != "n"},
                                     "sample": {k: _none_if_nan(v) for k, v in axis_stats(rs).items() if k != "n"},
                                     "planar": {k: (_none_if_nan(v) if k != "n" else v)
                                                for k, v in planar_stats(rs, rl).items()}}
            ce = None
            if sel.any() and ground_offsets is not None:
                e, n_ = ground_offsets(sel, rs, rl)
                ce = _none_if_nan(ce90(e, n_))
            elif sel.any() and ground_m_per_px is not None:
                ce = _none_if_nan(ce90(rs, rl) * float(ground_m_per_px))
            st["ce90_m"] = ce
            entry[when] = st
        out[name] = entry
    return out


def fit_rotation_translation(sample_meas, line_meas, sample_pred, line_pred):
    """Least-squares rotation ``theta`` and translation ``(ds, dl)`` mapping predicted onto measured (eq. 8).

    Model: ``s_meas = cos(t)(s_pred - cs) - sin(t)(l_pred - cl) + cs + ds`` and likewise for the line, about
    the centroid ``(cs, cl)`` of the predicted points (solved in closed form, Procrustes without scale).
    Returns ``theta`` (rad), ``ds``, ``dl`` and the residuals after removing them.
    """
    sm, lm, sp, lp = (np.asarray(a, dtype=float).ravel() for a in (sample_meas, line_meas, sample_pred, line_pred))
    ok = np.isfinite(sm) & np.isfinite(lm) & np.isfinite(sp) & np.isfinite(lp)
    if np.count_nonzero(ok) < 2:
        raise DegenerateGeometryError("internal accuracy needs at least 2 points (rotation + translation)")
    cs, cl = sp[ok].mean(), lp[ok].mean()
    ms, ml = sm[ok].mean(), lm[ok].mean()
    xs, ys = sp[ok] - cs, lp[ok] - cl
    xm, ym = sm[ok] - ms, lm[ok] - ml
    theta = float(np.arctan2(np.sum(xs * ym - ys * xm), np.sum(xs * xm + ys * ym)))
    c, s = np.cos(theta), np.sin(theta)
    ds, dl = ms - cs, ml - cl
    s_fit = c * (sp - cs) - s * (lp - cl) + cs + ds
    l_fit = s * (sp - cs) + c * (lp - cl) + cl + dl
    return {"theta_rad": theta, "ds": float(ds), "dl": float(dl), "res_sample": sm - s_fit, "res_line": lm - l_fit}


def internal_accuracy(sample_meas, line_meas, sample_pred, line_pred) -> Dict[str, object]:
    """Internal (relative) accuracy, seed 000 eq. 8: residuals after removing rotation + translation.

    Returns ``{"theta_rad", "ds", "dl", "line": {...}, "sample": {...}, "planar": {...}}`` with per-axis
    mean/rms/std/max in pixels.
    """
    fit = fit_rotation_translation(sample_meas, line_meas, sample_pred, line_pred)
    out = {"theta_rad": fit["theta_rad"], "ds": fit["ds"], "dl": fit["dl"]}
    out.update(residual_report(fit["res_sample"], fit["res_line"]))
    return out


def remove_low_order(sample_meas, line_meas, sample_pred, line_pred):
    """Residuals after removing rotation + translation (what :func:`internal_accuracy` reports on)."""
    fit = fit_rotation_translation(sample_meas, line_meas, sample_pred, line_pred)
    return fit["res_sample"], fit["res_line"]


class GroupedMean(NamedTuple):
    """Result of :func:`grouped_trimmed_mean`: ``mean, sigma`` (groups, axes), ``median`` (groups, axes), ``n``
    (groups,) values kept; NaN / 0 for empty groups."""

    mean: np.ndarray
    sigma: np.ndarray
    median: np.ndarray
    n: np.ndarray


def _grouped_median(g: np.ndarray, v: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Median of ``v`` (1-D) per group ``g`` (ints in ``[0, len(counts))``), NaN for empty groups; vectorised."""
    order = np.lexsort((v, g))
    vs = v[order]
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    c = counts
    lo = np.clip(start + (c - 1) // 2, 0, max(vs.size - 1, 0))
    hi = np.clip(start + c // 2, 0, max(vs.size - 1, 0))
    if vs.size == 0:
        return np.full(c.size, np.nan)
    return np.where(c > 0, 0.5 * (vs[lo] + vs[hi]), np.nan)


def grouped_trimmed_mean(groups, values, n_groups: int, *, k: float = 3.0, sigma=None) -> GroupedMean:
    """Robust mean per group: the mean of the values within ``k`` robust standard deviations (1.4826 MAD) of the
    group's median on every axis (a MAD-trimmed mean about the median), vectorised over all groups.

    ``groups`` ints in ``[0, n_groups)``, ``values`` ``(N,)`` or ``(N, axes)``. ``sigma`` (optional, ``(N,)``):
    each value's own precision; the returned ``sigma`` (standard error of each mean) is the larger of the kept
    values' spread over sqrt(n) and their root-mean-square precision over sqrt(n) (a group of nearly equal values
    does not claim more than its members' precision allows).
    """
    g = np.asarray(groups, dtype=np.int64).ravel()
    v = np.asarray(values, dtype=float)
    v = v if v.ndim == 2 else v.reshape(-1, 1)          # (N, axes), also when N == 0
    G, A = int(n_groups), v.shape[1]
    counts = np.bincount(g, minlength=G)
    med = np.column_stack([_grouped_median(g, v[:, a], counts) for a in range(A)])
    dev = np.abs(v - med[g])
    mad = np.column_stack([_grouped_median(g, dev[:, a], counts) for a in range(A)])
    thr = k * 1.4826 * mad
    keep = np.all(dev <= thr[g] + 1e-12, axis=1)
    gk, vk = g[keep], v[keep]
    n = np.bincount(gk, minlength=G)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.column_stack([np.bincount(gk, vk[:, a], minlength=G) for a in range(A)]) / n[:, None]
        ss = np.column_stack([np.bincount(gk, (vk[:, a] - mean[gk, a]) ** 2, minlength=G) for a in range(A)])
        se = np.sqrt(ss / np.maximum(n - 1, 1)[:, None] / n[:, None])
        if sigma is not None:
            s2 = np.bincount(gk, np.asarray(sigma, dtype=float).ravel()[keep] ** 2, minlength=G)
            se = np.maximum(se, np.sqrt(s2 / n / n)[:, None])
    se[n < 2] = np.nan if sigma is None else se[n < 2]
    mean[n == 0] = np.nan
    se[n == 0] = np.nan
    return GroupedMean(mean, se, med, n)
