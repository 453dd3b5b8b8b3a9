"""Look-angle calibration of an area-array camera from the RPC alone (METHODS §5, seed 000: GF4 PMS).

The camera is a :class:`~gdal_gf4cal.camera.LookAngleModel`: ``tan(phi_x)``, ``tan(phi_y)`` as cubic polynomials of
the detector numbers ``(s, l)`` (= image ``(sample, line)``, GDAL pixel convention). A scene's RPC was fitted from the
rigorous model built with the *current* camera ``(c, d)``. For a GCP ``(lon, lat, h) <-> (s, l)``:

1. virtual image point ``(s', l') = RPC(lon, lat, h)``;
2. the ray the current camera assigns to it, ``V = tan_old(s', l')``, is the ray to the ground point (the exterior
   orientation is unchanged, so the rigorous model's object space is the same);
3. the new camera ``(a, b)`` must give that ray at the *measured* detector: ``tan_new(s, l) = V`` (paper eq. 1, 5).

:func:`calibrate_lookangle` solves step 3 by Gauss-Newton on residuals in **pixels**
(``(s, l) - tan_new^-1(V)``), in coordinates normalised to the frame for conditioning, with robust reweighting (Huber,
then hard rejection at ``k`` robust sigmas). :func:`recalibrate_rpc` makes the new RPC of any scene whose RPC was made
with the current camera (step 4), :func:`compare_lookangle` compares two cameras in pixels (paper Table 2).

Why no rigorous model is needed: everything above uses only the image-space mapping
``(s', l') -> tan_new^-1(tan_old(s', l'))``. With the vendor's camera file the result is a true camera update; with
a nominal camera (:meth:`LookAngleModel.from_nominal`) the recalibrated RPCs are just as right, and the new camera
file is meaningful relative to that nominal model only.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import pandas as pd

from .basis import LOOKANGLE_POWERS, lookangle_cubic
from .camera import CameraFormatError, LookAngleModel
from .errors import ConvergenceError, DegenerateGeometryError, GCPError
from .estimation import Estimate, LinearProblem, RadialHuber, high_breakdown_start, robust_fit, sigma0_and_cov
from .progress import report
from .rpc_fit import fit_rpc_from_model
from .sensor import SensorModelMixin
from .stats import accuracy_by_role

__all__ = [
    "LookAngleCalibration", "LookAngleConditionWarning", "calibrate_lookangle", "recalibrate_rpc",
    "compare_lookangle", "lookangle_monomials", "layout_condition", "RecalibratedSensor", "MIN_GCPS",
    "calibrate_lookangle_rigorous",
]

#: Exponents ``(p, q)`` of ``s^p l^q`` for the 10 terms, in the camera file's order
#: ``1, s, l, s·l, s², l², s²·l, s·l², s³, l³`` (METHODS §5; the paper's eq. 4 typo fixed).
POWERS: Tuple[Tuple[int, int], ...] = LOOKANGLE_POWERS

#: 10 coefficients per axis: fewer control points leave the cubic undetermined.
MIN_GCPS = 10

#: Condition number (normal matrix of the cubic basis over the frame-normalised control points, per point) above
#: which the layout is refused, and above which a warning is given. A uniform layout gives ~1e2; half the frame
#: ~2e4; one 3000 px corner of a 10240 px frame ~3e6; points on a line ~1e16.
MAX_CONDITION = 1e6
WARN_CONDITION = 1e4

_HUBER_C = 2.5        # radial normalised residual where Huber down-weighting starts
_REJECT_K = 4.0       # hard rejection; P(Rayleigh > 4 sigma) = 3e-4, so ~no good point is lost
_MIN_SCALE_PX = 0.01  # floor of the robust scale in pixels (an RPC reproduces its model to ~1e-3 px)
_MIN_ROBUST_GCPS = 20  # below this the redundancy is too small to estimate a robust scale
#: Up to this many control GCPs the robust solve starts from the high-breakdown estimate (few GCPs, where several
#: blunders break a Huber start); above it the MAD-scaled Huber start has ~50 % breakdown already and the start
#: would only cost time (bench/bench_lookangle.py).
_START_MAX_GCPS = 1000
#: ... and from this many: the start's trimmed half (h = (n + 11) // 2 points) must have well more redundant
#: observations than the 20 parameters (2 h - 20 >= 50); with fewer, fitting 20 coefficients to half the points
#: over-fits and flags good points (seen at 40 GCPs), and the Huber start of today is kept.
_START_MIN_GCPS = 60
_LAYOUT_HINT = ("the control points leave the cubic look-angle model unconstrained (all on one line, in one corner "
                "or too few); spread them over the whole image")
_TOO_FEW = (" (control GCPs); the GCPs are inconsistent (check the camera file and the RPC belong to this "
            "scene)")


class LookAngleConditionWarning(UserWarning):
    """The control points constrain the look-angle model poorly (condition number given in the message)."""


# ---------------------------------------------------------------------------------------------------- basis
#: The 10 look-angle terms of ``(u, v)``, shape ``(..., 10)`` (order of :data:`POWERS`): :mod:`gdal_gf4cal.basis`.
lookangle_monomials = lookangle_cubic


def _basis_change(a_s: float, b_s: float, a_l: float, b_l: float) -> np.ndarray:
    """Matrix ``R`` with ``m_c(x) = sum_r R[r, c] m_r(y)`` for ``x_s = a_s + b_s y_s``, ``x_l = a_l + b_l y_l``.

    The 10 terms are the complete bivariate cubic, so the space is closed under this affine change: coefficients
    ``alpha`` in the ``x`` basis are ``R @ alpha`` in the ``y`` basis, exactly.
    """
    index = {pq: i for i, pq in enumerate(POWERS)}
    R = np.zeros((10, 10))
    for c, (p, q) in enumerate(POWERS):
        for i in range(p + 1):
            ci = math.comb(p, i) * a_s ** (p - i) * b_s ** i
            for j in range(q + 1):
                R[index[(i, j)], c] += ci * math.comb(q, j) * a_l ** (q - j) * b_l ** j
    return R


@dataclass(frozen=True)
class _Frame:
    """Frame normalisation ``u = (s - s0) / ks``, ``v = (l - l0) / kl`` (the detector array maps onto [-1, 1]²)."""

    s0: float
    l0: float
    ks: float
    kl: float

    @classmethod
    def of(cls, camera) -> "_Frame":
        width, height = (float(x) for x in camera.size)
        return cls(width / 2.0, height / 2.0, max(width / 2.0, 0.5), max(height / 2.0, 0.5))

    def uv(self, s, l):
        return (np.asarray(s, dtype=float) - self.s0) / self.ks, (np.asarray(l, dtype=float) - self.l0) / self.kl

    @property
    def to_raw(self) -> np.ndarray:
        """Normalised-basis coefficients -> raw detector-number coefficients."""
        return _basis_change(-self.s0 / self.ks, 1.0 / self.ks, -self.l0 / self.kl, 1.0 / self.kl)

    @property
    def to_norm(self) -> np.ndarray:
        """Raw detector-number coefficients -> normalised-basis coefficients."""
        return _basis_change(self.s0, self.ks, self.l0, self.kl)


def _coefficients(camera) -> Tuple[np.ndarray, np.ndarray]:
    return np.asarray(camera.x, dtype=float).reshape(10), np.asarray(camera.y, dtype=float).reshape(10)


def _with_coefficients(template, x, y, name: Optional[str] = None):
    """A LookAngleModel like ``template`` with new raw coefficients."""
    cls = LookAngleModel
    kwargs = dict(size=tuple(template.size), x=np.asarray(x, dtype=float), y=np.asarray(y, dtype=float))
    kwargs["name"] = name if name is not None else getattr(template, "name", None)
    return cls(**kwargs)


def _inverse_jacobian(camera, s, l) -> np.ndarray:
    """``(N, 2, 2)`` d(s, l)/d(tan_x, tan_y) at detector points (closed-form 2 x 2 inverse: 4x faster than
    ``np.linalg.inv`` on a stack of 2 x 2 matrices; NaN where the Jacobian is singular)."""
    j = np.asarray(camera.jacobian(s, l), dtype=float).reshape(-1, 2, 2)
    a, b, c, d = j[:, 0, 0], j[:, 0, 1], j[:, 1, 0], j[:, 1, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / (a * d - b * c)
    out = np.empty_like(j)
    out[:, 0, 0], out[:, 0, 1] = d * inv_det, -b * inv_det
    out[:, 1, 0], out[:, 1, 1] = -c * inv_det, a * inv_det
    return out


def _design(camera, frame: _Frame, s, l) -> Tuple[np.ndarray, np.ndarray]:
    """``(N, 2, 20)`` d(residual s, l)/d(normalised coefficients) ``= J^-1 · blockdiag(m(u, v))``, and ``J^-1``.

    With ``tan_new(p) = V`` fixed, ``dp = -J^-1 m dalpha``; residuals are ``measured - p`` so ``dr = +J^-1 m dalpha``.
    """
    m = lookangle_monomials(*frame.uv(s, l))                # (N, 10)
    Jinv = _inverse_jacobian(camera, s, l)                  # (N, 2, 2)
    A = np.empty((m.shape[0], 2, 20))
    A[:, :, :10] = Jinv[:, :, 0:1] * m[:, None, :]
    A[:, :, 10:] = Jinv[:, :, 1:2] * m[:, None, :]
    return A, Jinv


def layout_condition(sample, line, size, weights=None) -> float:
    """Condition number of the cubic look-angle basis over frame-normalised points (METHODS §5).

    ``cond(M^T W M / sum W)`` with ``M`` the 10 terms at ``u, v`` in [-1, 1]² over the frame: ~1e2 for points
    spread over the frame, large when they leave the cubic unconstrained (one line, one corner, too few).
    """
    width, height = (float(x) for x in size)
    frame = _Frame(width / 2.0, height / 2.0, width / 2.0, height / 2.0)
    m = lookangle_monomials(*frame.uv(sample, line))
    w = np.ones(m.shape[0]) if weights is None else np.asarray(weights, dtype=float).reshape(m.shape[0], -1).mean(1)
    N = (m * w[:, None]).T @ m / max(float(w.sum()), 1e-300)
    with np.errstate(all="ignore"):
        cond = float(np.linalg.cond(N))
    return cond if math.isfinite(cond) else float("inf")


# ---------------------------------------------------------------------------------------------------- result
@dataclass
class LookAngleCalibration:
    """Result of :func:`calibrate_lookangle` (METHODS §5). Writing files is a separate step.

    Attributes
    ----------
    The estimate is the core's :class:`gdal_gf4cal.estimation.Estimate` (``estimate``: blocks ``x``, ``y`` of the raw
    coefficients ``[a0..a9, b0..b9]``, their covariance ``sigma0² N^-1``, per-GCP outlier flags of control and
    check points, residuals after, redundancy numbers); ``iterations``, ``sigma0``, ``covariance``,
    ``condition_number`` and ``warnings`` are its fields under the names callers use. The rest is what only a
    look-angle calibration has.

    Attributes
    ----------
    camera : the recalibrated LookAngleModel (raw detector-number coefficients, camera-file units).
    current : the camera the scene's RPC was made with.
    estimate : the :class:`~gdal_gf4cal.estimation.Estimate` above.
    converged : whether the last correction was below ``tol_px`` with a stable outlier set.
    corrections : ``(iterations, 20)`` coefficient corrections per iteration, raw units, ``[a0..a9, b0..b9]``.
    correction_px : ``(iterations,)`` largest change of a predicted control point per iteration (px).
    history : per-iteration dicts (iteration, max_correction_px, rms_px, n_outliers).
    covariance_normalised : the covariance of the coefficients of the frame-normalised basis (what is solved).
    robust_sigma_px : the robust scale of the radial residuals (1: they match the GCP sigmas).
    gcps : copy of the input table with columns ``virtual_sample, virtual_line`` (``RPC(ground)``),
        ``res_sample_before, res_line_before`` (measured - RPC(ground)), ``pred_sample, pred_line``
        (``tan_new^-1(tan_old(s', l'))``; also as ``pred_*_after``, with ``pred_*_before`` = ``virtual_*``),
        ``res_sample_after, res_line_after``, ``norm_residual`` (radial residual / robust sigma), ``weight``
        (final robust weight, 0 if rejected), ``outlier`` (bool; control and check points), ``outlier_level``
        (``'start'``, ``'reject'`` or ``''``).
    control_stats, check_stats : one role of :func:`gdal_gf4cal.stats.accuracy_by_role` (``{n_outliers,
        before|after: {n, sample|line: {mean, rms, rmse, max}, planar, ce90_m}}``, ``ce90_m`` None) plus ``n``
        (points in the statistics); outliers excluded; ``check_stats`` is None without check points.
    n_control, n_outliers : control points used, and those flagged.
    """

    camera: Any
    current: Any
    estimate: Estimate
    converged: bool
    corrections: np.ndarray
    correction_px: np.ndarray
    history: List[Dict[str, float]]
    covariance_normalised: np.ndarray
    robust_sigma_px: float
    gcps: Any
    control_stats: Dict[str, Any]
    check_stats: Optional[Dict[str, Any]]
    n_control: int
    n_outliers: int

    @property
    def iterations(self) -> int:
        """Gauss-Newton iterations used."""
        return self.estimate.iterations

    @property
    def sigma0(self) -> float:
        """A-posteriori standard deviation of unit weight (~1 when the GCP sigmas in px are right)."""
        return self.estimate.sigma0

    @property
    def covariance(self) -> np.ndarray:
        """``(20, 20)`` covariance of ``[a0..a9, b0..b9]`` (raw units), ``sigma0² N^-1``."""
        return self.estimate.cov

    @property
    def condition_number(self) -> float:
        """:func:`layout_condition` of the control points."""
        return self.estimate.condition_number

    @property
    def warnings(self) -> List[str]:
        return self.estimate.warnings

    @property
    def residuals_before(self) -> np.ndarray:
        """``(N, 2)`` measured - RPC(ground), columns (sample, line), px."""
        return self.gcps[["res_sample_before", "res_line_before"]].to_numpy(float)

    @property
    def residuals_after(self) -> np.ndarray:
        """``(N, 2)`` measured - recalibrated prediction, columns (sample, line), px."""
        return self.gcps[["res_sample_after", "res_line_after"]].to_numpy(float)

    @property
    def outliers(self) -> np.ndarray:
        return self.gcps["outlier"].to_numpy(bool)

    @property
    def coefficient_std(self) -> np.ndarray:
        """Standard deviations of ``[a0..a9, b0..b9]`` (raw units)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def precision_px(self, grid_px: float = 250.0) -> Dict[str, Dict[str, float]]:
        """Propagated standard deviation of the new camera's look angles over the whole array, in pixels.

        ``J^-1 m(u, v)`` times the covariance, on a ``grid_px`` grid: ``{"sample"|"line": {"rms", "max"}}``. The
        RMS is the least-squares floor the recalibrated RPC can reach with these GCPs (``~sigma sqrt(10 / n)`` for
        points spread uniformly; larger where the layout leaves corners uncovered, which ``max`` shows).
        """
        frame = _Frame.of(self.camera)
        width, height = (float(v) for v in self.camera.size)
        S, L = (a.ravel() for a in np.meshgrid(np.arange(grid_px / 2, width, grid_px),
                                                np.arange(grid_px / 2, height, grid_px)))
        A, _ = _design(self.camera, frame, S, L)
        var = np.einsum("nij,jk,nik->ni", A, self.covariance_normalised, A)
        sd = np.sqrt(np.clip(var, 0.0, None))
        return {axis: {"rms": float(np.sqrt(np.mean(var[:, k]))), "max": float(np.max(sd[:, k]))}
                for k, axis in enumerate(("sample", "line"))}

    def to_dict(self) -> Dict[str, Any]:
        """JSON-friendly summary (for report.json)."""
        return {
            "method": "lookangle-from-rpc (METHODS §5)",
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
            "history": self.history,
            "sigma0": float(self.sigma0),
            "robust_sigma_px": float(self.robust_sigma_px),
            "condition_number": float(self.condition_number),
            "n_control": int(self.n_control),
            "n_outliers": int(self.n_outliers),
            "outlier_ids": [str(i) for i in self.gcps.loc[self.outliers, "id"]] if "id" in self.gcps else [],
            "control": self.control_stats,
            "check": self.check_stats,
            "camera_new": {"x": [float(v) for v in self.camera.x], "y": [float(v) for v in self.camera.y]},
            "coefficient_std": [float(v) for v in self.coefficient_std],
            "precision_px": self.precision_px(),
            "warnings": list(self.warnings),
        }


# ---------------------------------------------------------------------------------------------------- helpers
def _gcp_columns(gcps):
    missing = [c for c in ("lon", "lat", "h", "sample", "line") if c not in getattr(gcps, "columns", ())]
    if missing:
        raise GCPError(f"GCP table lacks column(s) {', '.join(missing)}; read it with gdal_gf4cal.gcp.read_gcps")
    cols = {c: np.asarray(gcps[c], dtype=float) for c in ("lon", "lat", "h", "sample", "line")}
    n = cols["lon"].size
    if "role" in gcps.columns:
        role = np.asarray(gcps["role"]).astype(str)
        control = role == "control"
    else:
        control = np.ones(n, bool)
    sigma = np.asarray(gcps["sigma"], dtype=float) if "sigma" in gcps.columns else np.ones(n)
    if np.any(~np.isfinite(sigma[control]) | (sigma[control] <= 0)):
        raise GCPError("GCP sigma must be positive and finite; fix the 'sigma' column (pixels)")
    return cols, control, sigma


def _base_weights(weights, sigma: np.ndarray, ctrl: np.ndarray) -> np.ndarray:
    """``(N, 2)`` a-priori weights: ``1 / sigma²`` per axis, or the ``weights`` given (one or two per GCP)."""
    n = ctrl.size
    if weights is None:
        return np.repeat((1.0 / sigma ** 2)[:, None], 2, axis=1)
    base_w = np.asarray(weights, dtype=float)
    if base_w.size not in (n, 2 * n):
        raise GCPError(f"weights must have one value per GCP ({n}) or two (sample, line; {2 * n} values), got "
                       f"{base_w.size}; give one weight per row of the GCP table")
    base_w = np.repeat(base_w.reshape(n, 1), 2, axis=1) if base_w.size == n else base_w.reshape(n, 2)
    if np.any(~np.isfinite(base_w[ctrl])) or np.any(base_w[ctrl] < 0):
        raise GCPError("weights must be finite and non-negative")
    return base_w


@dataclass
class _Inputs:
    """The GCPs as the calibration uses them: measured points ``obs`` (N, 2), virtual points ``sv, lv`` =
    RPC(ground), ``usable`` (finite everywhere), ``control`` (role), a-priori weights ``base_w`` (N, 2) and the
    effective sigma per point."""

    obs: np.ndarray
    sv: np.ndarray
    lv: np.ndarray
    usable: np.ndarray
    control: np.ndarray
    base_w: np.ndarray
    eff_sigma: np.ndarray

    @property
    def ctrl(self) -> np.ndarray:
        return self.control & self.usable


def _read_inputs(rpc, gcps, weights, progress) -> _Inputs:
    """The GCP table, its virtual points and weights (METHODS §5 step 1); :class:`GCPError` for too few control
    points or bad weights."""
    cols, control, sigma = _gcp_columns(gcps)
    n = control.size
    report(progress, 0.0, "virtual image points")
    sv, lv = rpc.project(cols["lon"], cols["lat"], cols["h"])
    sv = np.asarray(sv, dtype=float).reshape(n)
    lv = np.asarray(lv, dtype=float).reshape(n)
    obs = np.column_stack([cols["sample"], cols["line"]])
    usable = (np.isfinite(sv) & np.isfinite(lv) & np.all(np.isfinite(obs), axis=1) & np.isfinite(cols["h"])
              & np.isfinite(cols["lon"]) & np.isfinite(cols["lat"]))
    ctrl = control & usable
    n_ctrl = int(ctrl.sum())
    if n_ctrl < MIN_GCPS:
        raise GCPError(f"look-angle calibration needs at least {MIN_GCPS} control GCPs (20 coefficients), got "
                       f"{n_ctrl} usable of {int(control.sum())}; add control points spread over the image")
    base_w = _base_weights(weights, sigma, ctrl)
    eff_sigma = 1.0 / np.sqrt(np.maximum(base_w.mean(axis=1), 1e-300))
    return _Inputs(obs, sv, lv, usable, control, base_w, eff_sigma)


def _check_layout(inp: _Inputs, size, max_condition: float) -> Tuple[float, List[str]]:
    """:func:`layout_condition` of the control points: refused above ``max_condition``, warned about above
    :data:`WARN_CONDITION` (the warning also returned, for the report)."""
    ctrl = inp.ctrl
    cond = layout_condition(inp.obs[ctrl, 0], inp.obs[ctrl, 1], size, inp.base_w[ctrl])
    if not cond <= max_condition:
        raise DegenerateGeometryError(f"condition number {cond:.3g} > {max_condition:.3g}: {_LAYOUT_HINT}")
    msgs: List[str] = []
    if cond > WARN_CONDITION:
        msg = (f"condition number {cond:.3g} of the control-point layout is high (> {WARN_CONDITION:.0e}): the "
               "look-angle model is poorly constrained away from the control points; spread them over the image")
        msgs.append(msg)
        warnings.warn(msg, LookAngleConditionWarning, stacklevel=3)
    return cond, msgs


def _start_out(A: np.ndarray, r0: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Points the high-breakdown start leaves out, on the first linearisation (blunders cannot pull it; METHODS
    §5 step 3); none when it keeps no more than a minimal subset."""
    inl, _, _ = high_breakdown_start(A, -r0, w, min_points=MIN_GCPS)
    return ~inl if inl.sum() > MIN_GCPS else np.zeros(A.shape[0], bool)


def _robust_solve(A: np.ndarray, r0: np.ndarray, w_base: np.ndarray, sigma: np.ndarray, robust: bool, *,
                  tol_px: float = 1e-6, max_steps: int = 100, start_out: Optional[np.ndarray] = None) -> Estimate:
    """Solve the linearised problem ``r(delta) = r0 + A delta`` (pixels, ``A delta ~ -r0``) with the one robust
    driver: radial Huber to convergence with the start's points ``start_out`` left out, then hard rejection at
    :data:`_REJECT_K` robust sigmas (METHODS §5 step 3); one plain solve when not ``robust``. ``.x`` is delta."""
    problem = LinearProblem(A, -r0, w_base, hint=_LAYOUT_HINT, solver="normal")
    norm = RadialHuber(_HUBER_C, _REJECT_K, _MIN_SCALE_PX, sigma=sigma, min_points=MIN_GCPS, too_few=_TOO_FEW)
    return robust_fit(problem, norm=norm, start=None if start_out is None else ~start_out,
                      max_iter=max_steps if robust else 0, tol=tol_px)


@dataclass
class _Solution:
    """What the Gauss-Newton iterations leave: the camera, the last robust solve, the start's points left out and
    the per-iteration records."""

    camera: Any
    solve: Estimate
    start_out: Optional[np.ndarray]
    iterations: int
    corrections: List[np.ndarray] = field(default_factory=list)
    correction_px: List[float] = field(default_factory=list)
    history: List[Dict[str, float]] = field(default_factory=list)


def _gauss_newton(current, frame: _Frame, obs_c, V, w_c, sig_c, robust: bool, *, max_iter: int, tol_px: float,
                  progress) -> _Solution:
    """Gauss-Newton on the pixel residuals of the control points, each linearisation solved robustly
    (:func:`_robust_solve`; see :func:`calibrate_lookangle`'s notes); :class:`ConvergenceError` when the
    correction stays above ``tol_px``."""
    to_raw = frame.to_raw
    cx, cy = _coefficients(current)
    alpha = np.concatenate([frame.to_norm @ cx, frame.to_norm @ cy])
    out = _Solution(current, None, None, 0)
    n_ctrl = obs_c.shape[0]
    for iteration in range(1, max_iter + 1):
        report(progress, 0.05 + 0.85 * (iteration - 1) / max_iter, f"iteration {iteration}")
        A, Jinv = _design(out.camera, frame, obs_c[:, 0], obs_c[:, 1])
        tx, ty = out.camera.tan_angles(obs_c[:, 0], obs_c[:, 1])
        r0 = np.einsum("nij,nj->ni", Jinv, np.column_stack([tx - V[0], ty - V[1]]))
        if robust and out.start_out is None and _START_MIN_GCPS <= n_ctrl <= _START_MAX_GCPS:
            out.start_out = _start_out(A, r0, w_c)
        sol = _robust_solve(A, r0, w_c, sig_c, robust, start_out=out.start_out)
        alpha = alpha + sol.x
        out.camera = _with_coefficients(current, to_raw @ alpha[:10], to_raw @ alpha[10:])
        out.solve, out.iterations = sol, iteration
        step = float(np.max(np.abs(np.einsum("nij,j->ni", A, sol.x))))
        r_lin = r0 + np.einsum("nij,j->ni", A, sol.x)
        good = ~sol.outlier
        out.corrections.append(np.concatenate([to_raw @ sol.x[:10], to_raw @ sol.x[10:]]))
        out.correction_px.append(step)
        out.history.append({"iteration": iteration, "max_correction_px": step,
                            "rms_px": float(np.sqrt(np.mean(r_lin[good] ** 2))),
                            "n_outliers": int(sol.outlier.sum()), "reweighting_steps": int(sol.iterations + 1)})
        if step < tol_px:
            return out
    raise ConvergenceError(f"look-angle calibration did not converge in {max_iter} iterations (last correction "
                           f"{out.correction_px[-1]:.3g} px); check the GCPs for gross errors or raise max_iter")


@dataclass
class _Precision:
    """sigma0 and the covariance of the normalised coefficients (through the core's :func:`sigma0_and_cov`), the
    raw-unit covariance, the final design ``A2`` (2 n, 20) and weights ``wr`` (n, 2), the exact residuals."""

    sigma0: float
    dof: int
    cov_norm: np.ndarray
    cov_raw: np.ndarray
    design: np.ndarray
    wr: np.ndarray
    residuals: np.ndarray


def _precision(cam, frame: _Frame, obs_c, V, w_c, point_weights) -> _Precision:
    """sigma0 from the weighted inlier residuals through the recalibrated model (exact, not linearised) and
    ``sigma0² N^-1`` of the final linearisation (normalised basis, then raw units)."""
    r_c = obs_c - np.column_stack(cam.detector_of(V[0], V[1], obs_c[:, 0], obs_c[:, 1]))
    wr = w_c * point_weights[:, None]
    dof = int(np.count_nonzero(wr)) - 20       # observations that carry weight, minus the 20 coefficients
    A, _ = _design(cam, frame, obs_c[:, 0], obs_c[:, 1])
    A2 = A.reshape(-1, 20)
    N = (A2 * wr.reshape(-1)[:, None]).T @ A2
    sigma0, cov_norm = sigma0_and_cov(N, float(np.sum(wr * r_c ** 2)), dof)
    T = np.zeros((20, 20))
    T[:10, :10] = frame.to_raw
    T[10:, 10:] = frame.to_raw
    return _Precision(sigma0, dof, cov_norm, T @ cov_norm @ T.T, A2, wr, r_c)


def _residual_table(gcps, inp: _Inputs, current, cam):
    """The input table with the virtual points, the predictions through the recalibrated camera (exact:
    ``tan_new^-1(tan_old(s', l'))``) and the residuals before / after; :class:`ConvergenceError` when the camera
    cannot be inverted at a control point."""
    n = inp.usable.size
    u_idx = np.flatnonzero(inp.usable)
    Vux, Vuy = current.tan_angles(inp.sv[u_idx], inp.lv[u_idx])
    pred = np.column_stack(cam.detector_of(Vux, Vuy, inp.obs[u_idx, 0], inp.obs[u_idx, 1]))
    if np.any(~np.isfinite(pred[inp.ctrl[u_idx]])):
        raise ConvergenceError("the recalibrated camera cannot be inverted at some control points; check the GCPs "
                               "(gross errors?) and the camera file")
    out = gcps.copy()
    out["virtual_sample"], out["virtual_line"] = inp.sv, inp.lv
    out["res_sample_before"] = inp.obs[:, 0] - inp.sv
    out["res_line_before"] = inp.obs[:, 1] - inp.lv
    out["pred_sample"] = _scatter(n, u_idx, pred[:, 0])
    out["pred_line"] = _scatter(n, u_idx, pred[:, 1])
    # explicit names of the one table shape (gdal_gf4cal.stats): before = the RPC, after = the recalibrated camera
    out["pred_sample_before"], out["pred_line_before"] = inp.sv, inp.lv
    out["pred_sample_after"], out["pred_line_after"] = out["pred_sample"], out["pred_line"]
    out["res_sample_after"] = inp.obs[:, 0] - out["pred_sample"].to_numpy(float)
    out["res_line_after"] = inp.obs[:, 1] - out["pred_line"].to_numpy(float)
    return out


def _robust_scale(sol: Estimate, prec: _Precision, sig_c, robust: bool) -> Tuple[float, np.ndarray]:
    """The robust scale and the control points' normalised radial residuals: the driver's, or without the robust
    reweighting the plain scale of the exact residuals."""
    if robust:
        return float(sol.norm_info["scale"]), sol.norm_info["z"]
    radial = np.hypot(prec.residuals[:, 0], prec.residuals[:, 1]) / sig_c
    scale = float(np.sqrt(np.sum(radial ** 2) / max(prec.dof, 1)))
    return scale, radial / max(scale, 1e-12)


def _flag_outliers(out, inp: _Inputs, sol: Estimate, scale: float, z_c, robust: bool) -> None:
    """``norm_residual``, ``weight``, ``outlier`` and ``outlier_level`` of the table: control points as the robust
    solve left them (``'start'``: the high-breakdown start, never re-admitted; ``'reject'``: rejected by the radial
    Huber norm), check points by the same rule (radial residual over :data:`_REJECT_K` robust sigmas: ``'reject'``)."""
    n = inp.usable.size
    c_idx = np.flatnonzero(inp.ctrl)
    out["norm_residual"] = _scatter(n, c_idx, z_c)
    out["weight"] = _scatter(n, c_idx, sol.point_weights, 0.0)
    outlier = _scatter(n, c_idx, sol.outlier, False).astype(bool)
    level = np.full(n, "", dtype=object)
    level[c_idx] = np.where(sol.outlier_level == "start", "start", np.where(sol.outlier, "reject", ""))
    check = ~inp.control & inp.usable
    if robust and check.any():
        k_idx = np.flatnonzero(check)
        radial_px = np.hypot(out["res_sample_after"].to_numpy(float)[k_idx],
                             out["res_line_after"].to_numpy(float)[k_idx])
        bad = radial_px / np.maximum(inp.eff_sigma[k_idx] * scale, _MIN_SCALE_PX) > _REJECT_K
        outlier[k_idx[bad]] = True
        level[k_idx[bad]] = "reject"
    out["outlier"] = outlier
    out["outlier_level"] = level.astype(str)


# ---------------------------------------------------------------------------------------------------- calibrate
def calibrate_lookangle(rpc, gcps, current, *, weights=None, max_iter: int = 10, robust: bool = True,
                        progress=None, tol_px: float = 1e-3, max_condition: float = MAX_CONDITION,
                        ) -> LookAngleCalibration:
    """Recalibrate the look-angle model of an area-array camera from a scene's RPC and GCPs (METHODS §5).

    Parameters
    ----------
    rpc : :class:`~gdal_gf4cal.rpc.RPCModel` of the scene, fitted from the rigorous model with ``current``. Any
        object with ``project(lon, lat, h) -> (sample, line)`` (GDAL convention) works: passing the rigorous
        current sensor model gives the rigorous baseline (the virtual point then comes from the rigorous model).
    gcps : GCP GeoDataFrame (:mod:`gdal_gf4cal.gcp` schema): ``lon, lat, h, sample, line`` (GDAL convention),
        optional ``role`` ('control' rows are used, 'check' rows are only evaluated), ``sigma`` (px), ``id``.
    current : :class:`~gdal_gf4cal.camera.LookAngleModel`, the camera the RPC was made with (initial values).
    weights : optional per-GCP weights ``(N,)`` or ``(N, 2)`` (sample, line) replacing ``1 / sigma²``.
    max_iter : Gauss-Newton iteration limit; ``ConvergenceError`` if the correction is still above ``tol_px``.
    robust : robust reweighting inside each iteration: Huber, then hard rejection at 4 robust sigmas (MAD-type
        scale of the radial residual); flagged points get ``outlier=True``.
    progress : ``progress(fraction, message)``; may raise CancelledError.
    tol_px : convergence: largest change of a predicted control point in one iteration, px.
    max_condition : refuse layouts whose :func:`layout_condition` exceeds it (DegenerateGeometryError).

    Returns
    -------
    LookAngleCalibration
        Residuals ``after`` are exact: ``(s, l) - tan_new^-1(tan_old(RPC(ground)))``, i.e. the ground point
        re-projected through the recalibrated model, in pixels.

    Notes
    -----
    Each Gauss-Newton iteration linearises the pixel residual at the measured points,
    ``r = J^-1 (tan_new(s, l) - V)`` with ``J = d tan / d(s, l)`` of the current estimate: linear in the 20
    coefficients for a fixed ``J``, so the robust reweighting runs on that linear problem, and the next iteration
    only refreshes ``J`` (the correction drops by ~1e3 per iteration). The unknowns are the coefficients of the
    frame-normalised basis (``u, v`` in [-1, 1]); the result is converted exactly to raw detector numbers.

    Raises
    ------
    GCPError : fewer than 10 usable control points, missing columns, bad sigma.
    DegenerateGeometryError : control points that leave the cubic unconstrained (condition number in the message).
    ConvergenceError : no convergence within ``max_iter``.
    """
    inp = _read_inputs(rpc, gcps, weights, progress)
    cond, msgs = _check_layout(inp, current.size, max_condition)
    ctrl = inp.ctrl
    frame = _Frame.of(current)
    # The rays of the virtual points (paper eq. 4-5: constants during the adjustment).
    V = tuple(np.asarray(v, dtype=float) for v in current.tan_angles(inp.sv[ctrl], inp.lv[ctrl]))
    obs_c, w_c, sig_c = inp.obs[ctrl], inp.base_w[ctrl], inp.eff_sigma[ctrl]
    use_robust = robust and int(ctrl.sum()) >= _MIN_ROBUST_GCPS
    gn = _gauss_newton(current, frame, obs_c, V, w_c, sig_c, use_robust, max_iter=max_iter, tol_px=tol_px,
                       progress=progress)
    out = _residual_table(gcps, inp, current, gn.camera)
    prec = _precision(gn.camera, frame, obs_c, V, w_c, gn.solve.point_weights)
    scale, z_c = _robust_scale(gn.solve, prec, sig_c, use_robust)
    _flag_outliers(out, inp, gn.solve, scale, z_c, use_robust)
    # The one accuracy-report shape (gdal_gf4cal.stats.accuracy_by_role) over the usable points; flagged points
    # are left out of before and after. ``n`` (points in the statistics) is kept at the top for the printers.
    by_role = _stats_by_role(out, inp.usable, inp.control)
    estimate = _estimate(gn.camera, prec, cond, gn.iterations, msgs, out, ctrl)
    report(progress, 1.0, "look-angle calibration done")
    name = getattr(current, "name", "") or ""
    cam = _with_coefficients(current, gn.camera.x, gn.camera.y,
                             name=(f"{name} recalibrated" if name else "recalibrated"))
    return LookAngleCalibration(
        camera=cam, current=current, estimate=estimate, converged=True, corrections=np.array(gn.corrections),
        correction_px=np.array(gn.correction_px), history=gn.history, covariance_normalised=prec.cov_norm,
        robust_sigma_px=scale, gcps=out, control_stats=by_role["control"],
        check_stats=by_role["check"] if (~inp.control & inp.usable).any() else None,
        n_control=int(ctrl.sum()), n_outliers=int(gn.solve.outlier.sum()))


def _stats_by_role(out, usable: np.ndarray, control: np.ndarray) -> Dict[str, Any]:
    """:func:`gdal_gf4cal.stats.accuracy_by_role` of the usable rows of the output table, with ``n`` (points in
    the statistics, outliers left out) at the top of each role for the printers (METHODS §6)."""
    tab = pd.DataFrame({"role": np.where(control, "control", "check")[usable],
                        "outlier": out["outlier"].to_numpy(bool)[usable]})
    for c in ("res_sample_before", "res_line_before", "res_sample_after", "res_line_after"):
        tab[c] = out[c].to_numpy(float)[usable]
    rep = accuracy_by_role(tab)
    for entry in rep.values():
        entry["n"] = int(entry["after"]["n"])
    return rep


def _estimate(cam, prec: _Precision, cond, iterations, msgs, out, ctrl) -> Estimate:
    """:class:`gdal_gf4cal.estimation.Estimate` of a look-angle calibration (METHODS §4, §5): blocks ``x``
    (``a0..a9``) and ``y`` (``b0..b9``, raw units), residuals ``measured - predicted`` after, interleaved (sample,
    line) per GCP; weights ``1/sigma^2`` x robust factor (0: left out or not a control point); redundancy numbers
    ``1 - w a N^-1 a`` of the final linearisation."""
    n = len(out)
    c_idx = np.flatnonzero(ctrl)
    sigma0, wr = prec.sigma0, prec.wr
    n_inv_norm = prec.cov_norm / (sigma0 ** 2 if prec.dof > 0 else 1.0)
    q_c = np.einsum("ij,jk,ik->i", prec.design, n_inv_norm, prec.design).reshape(-1, 2)
    res = np.stack([out["res_sample_after"].to_numpy(float), out["res_line_after"].to_numpy(float)], axis=1)
    w = np.zeros((n, 2))
    w[c_idx] = wr
    red = np.zeros((n, 2))
    red[c_idx] = np.where(wr > 0, 1.0 - wr * q_c, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = np.where((w > 0) & (red > 1e-12), res / (max(sigma0, 1e-300) * np.sqrt(red / np.where(w > 0, w, 1.0))),
                        np.nan)
    names = [f"a{i}" for i in range(10)] + [f"b{i}" for i in range(10)]
    return Estimate(names=names, x=np.concatenate([np.asarray(cam.x, float), np.asarray(cam.y, float)]),
                    cov=prec.cov_raw, sigma0=float(sigma0), dof=int(prec.dof), redundancy=red.ravel(),
                    residuals=res.ravel(), normalised=norm.ravel(), weights=w.ravel(),
                    blocks={"x": slice(0, 10), "y": slice(10, 20)}, outlier=out["outlier"].to_numpy(bool),
                    outlier_level=out["outlier_level"].to_numpy(str), condition_number=float(cond),
                    iterations=int(iterations), warnings=list(msgs))


def calibrate_lookangle_rigorous(model, gcps, current=None, **kwargs) -> LookAngleCalibration:
    """The rigorous baseline (for comparison only): the same calibration with the virtual points taken from the
    rigorous *current* sensor model instead of the RPC, ``V = current.tan_angles(model.project(P))`` =
    ``model.look_angles(P)`` (METHODS §5; the paper's "calibration based on the physical imaging model").

    ``model`` is a rigorous frame model (e.g. the simulator's ``image.current``) whose camera is the current one
    (``current`` defaults to ``model.camera``); other arguments as :func:`calibrate_lookangle`. Its calibrated
    rigorous model is ``model.with_camera(result.camera)``.
    """
    return calibrate_lookangle(model, gcps, model.camera if current is None else current, **kwargs)


def _scatter(n: int, idx: np.ndarray, values: np.ndarray, fill=np.nan) -> np.ndarray:
    values = np.asarray(values)
    out = np.full(n, fill, dtype=values.dtype if values.dtype == bool else float)
    out[idx] = values
    return out


# ---------------------------------------------------------------------------------------------------- compare
def compare_lookangle(a, b, grid_px: float = 50) -> Dict[str, Any]:
    """Difference of two look-angle models in pixels over the whole array (METHODS §5, paper Table 2).

    At the centres of a ``grid_px`` grid over the detector array, ``tan_a - tan_b`` is turned into pixels with the
    local inverse Jacobian of ``b`` (the local angular size of a detector, rotation included):
    ``J_b^-1 (tan_a - tan_b)``. Returns ``{"sample": {mean, rms, max}, "line": {...}, "n": N, "grid_px": g}``
    (``max`` unsigned).
    """
    if tuple(a.size) != tuple(b.size):
        raise CameraFormatError(f"cameras have different sizes {tuple(a.size)} and {tuple(b.size)}")
    width, height = (float(x) for x in b.size)
    g = float(grid_px)
    if not g > 0:
        raise ValueError("grid_px must be positive")
    ss = np.arange(g / 2.0, width, g)
    ll = np.arange(g / 2.0, height, g)
    S, L = (x.ravel() for x in np.meshgrid(ss, ll))
    ax, ay = a.tan_angles(S, L)
    bx, by = b.tan_angles(S, L)
    Jinv = _inverse_jacobian(b, S, L)
    d = np.einsum("nij,nj->ni", Jinv, np.column_stack([np.asarray(ax) - bx, np.asarray(ay) - by]))

    def st(x):
        return {"mean": float(np.mean(x)), "rms": float(np.sqrt(np.mean(x ** 2))), "max": float(np.max(np.abs(x)))}

    return {"sample": st(d[:, 0]), "line": st(d[:, 1]), "n": int(S.size), "grid_px": g}


# ---------------------------------------------------------------------------------------------------- recalibrate
class RecalibratedSensor(SensorModelMixin):
    """The scene's geometry with the recalibrated camera, as an image-space composition over the old RPC.

    ``project(lon, lat, h) = tan_new^-1(tan_old(RPC(lon, lat, h)))`` and
    ``localize(s, l, h) = RPC.localize(tan_old^-1(tan_new(s, l)), h)`` (METHODS §5 step 4), GDAL convention unless
    ``pixel_convention="rpc"``. A :class:`~gdal_gf4cal.sensor.SensorModel` made of ``.rpc``, ``.current`` and
    ``.new``, with no writers: :func:`recalibrate_rpc` fits the RPC of it that is written.
    """

    def __init__(self, rpc, current, new):
        if tuple(current.size) != tuple(new.size):
            raise CameraFormatError(f"current and new cameras have different sizes {tuple(current.size)} and "
                             f"{tuple(new.size)}")
        self.rpc, self.current, self.new = rpc, current, new
        self.size = tuple(new.size)

    @property
    def height_range(self):
        """The RPC's valid height range (m)."""
        return tuple(self.rpc.height_range)

    def _project_gdal(self, lon, lat, h):
        sv, lv = self.rpc.project(lon, lat, h)
        sv = np.asarray(sv, float).ravel()
        lv = np.asarray(lv, float).ravel()
        tx, ty = self.current.tan_angles(sv, lv)
        s, l = self.new.detector_of(tx, ty, sv, lv)
        return np.asarray(s, float).ravel(), np.asarray(l, float).ravel()

    def _localize_gdal(self, sample, line, h):
        tx, ty = self.new.tan_angles(sample, line)
        sv, lv = self.current.detector_of(tx, ty, sample, line)
        return self.rpc.localize(np.asarray(sv, float).ravel(), np.asarray(lv, float).ravel(), h)


def recalibrate_rpc(rpc, current, new, height_range=None, *, grid=(21, 21), n_layers: int = 7, progress=None):
    """New RPC of a scene whose RPC was made with camera ``current``, for the recalibrated camera ``new``
    (METHODS §5 step 4, fitted terrain-independently as in METHODS §3).

    Ground points come from the old RPC (localised over an image grid x height layers); ``(s', l') = RPC(ground)``,
    ``V = tan_old(s', l')``, ``(s, l) = tan_new^-1(V)`` (2-D Newton, :meth:`LookAngleModel.detector_of`), and a new
    RPC is fitted on ``ground <-> (s, l)``; it is checked on a second grid offset by half a cell at intermediate
    heights (see :class:`RecalibratedSensor`).

    Parameters
    ----------
    rpc : the scene's RPCModel; current, new : LookAngleModel (same size).
    height_range : (min, max) ellipsoidal heights (m); default the RPC's ``HEIGHT_OFF ± HEIGHT_SCALE``.
    grid, n_layers : fitting grid ``(n_sample, n_line)`` and number of height layers (METHODS §3: >= 20 x 20, >= 6).
    progress : ``progress(fraction, message)``; may raise CancelledError.

    Returns
    -------
    (RPCModel, FitReport) as from :func:`gdal_gf4cal.rpc_fit.fit_rpc_from_model`; ``FitReport.check`` is the error
    of the new RPC against the exact composition (px).
    """
    sensor = RecalibratedSensor(rpc, current, new)
    if height_range is None:
        height_range = rpc.height_range
    return fit_rpc_from_model(sensor, size=sensor.size, height_range=tuple(height_range), grid=tuple(grid),
                              n_layers=n_layers, progress=progress)
