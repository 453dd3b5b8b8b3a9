"""Estimating an image-space compensation from GCPs (METHODS §4): :func:`fit_compensation` on the one robust driver.

The two image axes are estimated separately (each with its own terms) from the same points;
:class:`CompensationProblem` presents them to :func:`gdal_gf4cal.estimation.robust_fit` as one problem of two
observations per GCP, with per-axis degrees of freedom (``Estimate.axis_dof``) and, with little redundancy, one
sigma pooled over both axes.
"""
from __future__ import annotations

import math
from typing import Any, Optional, Sequence, Tuple

import numpy as np

from ..errors import DegenerateGeometryError, GCPError
from ..estimation import Estimate, Snooping, robust_fit, subset_count, weighted_lsq
from ..estimation.lsq import NORMAL_CONDITION, gram, weighted_lsq_many
from ..threads import blas_serial
from .model import CompensationModel, CompensationResult, _monomials
from .outputs import check_point_warnings

__all__ = ["fit_compensation", "CompensationProblem"]

#: Data-snooping note when the rule would leave no redundancy.
_TOO_MANY = "too many GCPs look like blunders for a robust estimate; all control points kept"


def _frame_from_rpc(rpc) -> Tuple[float, float, float, float]:
    try:
        # RPC00B offsets are raw (first pixel centre at 0); GDAL convention adds half a pixel.
        return (float(rpc.samp_off) + 0.5, float(abs(rpc.samp_scale)) or 1.0,
                float(rpc.line_off) + 0.5, float(abs(rpc.line_scale)) or 1.0)
    except AttributeError:
        return (0.0, 1.0, 0.0, 1.0)


def _table(gcps):
    import pandas as pd              # ~1 s to import: only when first needed (CLI, QGIS start-up)
    if isinstance(gcps, pd.DataFrame):
        tab = gcps.reset_index(drop=True)            # a copy: the caller's table is never changed
    elif isinstance(gcps, dict):
        tab = pd.DataFrame(gcps)
    else:
        raise GCPError("GCPs must be a table (GeoDataFrame/DataFrame) with columns lon, lat, h, sample, line")
    missing = [c for c in ("lon", "lat", "sample", "line") if c not in tab.columns]
    if missing:
        raise GCPError(f"GCP table lacks column(s) {', '.join(missing)}; expected id, lon, lat, h, sample, line, role")
    if not isinstance(gcps, pd.DataFrame):
        tab = tab.reset_index(drop=True)
    new = {}                         # the columns set, by one _set_columns (one insertion each cost more)
    if "id" not in tab.columns:
        new["id"] = [str(i + 1) for i in range(len(tab))]
    new["role"], roles = _normalised_labels(tab["role"] if "role" in tab.columns else
                                            pd.Series("control", index=tab.index, dtype=object))
    bad = sorted(roles - {"control", "check"})
    if bad:
        raise GCPError(f"GCP role must be 'control' or 'check', found {bad}")
    new["sigma"] = (tab["sigma"].astype(float).fillna(1.0) if "sigma" in tab.columns else
                    pd.Series(1.0, index=tab.index))
    if (new["sigma"] <= 0).any():
        raise GCPError("GCP sigma must be > 0 px")
    if "h" not in tab.columns:
        new["h"] = np.full(len(tab), np.nan)
    return _set_columns(tab, new)


def _normalised_labels(col):
    """``(col.fillna("control").astype(str).str.strip().str.lower(), the set of its values)`` computed once per
    distinct value (a role column of 10,000 GCPs holds one or two): pandas' string methods cost more than the
    robust fit."""
    import pandas as pd              # ~1 s to import: only when first needed (CLI, QGIS start-up)
    codes, uniques = pd.factorize(col)                                   # missing values: code -1
    labels = np.array([str(u).strip().lower() for u in uniques] + ["control"], dtype=object)
    present = set(labels[:-1]) | ({"control"} if (codes < 0).any() else set())
    return pd.Series(labels[codes], index=col.index, dtype=object), present


def _solve_axis(a, y, w, prior=None, solver: str = "svd") -> Tuple[np.ndarray, np.ndarray, Any]:
    """Weighted LS of one axis through :func:`gdal_gf4cal.estimation.weighted_lsq` (METHODS §4): returns
    ``(coef, N^-1, estimate)`` for weights ``w`` (zeros drop a row; their residuals are still computed and
    normalised with the a-priori weights ``prior``)."""
    est = weighted_lsq(a, y, w, prior=prior, apriori=True, solver=solver)
    return est.x, est.cov, est

def _check_rank(a_list, terms, model: CompensationModel, n_ctrl: int) -> float:
    """Raise DegenerateGeometryError if the control layout does not determine the model over the image.

    Two tests per axis: the column-equilibrated design is (numerically) rank deficient, or GCP noise would be
    amplified more than ``_MAX_AMPLIFICATION`` times at the image corners (u, v = +-1), e.g. GCPs spread over one
    pixel in line for a model with a line drift. Returns the worst condition number.
    """
    worst = 1.0
    amp = 0.0
    corners = np.array([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [0.0, 0.0]])
    for k, a in enumerate(a_list):
        cond, n_inv = _condition(a)
        worst = max(worst, cond)
        if terms is not None and math.isfinite(cond) and cond < 1e8:
            q = _monomials(terms[k], corners[:, 0], corners[:, 1])
            amp = max(amp, float(np.sqrt(np.max(np.einsum("ij,jk,ik->i", q, n_inv, q)))))
    if worst > 1e8 or amp > _MAX_AMPLIFICATION:
        hint = {"translation": "", "shift-drift": " (both axes need GCPs at different lines and samples)",
                "affine": " (the GCPs are collinear or too close together)",
                "poly2": " (the GCPs lie on one line or conic, or too close together)",
                "detector-poly": " (too few distinct detector positions)"}[model.name]
        raise DegenerateGeometryError(
            f"the {n_ctrl} control GCPs do not determine model {model.label!r}{hint}; spread GCPs over the image "
            f"or choose a simpler model")
    return worst


def _condition(a) -> Tuple[float, np.ndarray]:
    """``(condition number of the column-equilibrated a, pinv(a^T a))``: from the eigenvalues of the small normal
    matrix when that is clearly well conditioned (below :data:`~gdal_gf4cal.estimation.lsq.NORMAL_CONDITION`,
    where its squared condition loses nothing; one ``A^T A`` instead of an SVD of the n x p design), else from the
    SVD of the design."""
    n_mat = gram(a, a)
    d = np.sqrt(np.diag(n_mat))
    if np.all(d > 0):
        ev = np.linalg.eigvalsh(n_mat / np.outer(d, d))
        if ev[0] > 0 and math.sqrt(ev[-1] / ev[0]) <= NORMAL_CONDITION:
            return math.sqrt(ev[-1] / ev[0]), np.linalg.pinv(n_mat, hermitian=True)
    sv = np.linalg.svd(a / np.maximum(np.linalg.norm(a, axis=0), 1e-300), compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    return cond, np.linalg.pinv(n_mat, hermitian=True)


def _axis_designs(a_s, a_l, mask, terms):
    """``(designs, terms)`` of the axes on the rows of ``mask`` for :func:`_check_rank`: one when both axes have the
    same design (the same terms: the same condition and amplification)."""
    if a_l is a_s:
        return [a_s[mask]], terms[:1]
    return [a_s[mask], a_l[mask]], terms


#: Largest tolerated amplification of GCP noise at the image corners before a layout counts as degenerate.
_MAX_AMPLIFICATION = 1000.0


class CompensationProblem:
    """The control GCPs of a compensation as a problem of the robust driver (its protocol: ``n_points``, ``k``,
    ``n_params``, ``min_points``, ``fit``, ``redundancy``, ``start_design``): per point a sample and a line
    observation, the two axes solved separately (:func:`_normalised`; ``parts`` keeps its last result).
    ``solver``: ``"normal"`` for the robust iterations (:func:`_robust_set`), ``"svd"`` for the final estimate
    and its covariance (:func:`~gdal_gf4cal.estimation.solve_normal_scaled`). The LTS start takes its ``normal``
    evaluation (:func:`~gdal_gf4cal.estimation.high_breakdown_start`; the same results, 3x less CPU at 10,000
    GCPs), on the shared design ``(n, q)`` when both axes have the same terms (the same start as the
    block-diagonal one, at the cost of one axis)."""

    start_normal = True

    def __init__(self, a_s, a_l, y_s, y_l, w0, min_points: int, solver: str = "svd"):
        self.a_s, self.a_l, self.y_s, self.y_l, self.w0 = a_s, a_l, y_s, y_l, w0
        self.solver = solver
        self.n_points, self.k, self.n_params = len(w0), 2, a_s.shape[1] + a_l.shape[1]
        self.min_points = int(min_points)
        self.parts: tuple = ()

    def redundancy(self, mask) -> int:
        return int(np.count_nonzero(mask)) - max(self.a_s.shape[1], self.a_l.shape[1])

    def start_design(self, idx):
        if self.a_l is self.a_s:         # the same terms on both axes: the start's shared design (one axis' cost)
            return self.a_s[idx], np.stack([self.y_s[idx], self.y_l[idx]], axis=1), self.w0[idx]
        p_s = self.a_s.shape[1]
        design = np.zeros((idx.size, 2, self.n_params))
        design[:, 0, :p_s], design[:, 1, p_s:] = self.a_s[idx], self.a_l[idx]
        return (design, np.stack([self.y_s[idx], self.y_l[idx]], axis=1),
                np.repeat(self.w0[idx, None], 2, axis=1))

    def fit(self, point_weights) -> Estimate:
        used = np.asarray(point_weights) > 0
        *parts, vs, vl = _normalised(self.a_s, self.a_l, self.y_s, self.y_l, self.w0, used, self.solver)
        self.parts = norm_s, norm_l, cs, cl, ns, nl, sig_s, sig_l, red, dof = tuple(parts)
        p_s = cs.size
        cov = np.zeros((self.n_params, self.n_params))
        cov[:p_s, :p_s], cov[p_s:, p_s:] = sig_s ** 2 * ns, sig_l ** 2 * nl
        res = np.stack([vs, vl], axis=1).ravel()
        return Estimate(names=[f"x{i}" for i in range(self.n_params)], x=np.concatenate([cs, cl]), cov=cov,
                        sigma0=max(sig_s, sig_l), dof=red, redundancy=np.full(res.size, np.nan), residuals=res,
                        normalised=np.stack([norm_s, norm_l], axis=1).ravel(),
                        weights=np.repeat(np.where(used, self.w0, 0.0), 2), axis_dof=tuple(dof))


def fit_compensation(rpc, gcps, model="affine", *, order: Optional[int] = None, along: Optional[str] = None,
                     ccd_axis: str = "sample", dem=None, frame: Optional[Sequence[float]] = None,
                     robust: bool = True, outlier_threshold: float = 4.0, max_iter: int = 20,
                     leave_one_out: bool = False) -> CompensationResult:
    """Estimate an image-space correction of ``rpc`` from GCPs (METHODS §4).

    Parameters
    ----------
    rpc : RPCModel or any object with ``project(lon, lat, h) -> (sample, line)`` (GDAL pixel convention)
    gcps : GeoDataFrame / DataFrame
        Columns ``lon, lat, h`` (ellipsoidal m), ``sample, line`` (GDAL convention), optional ``id``, ``role``
        (``control`` points are estimated from, ``check`` points only evaluated; default all control) and
        ``sigma`` (px, relative weights).
    model : str or CompensationModel
        ``translation`` (min 1 GCP), ``shift-drift`` (2), ``affine`` (3), ``poly2`` (6), ``detector-poly``
        (``order`` + 1 with the default ``along='translation'``).
    dem : DEM, optional
        Fills missing heights (``h`` NaN) with ``dem.height(lon, lat)``.
    frame : (s0, ss, l0, ls), optional
        Normalisation of image coordinates; default from the RPC offsets and scales.
    robust : bool
        Robust estimation (the one driver, :func:`gdal_gf4cal.estimation.robust_fit`): a high-breakdown start,
        then blunders are flagged while their normalised residual (residual / its standard deviation, Baarda's
        w) exceeds ``outlier_threshold`` (:class:`~gdal_gf4cal.estimation.Snooping`) and left out of the
        estimate. Needs a redundancy of 2; with less it is skipped.
    outlier_threshold : float
        Critical normalised residual for a large redundancy (a standard-normal quantile); with few redundant
        observations it is raised to the Student-t quantile of the same probability, because sigma is estimated
        from the same GCPs (the report's ``notes`` say so).
    leave_one_out : bool
        Also compute leave-one-out residuals of each control point (``res_*_loo``; exact for linear LS).

    Returns
    -------
    CompensationResult

    Raises
    ------
    GCPError
        Fewer control GCPs than the model needs, missing columns or heights.
    DegenerateGeometryError
        The control layout does not determine the model (e.g. collinear GCPs for ``affine``).
    """
    if not isinstance(model, CompensationModel):
        model = CompensationModel.from_name(model, order=order, along=along, ccd_axis=ccd_axis)
    tab = _table(gcps)
    _fill_heights(tab, dem)
    fr = tuple(float(x) for x in (frame if frame is not None else _frame_from_rpc(rpc)))
    pred = _predict(rpc, tab)
    problem, ctrl, cond = _problem(tab, model, fr, pred)
    snoop = Snooping(outlier_threshold, too_many=_TOO_MANY)
    est, used, start_out, iterations, notes = _estimate(problem, ctrl, model, robust, snoop, max_iter)
    norm_s, norm_l, cs, cl, ns, nl, sig_s, sig_l, red, dof = problem.parts
    outlier = ~used & ctrl
    if robust and red >= 2:
        # Check points are never in the estimate; flag those that are blunders by the same test.
        outlier |= (~ctrl) & snoop.exceeds(est, len(tab), 2)
        crit = float(snoop.critical(est, 2).max())          # the smaller dof's (wider) threshold
        if crit > 1.05 * outlier_threshold:
            notes.append(f"few redundant observations: blunder threshold raised from {outlier_threshold:g} to "
                         f"{crit:.3g} (Student-t, {min(dof)} degrees of freedom)")
    cols = _residual_columns(pred, (problem.y_s, problem.y_l), (problem.a_s @ cs, problem.a_l @ cl),
                             (norm_s, norm_l))
    cols["outlier"] = outlier
    cols["outlier_level"] = np.where(outlier, np.where(start_out, "start", "snooping"), "")
    cols["used"] = used
    if leave_one_out:
        _leave_one_out(cols, (problem.a_s, problem.a_l), (ns, nl), problem.w0, used)
    tab = _set_columns(tab, cols)
    return CompensationResult(model=model, frame=fr, coef_sample=cs, coef_line=cl,
                              cov_sample=sig_s ** 2 * ns, cov_line=sig_l ** 2 * nl, sigma0_px=(sig_s, sig_l),
                              gcps=tab, redundancy=red, iterations=iterations, condition_number=cond, notes=notes,
                              warnings=check_point_warnings(tab))


def _problem(tab, model: CompensationModel, fr, pred):
    """``(CompensationProblem, control mask, condition number)`` of the GCP table: designs in the normalised
    predicted coordinates, observations ``measured - RPC``; GCPError / DegenerateGeometryError when the control
    points cannot determine ``model``."""
    u, v = (pred[0] - fr[0]) / fr[1], (pred[1] - fr[2]) / fr[3]
    ts, tl = model.terms
    a_s = _monomials(ts, u, v)
    a_l = a_s if tl == ts else _monomials(tl, u, v)     # one array: one decomposition per fit
    ctrl = tab["role"].to_numpy() == "control"
    n_ctrl = int(ctrl.sum())
    if n_ctrl < model.min_gcps:
        raise GCPError(f"model {model.label!r} needs at least {model.min_gcps} control GCP(s), got {n_ctrl}; add "
                       f"control points or choose a simpler model (translation needs 1)")
    cond = _check_rank(*_axis_designs(a_s, a_l, ctrl, (ts, tl)), model, n_ctrl)
    # residuals before = what the correction explains
    y_s, y_l = tab["sample"].to_numpy(float) - pred[0], tab["line"].to_numpy(float) - pred[1]
    w0 = 1.0 / tab["sigma"].to_numpy(float) ** 2
    return CompensationProblem(a_s, a_l, y_s, y_l, w0, model.min_gcps), ctrl, cond


def _estimate(problem: CompensationProblem, ctrl, model: CompensationModel, robust: bool, snoop: Snooping,
              max_iter: int):
    """``(final Estimate, used, start_out, iterations, notes)``: :func:`_robust_set`, then the estimate on the
    points it keeps (all control points when rejecting would leave the model undetermined). BLAS on the calling
    thread (:func:`~gdal_gf4cal.threads.blas_serial`, as the CLI): hundreds of small LAPACK calls (the start's
    subset solves) and a few tall products, where OpenBLAS's threads cost more in synchronisation than they
    compute (10 us per 3 x 3 solve with 2 right-hand sides instead of 0.3)."""
    with blas_serial():
        used, start_out, iterations, notes = _robust_set(problem, ctrl, robust, snoop, max_iter)
        try:
            if not np.array_equal(used, ctrl):       # else the check of _problem
                _check_rank(*_axis_designs(problem.a_s, problem.a_l, used, model.terms), model, int(used.sum()))
        except DegenerateGeometryError:
            used = ctrl.copy()
            notes.append("rejecting blunders would leave the model undetermined; all control points kept")
        return problem.fit(used), used, start_out, iterations, notes


def _robust_set(problem: CompensationProblem, ctrl, robust: bool, snoop: Snooping, max_iter: int):
    """``(used, start_out, iterations, notes)``: the control points in the estimate after the robust driver
    (high-breakdown start, then data snooping); all control points when robust estimation is off or impossible."""
    if not robust:
        return ctrl.copy(), np.zeros(ctrl.size, bool), 0, []
    redundancy = problem.redundancy(ctrl)
    if redundancy < 2:
        return ctrl.copy(), np.zeros(ctrl.size, bool), 0, [
            f"no robust estimation: redundancy {max(redundancy, 0)} is too small to detect blunders"]
    problem.solver = "normal"        # the iterations: normal equations; the final estimate (the caller's): SVD
    try:
        est = robust_fit(problem, norm=snoop, start="lts", candidates=ctrl, min_points=problem.min_points,
                         n_subsets=subset_count(problem.min_points), max_iter=max_iter, on_degenerate="stop")
    finally:
        problem.solver = "svd"
    notes = list(est.notes)
    if est.norm_info.get("degenerate"):
        notes.append("rejecting blunders would leave the model undetermined; all control points kept")
        return ctrl.copy(), np.zeros(ctrl.size, bool), est.iterations, notes
    return est.point_weights > 0, ctrl & (est.outlier_level == "start"), est.iterations, notes


def _fill_heights(tab, dem) -> None:
    """Missing heights (``h`` NaN) from ``dem.height(lon, lat)``, in place; GCPError without a DEM."""
    h = tab["h"].to_numpy(float)
    if not np.isnan(h).any():
        return
    if dem is None:
        raise GCPError(f"{int(np.isnan(h).sum())} GCP(s) have no height; give a DEM (--dem) to take it from")
    miss = np.isnan(h)
    fill = np.asarray(dem.height(tab["lon"].to_numpy(float)[miss], tab["lat"].to_numpy(float)[miss]), dtype=float)
    if np.isnan(fill).any():
        raise GCPError("the DEM has no height under some GCPs; give their height or a DEM that covers them")
    h = h.copy()
    h[miss] = fill
    tab["h"] = h


def _predict(rpc, tab) -> Tuple[np.ndarray, np.ndarray]:
    """The RPC's image coordinates of the GCPs; GCPError for non-numeric coordinates or points it cannot project."""
    lon, lat, h = (tab[c].to_numpy(float) for c in ("lon", "lat", "h"))
    s_meas, l_meas = tab["sample"].to_numpy(float), tab["line"].to_numpy(float)
    finite = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h) & np.isfinite(s_meas) & np.isfinite(l_meas)
    if not finite.all():
        raise GCPError(f"{int((~finite).sum())} GCP(s) have non-numeric coordinates; fix or remove them")
    s_pred, l_pred = (np.asarray(x, dtype=float) for x in rpc.project(lon, lat, h))
    if not (np.isfinite(s_pred) & np.isfinite(l_pred)).all():
        raise GCPError("the RPC cannot project some GCPs (outside its validity domain); check their coordinates")
    return s_pred, l_pred


def _residual_columns(pred, before, corr, norm) -> dict:
    """The residual columns of the one table shape (gdal_gf4cal.stats): before = the RPC, after = corrected."""
    return {"pred_sample_before": pred[0], "pred_line_before": pred[1],
            "res_sample_before": before[0], "res_line_before": before[1],
            "pred_sample_after": pred[0] + corr[0], "pred_line_after": pred[1] + corr[1],
            "res_sample_after": before[0] - corr[0], "res_line_after": before[1] - corr[1],
            "norm_res_sample": norm[0], "norm_res_line": norm[1]}


def _set_columns(tab, cols: dict):
    """``tab`` with ``cols`` set: the columns it has replaced in place, the new ones appended in order. A plain
    DataFrame with unique names: one DataFrame built from the columns (one pandas insertion per column, or a
    concatenation, cost more than the robust fit at 10,000 GCPs); else (a GeoDataFrame keeps its class) the
    replaced columns set and the new ones concatenated."""
    import pandas as pd              # ~1 s to import: only when first needed (CLI, QGIS start-up)
    if type(tab) is pd.DataFrame and tab.columns.is_unique:
        out = {k: tab[k] for k in tab.columns}
        out.update(cols)
        return pd.DataFrame(out, index=tab.index, copy=False)
    for k in [k for k in cols if k in tab.columns]:
        tab[k] = cols.pop(k)
    if not cols:
        return tab
    return pd.concat([tab, pd.DataFrame(cols, index=tab.index)], axis=1)


def _leave_one_out(cols: dict, designs, n_invs, w0, used) -> None:
    """Exact LOO residuals of linear LS: ``v_i / (1 - h_ii)`` for points in the fit; others are already
    independent (``res_sample_loo``, ``res_line_loo`` added to ``cols``)."""
    for axis, a, n_inv in zip(("sample", "line"), designs, n_invs):
        hat = w0 * np.einsum("ij,jk,ik->i", a, n_inv, a)
        v = cols[f"res_{axis}_after"]
        with np.errstate(divide="ignore", invalid="ignore"):
            cols[f"res_{axis}_loo"] = np.where(used, v / (1.0 - hat), v)


def _normalised(a_s, a_l, y_s, y_l, w0, used, solver: str = "svd"):
    """LS on ``used``; normalised residuals of every point, coefficients and ``N^-1`` per axis, a-posteriori sigma
    per axis, redundancy, the degrees of freedom ``(sample, line)`` of the sigma estimates and the residuals
    ``(y - a x)`` per axis."""
    wu = np.where(used, w0, 0.0)
    if a_l is a_s:                   # the same terms on both axes: one decomposition (the same numbers)
        est_s, est_l = weighted_lsq_many(a_s, [y_s, y_l], wu, prior=w0, apriori=True, solver=solver)
        cs, ns, cl, nl = est_s.x, est_s.cov, est_l.x, est_l.cov
    else:
        cs, ns, est_s = _solve_axis(a_s, y_s, wu, w0, solver)
        cl, nl, est_l = _solve_axis(a_l, y_l, wu, w0, solver)
    vs, vl = est_s.residuals, est_l.residuals
    red_s, red_l = est_s.dof, est_l.dof
    # With no redundancy the a-priori sigma (weights) is all we know: sigma0 = 1 (weighted_lsq's convention).
    sig_s, sig_l = est_s.sigma0, est_l.sigma0
    dof = (red_s, red_l)
    if red_s > 0 and red_l > 0 and min(red_s, red_l) < 10:
        # Few redundant observations per axis: pool both axes for a steadier scale.
        pooled = float(np.sqrt((np.sum(wu * vs ** 2) + np.sum(wu * vl ** 2)) / (red_s + red_l)))
        sig_s = sig_l = pooled
        dof = (red_s + red_l,) * 2
    # weighted_lsq normalises with var(v) = sigma^2 (1/w - q) in the fit, sigma^2 (1/w + q) outside it; rescale
    # from its per-axis sigma to the (possibly pooled) one.
    norm_s = np.nan_to_num(est_s.normalised * (max(est_s.sigma0, 1e-300) / max(sig_s, 1e-12)), nan=0.0)
    norm_l = np.nan_to_num(est_l.normalised * (max(est_l.sigma0, 1e-300) / max(sig_l, 1e-12)), nan=0.0)
    return norm_s, norm_l, cs, cl, ns, nl, sig_s, sig_l, min(red_s, red_l), dof, vs, vl
