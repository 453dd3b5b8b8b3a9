"""The one robust driver (METHODS §4, §5 step 3, §6): a start, iteratively reweighted solves with a pluggable
weight object (a *norm*, as statsmodels' RLM takes its norms), then one :class:`Estimate`.

Observations come per *point* (``k`` observations each, e.g. sample and line); a norm gives each point a weight
factor (0: out of the estimate). The driver knows nothing of the model: a *problem* does the solving.

Problem protocol (:class:`LinearProblem` is the linear one; a Schur-eliminated or Gauss-Newton problem, e.g. block
or bundle adjustment, implements the same few names, its ``fit`` linearising at its current parameters and solving
with :func:`~gdal_gf4cal.estimation.solve_with_points`):

- ``n_points``, ``k`` (observations per point), ``n_params`` (free parameters);
- ``fit(point_weights (n_points,)) -> Estimate``: the estimate with the a-priori weights times the point factors;
  its ``residuals`` and ``normalised`` reshape to ``(n_points, k)`` (``normalised`` may be NaN when a norm does not
  use it: only :class:`Snooping` does), ``axis_dof`` optional (per-axis degrees of freedom when the axes are
  estimated separately);
- optional: ``redundancy(mask) -> int`` (observations minus parameters of a point set; default
  ``mask.sum() * k - n_params``), ``start_design(idx) -> (design (m, k, p), obs (m, k), weights (m, k))`` (the
  linear(ised) design of the points ``idx`` for ``start="lts"``; ``start_normal``: its ``normal`` evaluation,
  :func:`~gdal_gf4cal.estimation.high_breakdown_start`), ``min_points`` (points of a minimal subset),
  ``change(old, new) -> float`` (how far the fit moved, default the largest residual change).

Norms: :class:`Snooping` (data snooping with Student-t critical values and the readmission hysteresis),
:class:`RadialHuber` (down-weighting to convergence, then rejection; look-angle, block), :class:`Huber` and
:class:`Tukey` (IRLS weights of the point's residual norm over a MAD scale).
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Any, List, Optional, Sequence

import numpy as np

from ..errors import DegenerateGeometryError, GCPError
from .lsq import Block, normal_solve, sigma0_and_cov, weighted_lsq
from .result import ESTIMATE_LEVELS, Estimate, names_and_blocks
from .robust import (critical_value, high_breakdown_start, min_subset_points, radial_huber_weights, tukey_weights,
                     readmissible)

__all__ = ["robust_fit", "LinearProblem", "Snooping", "RadialHuber", "Huber", "Tukey", "RobustState",
           "ESTIMATE_LEVELS"]



class LinearProblem:
    """``design @ x ~ obs`` per point: ``design`` (n_points, k, p), ``obs`` and ``weights`` (n_points, k)
    (``1/sigma^2``), named freezable ``blocks`` (frozen ones held at ``values``), see
    :func:`~gdal_gf4cal.estimation.weighted_lsq`.

    ``solver="svd"``: each fit is :func:`weighted_lsq` (redundancy numbers, normalised residuals: for
    :class:`Snooping`); ``solver="normal"``: :func:`normal_solve` (one ``A^T W A`` per fit, no per-observation
    diagnostics, ``Estimate.normal`` set: for IRLS over many points).
    """

    def __init__(self, design, obs, weights=None, *, blocks: Sequence[Block] = (), frozen: Sequence[str] = (),
                 values=None, hint: str = "", solver: str = "svd"):
        self.design = np.asarray(design, dtype=float)
        n, k, p = self.design.shape
        self.obs = np.asarray(obs, dtype=float).reshape(n, k)
        self.weights = (np.ones((n, k)) if weights is None
                        else np.broadcast_to(np.asarray(weights, float), (n, k)).copy())
        self.blocks, self.frozen, self.values, self.hint, self.solver = blocks, frozen, values, hint, solver
        self.free = np.ones(p, bool)
        if blocks and frozen:
            _, sl = names_and_blocks(blocks, p)
            for name in frozen:
                if name in sl:
                    self.free[sl[name]] = False
        self.n_points, self.k, self.n_params = n, k, int(self.free.sum())
        self._min_points: Optional[int] = None

    @property
    def min_points(self) -> int:
        if self._min_points is None:
            self._min_points = min_subset_points(self.design[:, :, self.free])
        return self._min_points

    def start_design(self, idx):
        a, y = self.design[idx], self.obs[idx]
        if not self.free.all():
            x0 = np.zeros(self.free.size) if self.values is None else np.asarray(self.values, dtype=float)
            y = y - a[:, :, ~self.free] @ x0[~self.free]
            a = a[:, :, self.free]
        return a, y, self.weights[idx]

    def redundancy(self, mask) -> int:
        return int(np.count_nonzero(mask)) * self.k - self.n_params

    def fit(self, point_weights) -> Estimate:
        n, k, p = self.design.shape
        ww = (self.weights * np.asarray(point_weights)[:, None]).reshape(-1)
        a2, y2 = self.design.reshape(n * k, p), self.obs.reshape(-1)
        if self.solver == "svd":
            return weighted_lsq(a2, y2, ww, blocks=self.blocks, frozen=self.frozen, values=self.values,
                                prior=self.weights.reshape(-1), hint=self.hint)
        x, nmat = normal_solve(a2, y2, ww, self.hint)
        v = y2 - a2 @ x
        dof = int(np.count_nonzero(ww)) - p
        sigma0, cov = sigma0_and_cov(nmat, float(np.sum(ww * v * v)), dof)
        names, sl = names_and_blocks(self.blocks, p)
        nan = np.full(n * k, np.nan)
        return Estimate(names=names, x=x, cov=cov, sigma0=sigma0, dof=dof, redundancy=nan, residuals=v,
                        normalised=nan, weights=ww, blocks=sl, normal=nmat)

    def change(self, old: Estimate, new: Estimate) -> float:
        return float(np.max(np.abs(self.design @ (new.x - old.x))))


class RobustState:
    """What the driver and a norm share: ``candidates`` (points that may enter), ``weights`` (current point
    factors), ``start_out`` (left out by the start), ``start_sigma`` (the start's LTS scale), ``outlier``,
    ``phase``, ``tol``, ``notes`` and ``info`` (copied to ``Estimate.norm_info``)."""

    def __init__(self, candidates, weights, start_out, start_sigma: float, tol: float,
                 phase1_tol: Optional[float] = None):
        self.candidates, self.weights, self.start_out = candidates, weights, start_out
        self.start_sigma, self.tol = start_sigma, tol
        self.phase1_tol = tol if phase1_tol is None else max(float(phase1_tol), tol)
        self.outlier = np.zeros(candidates.size, bool)
        self.phase = 1
        self.notes: List[str] = []
        self.info: dict = {}


def _redundancy(problem, mask) -> int:
    if hasattr(problem, "redundancy"):
        return int(problem.redundancy(mask))
    return int(np.count_nonzero(mask)) * problem.k - problem.n_params


def _change(problem, old: Estimate, new: Estimate) -> float:
    if hasattr(problem, "change"):
        return float(problem.change(old, new))
    return float(np.max(np.abs(np.asarray(new.residuals) - np.asarray(old.residuals))))


def _point_residuals(problem, est: Estimate, what: str = "residuals") -> np.ndarray:
    return np.asarray(getattr(est, what), dtype=float).reshape(problem.n_points, problem.k)


class Snooping:
    """Data snooping (METHODS §4, §6): points whose normalised residual (Baarda's w) exceeds the Student-t
    critical value of ``threshold`` (:func:`~gdal_gf4cal.estimation.critical_value`) leave the estimate; a point
    out comes back only when it also passes :func:`~gdal_gf4cal.estimation.readmissible` (hysteresis); until the
    set is stable. Non-candidates are only tested. Levels ``'start'`` / ``'snooping'``. ``too_many``: the note
    when the rule would leave no redundancy (all candidates are then kept)."""

    def __init__(self, threshold: float = 4.0,
                 too_many: str = "too many points look like blunders for a robust estimate; all candidates kept"):
        self.threshold, self.too_many = float(threshold), too_many

    def _dofs(self, est: Estimate, k: int):
        return tuple(est.axis_dof) if est.axis_dof is not None else (int(est.dof),) * k

    def critical(self, est: Estimate, k: int = 1) -> np.ndarray:
        """Critical normalised residual per axis (Student-t of the estimate's degrees of freedom)."""
        return np.array([critical_value(self.threshold, d) for d in self._dofs(est, k)])

    def exceeds(self, est: Estimate, n_points: int, k: int) -> np.ndarray:
        """Per point: any axis' normalised residual beyond its critical value."""
        norm = np.nan_to_num(np.asarray(est.normalised, dtype=float), nan=0.0).reshape(n_points, k)
        return np.any(np.abs(norm) > self.critical(est, k)[None, :], axis=1)

    def step(self, problem, est: Estimate, st: RobustState):
        n, k = problem.n_points, problem.k
        norm = np.nan_to_num(_point_residuals(problem, est, "normalised"), nan=0.0)
        used = st.weights > 0
        back = readmissible(norm, min(self._dofs(est, k)), threshold=self.threshold, sigma=est.sigma0,
                            start_sigma=st.start_sigma)
        new = st.candidates & ~self.exceeds(est, n, k) & (used | back)
        if _redundancy(problem, new) < 1:
            st.notes.append(self.too_many)
            new = st.candidates.copy()
        return None if np.array_equal(new, used) else new.astype(float)

    def settled(self, problem, old: Estimate, new: Estimate, st: RobustState) -> bool:
        return False

    def finish(self, problem, est: Estimate, st: RobustState) -> None:
        used = st.weights > 0
        bad = self.exceeds(est, problem.n_points, problem.k)
        est.outlier = (st.candidates & ~used) | (~st.candidates & bad)
        est.outlier_level = np.where(est.outlier, np.where(st.start_out & est.outlier, "start", "snooping"), "")


class _IRLSNorm:
    """IRLS weight objects: ``weights(residuals (n, k), problem, est) -> (factor, reject, scale, z)``; the driver
    re-solves until the fit moves less than ``tol`` and the rejected set is stable."""

    two_phase = False
    min_points = 1
    too_few = ""

    def weights(self, res, problem, est):                     # pragma: no cover - abstract
        raise NotImplementedError

    def step(self, problem, est: Estimate, st: RobustState):
        fw, out, scale, z = self.weights(_point_residuals(problem, est), problem, est)
        if self.two_phase and st.phase == 1:                  # phase 1: down-weighting only, start's points out
            out = np.zeros(out.shape, bool)
            fw = fw * np.where(st.start_out, 0.0, 1.0)
        if int((~out).sum()) < self.min_points:
            raise GCPError(f"only {int((~out).sum())} points left after rejecting outliers{self.too_few}")
        st.info["pending"] = out
        return np.where(out, 0.0, fw) * st.candidates

    def settled(self, problem, old: Estimate, new: Estimate, st: RobustState) -> bool:
        out = st.info.pop("pending")
        stable = np.array_equal(out, st.outlier)
        st.outlier = out
        change = _change(problem, old, new)
        if stable and self.two_phase and st.phase == 1 and change < st.phase1_tol:
            st.phase = 2                                      # the rejection phase reweights on to tol
        elif change < st.tol and stable:
            return True
        return False

    def finish(self, problem, est: Estimate, st: RobustState) -> None:
        _, _, scale, z = self.weights(_point_residuals(problem, est), problem, est)
        est.outlier = st.outlier.copy()
        est.outlier_level = np.where(est.outlier, np.where(st.start_out & est.outlier, "start", "reject"), "")
        est.norm_info.update(scale=scale, z=z)


class RadialHuber(_IRLSNorm):
    """Radial Huber weights (:func:`~gdal_gf4cal.estimation.radial_huber_weights`, ``k = 2``): phase 1
    down-weighting without rejection (the start's points left out) to convergence, phase 2 rejection beyond
    ``reject_k`` robust sigmas too (start points re-admitted when they fit). ``sigma``: a-priori sigma per point
    (array, or ``callable(problem, est)``; default 1). Fewer than ``min_points`` kept raises
    :class:`GCPError` (``too_few`` ends its message)."""

    two_phase = True

    def __init__(self, huber_c: float = 2.5, reject_k: float = 4.0, min_scale: float = 0.01, *, sigma=None,
                 min_points: int = 1, too_few: str = ""):
        self.huber_c, self.reject_k, self.min_scale = huber_c, reject_k, min_scale
        self.sigma, self.min_points, self.too_few = sigma, min_points, too_few

    def weights(self, res, problem, est):
        sig = self.sigma(problem, est) if callable(self.sigma) else (
            np.ones(res.shape[0]) if self.sigma is None else self.sigma)
        return radial_huber_weights(res, sig, problem.n_params, huber_c=self.huber_c, reject_k=self.reject_k,
                                    min_scale=self.min_scale)


@lru_cache(maxsize=16)
def _chi_median(k: int) -> float:
    from scipy import stats     # ~1 s to import: only when first needed (CLI, QGIS start-up)
    return float(math.sqrt(stats.chi2.ppf(0.5, k)))


class Huber(_IRLSNorm):
    """Huber IRLS: ``z`` = a point's weighted residual norm over a MAD-like scale (median / chi_k median,
    corrected for the parameters), factor ``min(1, c / z)``; never rejects."""

    def __init__(self, c: float = 1.345):
        self.c = float(c)

    def _z(self, res, problem):
        w = problem.weights if hasattr(problem, "weights") else np.ones_like(res)
        u = np.sqrt(np.sum(w * res * res, axis=1))
        n_obs = res.size
        scale = float(np.median(u)) / _chi_median(res.shape[1]) * math.sqrt(n_obs / max(n_obs - problem.n_params, 1))
        scale = max(scale, 1e-12)
        return u / scale, scale

    def weights(self, res, problem, est):
        z, scale = self._z(res, problem)
        return np.minimum(1.0, self.c / np.maximum(z, 1e-300)), np.zeros(z.size, bool), scale, z


class Tukey(Huber):
    """Tukey biweight IRLS (redescending: start it from ``start="lts"``): factor ``(1 - (z/c)^2)^2`` below ``c``,
    0 (rejected, level ``'reject'``) beyond; ``z`` as :class:`Huber`."""

    def __init__(self, c: float = 4.685):
        self.c = float(c)

    def weights(self, res, problem, est):
        z, scale = self._z(res, problem)
        return tukey_weights(z, self.c), z >= self.c, scale, z


def _start(problem, start, candidates, min_points, n_subsets: int, seed: int, tol: float,
           phase1_tol: Optional[float] = None) -> RobustState:
    n = problem.n_points
    cand = np.ones(n, bool) if candidates is None else np.asarray(candidates, bool).copy()
    used, start_sigma = cand.copy(), 0.0
    if isinstance(start, str) and start == "lts":
        m = int(min_points) if min_points else int(problem.min_points)
        if _redundancy(problem, cand) >= 2 and int(cand.sum()) > m:
            idx = np.flatnonzero(cand)
            a, y, w = problem.start_design(idx)
            inl, _, info = high_breakdown_start(a, y, w, min_points=m, n_subsets=n_subsets, seed=seed,
                                                normal=bool(getattr(problem, "start_normal", False)))
            start_sigma = info.get("lts_scale", 0.0)
            used = np.zeros(n, bool)
            used[idx[inl]] = True
            if int(used.sum()) <= m:                         # a start that keeps a minimal subset is none
                used = cand.copy()
    elif start is not None and not isinstance(start, str):
        used = cand & np.asarray(start, bool)
    elif start is not None:
        raise ValueError(f"start must be 'lts', None or a mask, not {start!r}")
    return RobustState(cand, used.astype(float), cand & ~used, start_sigma, tol, phase1_tol)


#: A 2-cycle of the robust weights: the new weights back within this fraction of their jump from the current ones
#: to those of two steps ago (Giza: one ray's Huber weight jumps by 0.88 and comes back, closer by half each
#: round, so the corrections never settle).
CYCLE_TOL = 0.01


def _two_cycle(new_w, current, before) -> bool:
    """The reweighting is in a 2-cycle: the new weights are (within :data:`CYCLE_TOL` of their jump) those of two
    steps ago, and differ from the current ones."""
    if before is None:
        return False
    new_w, current, before = (np.asarray(a, float) for a in (new_w, current, before))
    jump = np.max(np.abs(new_w - current), initial=0.0)
    return bool(jump > 1e-6 and np.max(np.abs(new_w - before), initial=0.0) <= CYCLE_TOL * jump)


def robust_fit(problem, *, norm: Any = None, start: Any = "lts", candidates=None, min_points: Optional[int] = None,
               n_subsets: int = 300, seed: int = 0, max_iter: int = 20, tol: float = 1e-6,
               on_degenerate: str = "raise", phase1_tol: Optional[float] = None) -> Estimate:
    """Robust estimate of ``problem`` (module docstring): start, reweighted solves with ``norm``, one Estimate.

    Parameters
    ----------
    norm : Snooping, RadialHuber, Huber or Tukey (default ``Snooping()``)
    start : ``'lts'`` (:func:`~gdal_gf4cal.estimation.high_breakdown_start` on ``problem.start_design``, when
        the candidates have a redundancy of 2 or more), None (all candidates) or a bool mask (points in the start)
    candidates : bool (n_points,), optional
        Points that may enter the estimate; the others (check points) are only tested.
    max_iter : int
        Reweighted solves after the first; ``tol``: how little the fit must move for an IRLS norm to stop.
    phase1_tol : float, optional
        A two-phase norm (:class:`RadialHuber`) leaves its down-weighting phase when the fit moves less than this
        (default ``tol``): the rejection phase goes on reweighting to ``tol`` with the same weights, so a looser
        first phase saves re-solves (IRLS halves its move per re-solve) without a looser result.
    on_degenerate : ``'raise'`` or ``'stop'``
        A reweighted solve raising :class:`DegenerateGeometryError`: re-raise, or stop with the last estimate
        (``norm_info['degenerate'] = True``).

    Returns
    -------
    Estimate
        With ``outlier`` / ``outlier_level`` per point (:data:`ESTIMATE_LEVELS`), ``point_weights`` (the norm's
        factor per point, 0: out), ``iterations`` (reweighted solves) and ``norm_info`` (``start_sigma``, and
        ``scale`` / ``z`` of an IRLS norm).
    """
    norm = Snooping() if norm is None else norm
    st = _start(problem, start, candidates, min_points, n_subsets, seed, tol, phase1_tol)
    try:
        est = problem.fit(st.weights)
    except DegenerateGeometryError:
        if np.array_equal(st.weights > 0, st.candidates):
            raise
        # The start's set does not determine the model (a short piece of a piecewise model trimmed away; which
        # near-equal set the start keeps can depend on rounding): start again from every candidate. "stop" keeps
        # that estimate; "raise" goes on reweighting from it.
        st.info["degenerate_start"] = True
        st.weights, st.start_out = st.candidates.astype(float), np.zeros(st.candidates.size, bool)
        est = problem.fit(st.weights)
        if on_degenerate == "stop":
            st.info["degenerate"] = True
            max_iter = 0
    it = 0
    before = None                                         # the weights two steps ago
    for it in range(1, max_iter + 1):
        new_w = norm.step(problem, est, st)
        if new_w is None:
            break
        if _two_cycle(new_w, st.weights, before):
            st.info["cycle"] = True
            st.notes.append("the robust weights alternate between two sets: stopped on the current one")
            break
        before = st.weights
        try:
            new = problem.fit(new_w)
        except DegenerateGeometryError:
            if on_degenerate != "stop":
                raise
            st.info["degenerate"] = True
            break
        done = norm.settled(problem, est, new, st)
        est, st.weights = new, new_w
        if done:
            break
    norm.finish(problem, est, st)
    est.iterations, est.point_weights = it, st.weights
    est.notes.extend(st.notes)
    est.norm_info.update(start_sigma=st.start_sigma, **{k: v for k, v in st.info.items() if k != "pending"})
    return est


# ---------------------------------------------------------------------------------------------------------------
# the former entry points, as thin calls of robust_fit
# ---------------------------------------------------------------------------------------------------------------
def robust_lsq(design, obs, weights=None, *, blocks: Sequence[Block] = (), frozen: Sequence[str] = (),
               values=None, threshold: float = 4.0, min_points: Optional[int] = None, candidates=None,
               n_subsets: int = 300, seed: int = 0, max_iter: int = 20, hint: str = "") -> Estimate:
    """Robust weighted LS over points: ``robust_fit(LinearProblem(...), norm=Snooping(threshold), start='lts')``.

    ``design`` (n_points, k, p), ``obs`` and ``weights`` (n_points, k); ``candidates``: points that may enter the
    estimate (the others only tested). Returns the Estimate with per-point ``outlier`` / ``outlier_level``.
    """
    problem = LinearProblem(design, obs, weights, blocks=blocks, frozen=frozen, values=values, hint=hint)
    return robust_fit(problem, norm=Snooping(threshold), start="lts", candidates=candidates,
                      min_points=min_points, n_subsets=n_subsets, seed=seed, max_iter=max_iter)


class IRLSSolution:
    """Result of :func:`irls`: parameters ``x``, normal matrix ``N`` (a-priori weights x robust factors), the robust
    factor per point (0 = rejected), ``outlier`` flags, the robust ``scale``, ``z`` (normalised residuals of the
    weight function) and the number of solves ``steps``."""

    def __init__(self, x, N, weights, outlier, scale, z, steps):
        self.x, self.N, self.weights, self.outlier, self.scale, self.z, self.steps = (
            x, N, weights, outlier, scale, z, steps)


class _WeightFn(_IRLSNorm):
    """A plain weight function ``fn(residuals (n, k)) -> (factor, reject, scale, z)`` as a two-phase norm."""

    two_phase = True

    def __init__(self, fn, min_points: int, too_few: str):
        self.fn, self.min_points, self.too_few = fn, min_points, too_few

    def weights(self, res, problem, est):
        return self.fn(res)


def irls(design, obs, weights, weight_fn, *, x0=None, robust: bool = True, start_out=None, min_points: int = 1,
         tol: float = 1e-6, max_steps: int = 100, hint: str = "", too_few: str = "") -> IRLSSolution:
    """Iteratively reweighted LS over points with a weight function (e.g. :func:`radial_huber_weights`):
    ``robust_fit(LinearProblem(..., solver='normal'), start=~start_out)`` with the function as a two-phase norm
    (down-weighting to convergence, then rejection too; :class:`RadialHuber`). Raises :class:`GCPError` when
    fewer than ``min_points`` points are left (``too_few`` ends the message)."""
    problem = LinearProblem(design, obs, weights, hint=hint, solver="normal")
    n = problem.n_points
    if not robust:
        est = problem.fit(np.ones(n))
        return IRLSSolution(est.x, est.normal, np.ones(n), np.zeros(n, bool), float("nan"), np.full(n, np.nan), 1)
    start = None if start_out is None else ~np.asarray(start_out, bool)
    est = robust_fit(problem, norm=_WeightFn(weight_fn, min_points, too_few), start=start, max_iter=max_steps,
                     tol=tol)
    return IRLSSolution(est.x, est.normal, est.point_weights, est.outlier, est.norm_info["scale"],
                        est.norm_info["z"], est.iterations + 1)
