"""Image-space bias compensation of an RPC and detector-position polynomials (METHODS §4).

The observation model of every GCP (METHODS §4) is::

    line_meas   = line_rpc(lon, lat, h)   + dl(s', l')
    sample_meas = sample_rpc(lon, lat, h) + ds(s', l')

where ``(s', l') = rpc.project(lon, lat, h)`` are the RPC's own (GDAL-convention) image coordinates. Taking the
correction as a function of the *predicted* coordinates keeps the estimation linear and makes applying it an
explicit composition ``image = rpc(ground) + d(rpc(ground))``: translation and per-axis scale then fold exactly into
``SAMP_OFF/SAMP_SCALE`` and ``LINE_OFF/LINE_SCALE`` (METHODS §4.2). The difference to evaluating ``d`` at the
measured coordinates is second order in the (small) correction.

Internally both image axes are normalised, ``u = (s - s0) / ss`` and ``v = (l - l0) / ls`` with ``(s0, ss, l0, ls)``
taken from the RPC (``SAMP_OFF + 0.5``, ``SAMP_SCALE``, ...) unless given, so every model is a polynomial
``sum c_ij u^i v^j`` per axis with coefficients in pixels.

Estimating (:func:`fit_compensation` -> :class:`CompensationResult`) is separate from applying
(:func:`apply_compensation` -> :class:`AppliedCompensation`) and from writing (:func:`write_refined_rpc`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .basis import detector_terms, monomial_derivatives, monomials, term_name
from .errors import DegenerateGeometryError, GCPError
from .estimation import critical_value, high_breakdown_start, readmissible
from .geodesy import radii_of_curvature
from .sensor import GDAL_PIXEL_OFFSET, SensorModelMixin, pixel_shift

__all__ = [
    "MODEL_NAMES", "CompensationModel", "CompensationResult", "CompensatedRPC", "AppliedCompensation",
    "fit_compensation", "apply_compensation", "ground_offsets_m", "ground_jacobian", "accuracy_by_role",
]

#: Model names accepted by :meth:`CompensationModel.from_name` (and ``gf4cal refine --model``).
MODEL_NAMES = ("translation", "shift-drift", "affine", "poly2", "detector-poly")

# Exponents (i, j) of u^i v^j per axis for the base models of METHODS §4.1 (u: sample, v: line).
_BASE_TERMS = {
    "translation": (((0, 0),), ((0, 0),)),
    # shift + drift = translation + per-axis scale: ds depends on s only, dl on l only (folds exactly).
    "shift-drift": (((0, 0), (1, 0)), ((0, 0), (0, 1))),
    "affine": (((0, 0), (1, 0), (0, 1)), ((0, 0), (1, 0), (0, 1))),
    "poly2": (((0, 0), (1, 0), (0, 1), (1, 1), (2, 0), (0, 2)),) * 2,
}


@dataclass(frozen=True)
class CompensationModel:
    """Which image-space terms are estimated (METHODS §4.1, §4.3).

    Parameters
    ----------
    name : str
        One of :data:`MODEL_NAMES`.
    order : int
        Order (1..6) of the detector-position polynomial; only for ``detector-poly``.
    along : str
        For ``detector-poly``: the base model whose terms are combined with the polynomial (default
        ``translation``: one along-track shift). The polynomial ``k0 + k1 y + ... + kn y^n`` of the normalised
        detector position ``y`` is added to the cross-track axis.
    ccd_axis : {'sample', 'line'}
        Image axis along the CCD line (push-broom: ``sample``). The cross-track correction is on this axis.
    """

    name: str
    order: int = 0
    along: str = "translation"
    ccd_axis: str = "sample"

    @classmethod
    def from_name(cls, name: str, order: Optional[int] = None, along: Optional[str] = None,
                  ccd_axis: str = "sample") -> "CompensationModel":
        """Build and validate a model from its CLI name (``order`` only for ``detector-poly``)."""
        name = str(name).strip().lower().replace("_", "-")
        if name in ("shift", "shift+drift", "shiftdrift"):
            name = "shift-drift"
        if name not in MODEL_NAMES:
            raise GCPError(f"unknown compensation model {name!r}; choose one of {', '.join(MODEL_NAMES)}")
        if name == "detector-poly":
            if order is None:
                raise GCPError("model 'detector-poly' needs an order 1..6 (--order N)")
            along = "translation" if along is None else str(along).strip().lower()
            if along not in _BASE_TERMS:
                raise GCPError(f"--along must be one of {', '.join(_BASE_TERMS)}, got {along!r}")
            model = cls(name, int(order), along, ccd_axis)
        else:
            if order not in (None, 0):
                raise GCPError(f"--order applies only to model 'detector-poly', not {name!r}")
            model = cls(name, 0, "translation", ccd_axis)
        model._validate()
        return model

    def _validate(self) -> None:
        if self.name not in MODEL_NAMES:
            raise GCPError(f"unknown compensation model {self.name!r}; choose one of {', '.join(MODEL_NAMES)}")
        if self.ccd_axis not in ("sample", "line"):
            raise GCPError(f"ccd_axis must be 'sample' or 'line', got {self.ccd_axis!r}")
        if self.name == "detector-poly" and not 1 <= int(self.order) <= 6:
            raise GCPError(f"detector-poly order must be 1..6, got {self.order}")

    def __post_init__(self) -> None:
        self._validate()

    @property
    def label(self) -> str:
        """Short label, e.g. ``affine`` or ``detector-poly3+affine``."""
        if self.name != "detector-poly":
            return self.name
        return f"detector-poly{self.order}" + ("" if self.along == "translation" else f"+{self.along}")

    @property
    def terms(self) -> Tuple[Tuple[Tuple[int, int], ...], Tuple[Tuple[int, int], ...]]:
        """Exponents ``(i, j)`` of ``u^i v^j`` for the sample axis and for the line axis."""
        if self.name != "detector-poly":
            return _BASE_TERMS[self.name]
        ts, tl = (list(t) for t in _BASE_TERMS[self.along])
        poly = detector_terms(self.order, self.ccd_axis)
        if self.ccd_axis == "sample":
            ts = ts + [t for t in poly if t not in ts]
        else:
            tl = tl + [t for t in poly if t not in tl]
        return tuple(ts), tuple(tl)

    @property
    def n_params(self) -> int:
        """Total number of parameters (both axes)."""
        ts, tl = self.terms
        return len(ts) + len(tl)

    @property
    def min_gcps(self) -> int:
        """Minimum number of control GCPs (each gives one observation per axis)."""
        ts, tl = self.terms
        return max(len(ts), len(tl))

    @property
    def foldable(self) -> bool:
        """True if the correction folds exactly into the RPC offsets/scales (METHODS §4.2)."""
        ts, tl = self.terms
        return set(ts) <= {(0, 0), (1, 0)} and set(tl) <= {(0, 0), (0, 1)}


# The bases live in gdal_gf4cal.basis (METHODS §4.1); the private names stay for existing callers.
_monomials = monomials
_monomial_derivatives = monomial_derivatives
_term_name = term_name


@dataclass
class CompensationResult:
    """Estimated image-space correction and its statistics (METHODS §4, §6).

    Attributes
    ----------
    model : CompensationModel
    frame : tuple of float
        ``(s0, ss, l0, ls)``: the correction is a polynomial of ``u = (s' - s0)/ss``, ``v = (l' - l0)/ls``
        (GDAL pixel convention).
    coef_sample, coef_line : ndarray
        Coefficients (px) of the terms ``model.terms[0]`` / ``model.terms[1]``.
    cov_sample, cov_line : ndarray
        Their covariance (px^2), scaled by the a-posteriori variance of unit weight of each axis.
    sigma0_px : tuple of float
        A-posteriori standard deviation of unit weight (sample, line); a GCP with ``sigma = 1`` px has it in px.
    gcps : pandas.DataFrame
        The input table with added columns ``pred_sample_before, pred_line_before`` (RPC), ``res_sample_before,
        res_line_before``, ``pred_sample_after, pred_line_after, res_sample_after, res_line_after`` (corrected),
        ``norm_res_sample,
        norm_res_line`` (residual / its standard deviation), ``outlier`` (bool), ``outlier_level`` (``'start'``:
        left out by the high-breakdown start and never re-admitted, ``'snooping'``: by data snooping, ``''``),
        ``used`` (in the estimate),
        and with ``leave_one_out=True`` ``res_sample_loo, res_line_loo``. Residuals are measured - predicted, px.
    redundancy : int
        Observations minus parameters of the final estimate (the smaller axis).
    iterations : int
        Robust reweighting iterations.
    condition_number : float
        Worst condition number of the column-equilibrated control design (both axes).
    notes : list of str
        What the caller should know (robust estimation skipped, blunder threshold raised, ...).
    warnings : list of str
        What is likely wrong (the check points fit worse after compensation than before: blunders suspected, the
        worst points named, see ``suspects``); never silent.
    """

    model: CompensationModel
    frame: Tuple[float, float, float, float]
    coef_sample: np.ndarray
    coef_line: np.ndarray
    cov_sample: np.ndarray
    cov_line: np.ndarray
    sigma0_px: Tuple[float, float]
    gcps: Any
    redundancy: int = 0
    iterations: int = 0
    condition_number: float = 1.0
    notes: List[str] = field(default_factory=list)
    warnings: List[str] = field(default_factory=list)

    @classmethod
    def from_coefficients(cls, model, frame: Sequence[float], coef_sample, coef_line) -> "CompensationResult":
        """A known correction (no GCPs): ``coef_*`` for the terms of ``model.terms`` in px, ``frame`` as above.

        Useful to apply a correction estimated elsewhere, or to simulate a biased RPC from a true one.
        """
        import pandas as pd
        if not isinstance(model, CompensationModel):
            model = CompensationModel.from_name(model)
        ts, tl = model.terms
        cs, cl = np.asarray(coef_sample, float).ravel(), np.asarray(coef_line, float).ravel()
        if cs.size != len(ts) or cl.size != len(tl):
            raise GCPError(f"model {model.label!r} has {len(ts)} sample and {len(tl)} line terms; got "
                           f"{cs.size} and {cl.size} coefficients")
        cols = ["id", "lon", "lat", "h", "sample", "line", "role", "outlier"]
        return cls(model=model, frame=tuple(float(x) for x in frame), coef_sample=cs, coef_line=cl,
                   cov_sample=np.zeros((cs.size, cs.size)), cov_line=np.zeros((cl.size, cl.size)),
                   sigma0_px=(0.0, 0.0), gcps=pd.DataFrame({c: [] for c in cols}))

    # -- evaluating the correction -----------------------------------------------------------------------------
    def _uv(self, sample, line):
        s0, ss, l0, ls = self.frame
        return (np.asarray(sample, dtype=float) - s0) / ss, (np.asarray(line, dtype=float) - l0) / ls

    def correction(self, sample, line) -> Tuple[np.ndarray, np.ndarray]:
        """``(ds, dl)`` in px at RPC-predicted image coordinates ``(sample, line)`` (GDAL convention)."""
        u, v = self._uv(sample, line)
        ts, tl = self.model.terms
        return _monomials(ts, u, v) @ self.coef_sample, _monomials(tl, u, v) @ self.coef_line

    def correction_jacobian(self, sample, line) -> np.ndarray:
        """``d(ds, dl)/d(s', l')``, shape (..., 2, 2)."""
        s0, ss, l0, ls = self.frame
        u, v = self._uv(sample, line)
        ts, tl = self.model.terms
        dsu, dsv = _monomial_derivatives(ts, u, v)
        dlu, dlv = _monomial_derivatives(tl, u, v)
        jac = np.empty(np.shape(u) + (2, 2))
        jac[..., 0, 0] = dsu @ self.coef_sample / ss
        jac[..., 0, 1] = dsv @ self.coef_sample / ls
        jac[..., 1, 0] = dlu @ self.coef_line / ss
        jac[..., 1, 1] = dlv @ self.coef_line / ls
        return jac

    def correction_std(self, sample, line) -> Tuple[np.ndarray, np.ndarray]:
        """Standard deviation (px) of the estimated correction at ``(sample, line)``: the noise-propagation floor.

        This is what the GCP noise necessarily leaves in the corrected RPC: ``sigma0 * sqrt(a^T N^-1 a)`` per axis.
        """
        u, v = self._uv(sample, line)
        ts, tl = self.model.terms
        a_s, a_l = _monomials(ts, u, v), _monomials(tl, u, v)
        var_s = np.einsum("...i,ij,...j->...", a_s, self.cov_sample, a_s)
        var_l = np.einsum("...i,ij,...j->...", a_l, self.cov_line, a_l)
        return np.sqrt(np.maximum(var_s, 0.0)), np.sqrt(np.maximum(var_l, 0.0))

    def invert_correction(self, sample, line, tol: float = 1e-10, max_iter: int = 30):
        """RPC coordinates ``(s', l')`` such that ``(s', l') + d(s', l') = (sample, line)`` (vectorised Newton)."""
        s = np.asarray(sample, dtype=float)
        l = np.asarray(line, dtype=float)
        ds, dl = self.correction(s, l)
        sp, lp = s - ds, l - dl
        for _ in range(max_iter):
            ds, dl = self.correction(sp, lp)
            fs, fl = sp + ds - s, lp + dl - l
            jac = self.correction_jacobian(sp, lp)
            a, b = 1.0 + jac[..., 0, 0], jac[..., 0, 1]
            c, d = jac[..., 1, 0], 1.0 + jac[..., 1, 1]
            det = a * d - b * c
            step_s = (d * fs - b * fl) / det
            step_l = (a * fl - c * fs) / det
            sp, lp = sp - step_s, lp - step_l
            if np.all(~np.isfinite(step_s) | (np.abs(step_s) + np.abs(step_l) < tol)):
                break
        return sp, lp

    # -- parameters and statistics -----------------------------------------------------------------------------
    @property
    def parameter_names(self) -> List[str]:
        ts, tl = self.model.terms
        return [_term_name("sample", t) for t in ts] + [_term_name("line", t) for t in tl]

    @property
    def parameters(self) -> Dict[str, float]:
        """Coefficients by name (px), e.g. ``{'sample_1': 3.2, 'sample_u': -0.4, 'line_1': ...}``."""
        vals = list(self.coef_sample) + list(self.coef_line)
        return {n: float(x) for n, x in zip(self.parameter_names, vals)}

    @property
    def parameter_std(self) -> Dict[str, float]:
        sd = list(np.sqrt(np.diag(self.cov_sample))) + list(np.sqrt(np.diag(self.cov_line)))
        return {n: float(x) for n, x in zip(self.parameter_names, sd)}

    @property
    def estimate(self):
        """The estimate as the one result class :class:`gdal_gf4cal.estimation.Estimate` (METHODS §4).

        Blocks ``sample`` and ``line``; observations interleaved per GCP (sample, line); ``sigma0`` is the RMS of
        the two axes' values (they are pooled when the redundancy is small); redundancy numbers ``1 - w a N^-1 a``
        of the points in the estimate.
        """
        from .estimation import Estimate
        tab = self.gcps
        p_s = self.coef_sample.size
        p = p_s + self.coef_line.size
        cov = np.zeros((p, p))
        cov[:p_s, :p_s], cov[p_s:, p_s:] = self.cov_sample, self.cov_line
        n = len(tab)
        if n and "pred_sample_before" in tab.columns:
            u, v = self._uv(tab["pred_sample_before"].to_numpy(float), tab["pred_line_before"].to_numpy(float))
            ts, tl = self.model.terms
            w = 1.0 / tab["sigma"].to_numpy(float) ** 2
            used = tab["used"].to_numpy(bool)
            red = []
            for a, c, sg in ((_monomials(ts, u, v), self.cov_sample, self.sigma0_px[0]),
                             (_monomials(tl, u, v), self.cov_line, self.sigma0_px[1])):
                q = np.einsum("ij,jk,ik->i", a, c, a) / max(sg, 1e-300) ** 2
                red.append(np.where(used, 1.0 - w * q, 0.0))
            redundancy = np.stack(red, axis=1).ravel()
            weights = np.repeat(np.where(used, w, 0.0), 2)
            res = np.stack([tab["res_sample_after"], tab["res_line_after"]], axis=1).astype(float).ravel()
            norm = np.stack([tab["norm_res_sample"], tab["norm_res_line"]], axis=1).astype(float).ravel()
            outlier = tab["outlier"].to_numpy(bool)
            level = tab["outlier_level"].to_numpy(str) if "outlier_level" in tab.columns else None
        else:
            redundancy = weights = res = norm = np.zeros(0)
            outlier, level = np.zeros(0, bool), None
        dof = int(round(float(redundancy.sum()))) if redundancy.size else 0
        return Estimate(names=self.parameter_names, x=np.concatenate([self.coef_sample, self.coef_line]), cov=cov,
                        sigma0=float(np.sqrt(0.5 * (self.sigma0_px[0] ** 2 + self.sigma0_px[1] ** 2))), dof=dof,
                        redundancy=redundancy, residuals=res, normalised=norm, weights=weights,
                        blocks={"sample": slice(0, p_s), "line": slice(p_s, p)}, outlier=outlier,
                        outlier_level=level, condition_number=float(self.condition_number),
                        iterations=int(self.iterations), notes=list(self.notes), warnings=list(self.warnings))

    @property
    def suspects(self) -> List[Tuple[str, str, float]]:
        """:func:`suspected_blunders` of this result (empty unless the check points fit worse after it)."""
        return suspected_blunders(self.gcps)

    @property
    def outliers(self):
        """Rows of :attr:`gcps` flagged as blunders."""
        return self.gcps[self.gcps["outlier"].to_numpy(bool)]

    def accuracy(self, rpc=None) -> Dict[str, Any]:
        """Per role (control, check), before and after: n and per axis mean/rms/std/max (px), CE90 (m).

        Flagged outliers are left out of both (so before/after compare the same points) and counted in
        ``n_outliers``. With ``rpc`` the planar CE90 in metres is computed through the RPC's ground Jacobian.
        """
        return accuracy_by_role(self.gcps, rpc=rpc)

    def to_dict(self, rpc=None) -> Dict[str, Any]:
        """JSON-ready summary: model, parameters, accuracy per role, outliers (METHODS §6)."""
        out: Dict[str, Any] = {
            "model": {"name": self.model.name, "label": self.model.label,
                      "order": int(self.model.order) if self.model.name == "detector-poly" else None,
                      "along": self.model.along if self.model.name == "detector-poly" else None,
                      "ccd_axis": self.model.ccd_axis, "min_gcps": self.model.min_gcps,
                      "frame": {"s0": self.frame[0], "ss": self.frame[1], "l0": self.frame[2], "ls": self.frame[3]},
                      "parameters_px": self.parameters, "parameter_std_px": self.parameter_std,
                      "sigma0_px": {"sample": self.sigma0_px[0], "line": self.sigma0_px[1]},
                      "redundancy": int(self.redundancy), "iterations": int(self.iterations),
                      "condition_number": float(self.condition_number)},
        }
        out.update(self.accuracy(rpc))
        out["outliers"] = [
            {"id": str(r["id"]), "role": str(r["role"]),
             "norm_res_sample": _f(r["norm_res_sample"]), "norm_res_line": _f(r["norm_res_line"]),
             "res_sample_px": _f(r["res_sample_after"]), "res_line_px": _f(r["res_line_after"])}
            for _, r in self.outliers.iterrows()]
        out["notes"] = list(self.notes)
        out["warnings"] = list(self.warnings)
        return out


def _f(x) -> Optional[float]:
    x = float(x)
    return x if math.isfinite(x) else None


# ----------------------------------------------------------------------------------------------------------------
# statistics helpers (METHODS §6)
# ----------------------------------------------------------------------------------------------------------------
def _axis_stats(x) -> Dict[str, Optional[float]]:
    """``{mean, rms, std, max}`` (px) of one axis, :func:`gdal_gf4cal.stats.axis_stats`; None when empty."""
    from .stats import axis_stats
    return {k: _f(v) for k, v in axis_stats(x).items() if k != "n"}


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


def ground_jacobian(rpc, lon, lat, h) -> np.ndarray:
    """``d(sample, line)/d(lon, lat)`` (..., 2, 2) at fixed height, as :func:`ground_offsets_m` uses it."""
    return _jacobian(rpc, np.asarray(lon, float), np.asarray(lat, float), np.asarray(h, float))[..., :2]


def _jacobian(model, lon, lat, h):
    """``d(sample, line)/d(lon, lat, h)`` from ``model.project_jacobian`` or central differences."""
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


def accuracy_by_role(gcps, rpc=None) -> Dict[str, Any]:
    """``{control|check: {n_outliers, before|after: {n, line|sample: {mean, rms, std, max}, planar, ce90_m}}}``.

    The one report shape, :func:`gdal_gf4cal.stats.accuracy_by_role` (METHODS §6), from a table with
    ``res_{sample,line}_{before,after}`` columns (px); flagged outliers are left out. ``ce90_m`` is the planar CE90
    (m) of the image residuals taken to the ground through ``rpc`` (None without ``rpc``).
    """
    from .stats import accuracy_by_role as _by_role
    ground = None
    if rpc is not None:
        lon, lat, h = (gcps[c].to_numpy(float) for c in ("lon", "lat", "h"))
        jac = {}        # per row selection (a role): the ground Jacobian, shared by before and after

        def ground(sel, rs, rl):
            key = sel.tobytes()
            if key not in jac:
                jac.clear()
                jac[key] = ground_jacobian(rpc, lon[sel], lat[sel], h[sel])
            return ground_offsets_m(rpc, lon[sel], lat[sel], h[sel], rs, rl, jacobian=jac[key])
    return _by_role(gcps, ground_offsets=ground)


# ----------------------------------------------------------------------------------------------------------------
# estimation
# ----------------------------------------------------------------------------------------------------------------
def _frame_from_rpc(rpc) -> Tuple[float, float, float, float]:
    try:
        # RPC00B offsets are raw (first pixel centre at 0); GDAL convention adds half a pixel.
        return (float(rpc.samp_off) + 0.5, float(abs(rpc.samp_scale)) or 1.0,
                float(rpc.line_off) + 0.5, float(abs(rpc.line_scale)) or 1.0)
    except AttributeError:
        return (0.0, 1.0, 0.0, 1.0)


def _table(gcps):
    import pandas as pd
    if isinstance(gcps, pd.DataFrame):
        tab = gcps.copy()
    elif isinstance(gcps, dict):
        tab = pd.DataFrame(gcps)
    else:
        raise GCPError("GCPs must be a table (GeoDataFrame/DataFrame) with columns lon, lat, h, sample, line")
    missing = [c for c in ("lon", "lat", "sample", "line") if c not in tab.columns]
    if missing:
        raise GCPError(f"GCP table lacks column(s) {', '.join(missing)}; expected id, lon, lat, h, sample, line, role")
    tab = tab.reset_index(drop=True)
    if "id" not in tab.columns:
        tab["id"] = [str(i + 1) for i in range(len(tab))]
    if "role" not in tab.columns:
        tab["role"] = "control"
    tab["role"] = tab["role"].fillna("control").astype(str).str.strip().str.lower()
    bad = sorted(set(tab["role"]) - {"control", "check"})
    if bad:
        raise GCPError(f"GCP role must be 'control' or 'check', found {bad}")
    if "sigma" not in tab.columns:
        tab["sigma"] = 1.0
    tab["sigma"] = tab["sigma"].astype(float).fillna(1.0)
    if (tab["sigma"] <= 0).any():
        raise GCPError("GCP sigma must be > 0 px")
    if "h" not in tab.columns:
        tab["h"] = np.nan
    return tab


def _solve_axis(a, y, w, prior=None) -> Tuple[np.ndarray, np.ndarray, Any]:
    """Weighted LS of one axis through :func:`gdal_gf4cal.estimation.weighted_lsq` (METHODS §4): returns
    ``(coef, N^-1, estimate)`` for weights ``w`` (zeros drop a row; their residuals are still computed and
    normalised with the a-priori weights ``prior``)."""
    from .estimation import weighted_lsq
    est = weighted_lsq(a, y, w, prior=prior, apriori=True)
    return est.x, est.cov, est

def _check_rank(a_list, model: CompensationModel, n_ctrl: int, terms=None) -> float:
    """Raise DegenerateGeometryError if the control layout does not determine the model over the image.

    Two tests per axis: the column-equilibrated design is (numerically) rank deficient, or GCP noise would be
    amplified more than ``_MAX_AMPLIFICATION`` times at the image corners (u, v = +-1), e.g. GCPs spread over one
    pixel in line for a model with a line drift. Returns the worst condition number.
    """
    worst = 1.0
    amp = 0.0
    corners = np.array([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [0.0, 0.0]])
    for k, a in enumerate(a_list):
        sv = np.linalg.svd(a / np.maximum(np.linalg.norm(a, axis=0), 1e-300), compute_uv=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
        worst = max(worst, cond)
        if terms is not None and math.isfinite(cond) and cond < 1e8:
            q = _monomials(terms[k], corners[:, 0], corners[:, 1])
            n_inv = np.linalg.pinv(a.T @ a, hermitian=True)
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


#: Largest tolerated amplification of GCP noise at the image corners before a layout counts as degenerate.
_MAX_AMPLIFICATION = 1000.0


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
        Robust estimation: Huber then Tukey reweighting on standardised residuals, then blunders are flagged
        while their normalised residual (residual / its standard deviation, Baarda's w) exceeds
        ``outlier_threshold`` and left out of the estimate. Needs redundancy; with none it is skipped.
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
    h = tab["h"].to_numpy(float)
    if np.isnan(h).any():
        if dem is None:
            raise GCPError(f"{int(np.isnan(h).sum())} GCP(s) have no height; give a DEM (--dem) to take it from")
        fill = np.asarray(dem.height(tab["lon"].to_numpy(float)[np.isnan(h)], tab["lat"].to_numpy(float)[np.isnan(h)]),
                          dtype=float)
        if np.isnan(fill).any():
            raise GCPError("the DEM has no height under some GCPs; give their height or a DEM that covers them")
        h = h.copy()
        h[np.isnan(h)] = fill
        tab["h"] = h
    lon, lat = tab["lon"].to_numpy(float), tab["lat"].to_numpy(float)
    s_meas, l_meas = tab["sample"].to_numpy(float), tab["line"].to_numpy(float)
    finite = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h) & np.isfinite(s_meas) & np.isfinite(l_meas)
    if not finite.all():
        raise GCPError(f"{int((~finite).sum())} GCP(s) have non-numeric coordinates; fix or remove them")
    s_pred, l_pred = (np.asarray(x, dtype=float) for x in rpc.project(lon, lat, h))
    if not (np.isfinite(s_pred) & np.isfinite(l_pred)).all():
        raise GCPError("the RPC cannot project some GCPs (outside its validity domain); check their coordinates")

    fr = tuple(float(x) for x in (frame if frame is not None else _frame_from_rpc(rpc)))
    u, v = (s_pred - fr[0]) / fr[1], (l_pred - fr[2]) / fr[3]
    ts, tl = model.terms
    a_s, a_l = _monomials(ts, u, v), _monomials(tl, u, v)
    y_s, y_l = s_meas - s_pred, l_meas - l_pred                # residuals before = what the correction explains
    ctrl = (tab["role"] == "control").to_numpy()
    n_ctrl = int(ctrl.sum())
    if n_ctrl < model.min_gcps:
        raise GCPError(f"model {model.label!r} needs at least {model.min_gcps} control GCP(s), got {n_ctrl}; add "
                       f"control points or choose a simpler model (translation needs 1)")
    cond = _check_rank([a_s[ctrl], a_l[ctrl]], model, n_ctrl, (ts, tl))
    w0 = 1.0 / tab["sigma"].to_numpy(float) ** 2
    p_s, p_l = a_s.shape[1], a_l.shape[1]
    notes: List[str] = []

    used = ctrl.copy()
    iterations = 0
    redundancy_min = n_ctrl - max(p_s, p_l)
    start_out = np.zeros(len(tab), bool)
    if robust and redundancy_min >= 2:
        # Phase 1: high-breakdown start (least trimmed squares from every minimal subset of the control points,
        # or seeded random ones when there are many): several blunders, even coherent ones, cannot mask each other.
        idx = np.flatnonzero(ctrl)
        design = np.zeros((idx.size, 2, p_s + p_l))
        design[:, 0, :p_s], design[:, 1, p_s:] = a_s[idx], a_l[idx]
        inl, _, start_info = high_breakdown_start(design, np.stack([y_s[idx], y_l[idx]], axis=1),
                                         np.repeat(w0[idx, None], 2, axis=1), min_points=model.min_gcps)
        used = np.zeros(len(tab), bool)
        used[idx[inl]] = True
        if used.sum() <= model.min_gcps:
            used = ctrl.copy()
        start_out = ctrl & ~used
        # Phase 2: data snooping with normalised residuals on the robust inlier set until it is stable.
        for iterations in range(1, max_iter + 1):
            if used.sum() < model.min_gcps:
                used = ctrl.copy()
                break
            try:
                norm_s, norm_l, *_, sig_s, sig_l, _, dof = _normalised(a_s, a_l, y_s, y_l, w0, used)
            except DegenerateGeometryError:
                break                                        # undetermined subset: handled below
            # Hysteresis (estimation.readmissible): a point out of the fit comes back only when it also fits.
            back = readmissible(np.stack([norm_s, norm_l], axis=1), min(dof), threshold=outlier_threshold,
                                sigma=max(sig_s, sig_l), start_sigma=start_info.get("lts_scale", 0.0))
            new_used = ctrl & ~_exceeds(norm_s, norm_l, outlier_threshold, dof) & (used | back)
            if new_used.sum() < model.min_gcps or (new_used.sum() - max(p_s, p_l)) < 1:
                notes.append("too many GCPs look like blunders for a robust estimate; all control points kept")
                new_used = ctrl.copy()
            if np.array_equal(new_used, used):
                break
            used = new_used
    elif robust:
        notes.append(f"no robust estimation: redundancy {max(redundancy_min, 0)} is too small to detect blunders")

    try:
        _check_rank([a_s[used], a_l[used]], model, int(used.sum()), (ts, tl))
    except DegenerateGeometryError:
        used = ctrl.copy()
        notes.append("rejecting blunders would leave the model undetermined; all control points kept")
    norm_s, norm_l, cs, cl, ns, nl, sig_s, sig_l, red, dof = _normalised(a_s, a_l, y_s, y_l, w0, used)
    outlier = ~used & ctrl
    if robust and red >= 2:
        # Check points are never in the estimate; flag those that are blunders by the same test.
        outlier |= (~ctrl) & _exceeds(norm_s, norm_l, outlier_threshold, dof)
        crit = _critical_value(outlier_threshold, min(dof))
        if crit > 1.05 * outlier_threshold:
            notes.append(f"few redundant observations: blunder threshold raised from {outlier_threshold:g} to "
                         f"{crit:.3g} (Student-t, {min(dof)} degrees of freedom)")
    elif not robust:
        outlier[:] = False

    ds, dl = a_s @ cs, a_l @ cl
    tab["pred_sample_before"], tab["pred_line_before"] = s_pred, l_pred
    tab["res_sample_before"], tab["res_line_before"] = y_s, y_l
    tab["pred_sample_after"], tab["pred_line_after"] = s_pred + ds, l_pred + dl
    tab["res_sample_after"], tab["res_line_after"] = y_s - ds, y_l - dl
    tab["norm_res_sample"], tab["norm_res_line"] = norm_s, norm_l
    tab["outlier"] = outlier
    tab["outlier_level"] = np.where(outlier, np.where(start_out, "start", "snooping"), "")
    tab["used"] = used
    warns = _worse_check_warning(tab)
    if leave_one_out:
        # Exact LOO residual of linear LS: v_i / (1 - h_ii) for points in the fit; others are already independent.
        hs = w0 * np.einsum("ij,jk,ik->i", a_s, ns, a_s)
        hl = w0 * np.einsum("ij,jk,ik->i", a_l, nl, a_l)
        with np.errstate(divide="ignore", invalid="ignore"):
            tab["res_sample_loo"] = np.where(used, (y_s - ds) / (1.0 - hs), y_s - ds)
            tab["res_line_loo"] = np.where(used, (y_l - dl) / (1.0 - hl), y_l - dl)
    return CompensationResult(model=model, frame=fr, coef_sample=cs, coef_line=cl,
                              cov_sample=sig_s ** 2 * ns, cov_line=sig_l ** 2 * nl, sigma0_px=(sig_s, sig_l),
                              gcps=tab, redundancy=red, iterations=iterations, condition_number=cond, notes=notes,
                              warnings=warns)


def suspected_blunders(tab, n: int = 3) -> List[Tuple[str, str, float]]:
    """The control points most likely to be blunders when the check points fit worse after compensation than
    before: ``(id, role, planar residual after compensation px)`` of the ``n`` control points in the estimate with
    the largest normalised residuals (a blunder in the fit drags the correction and leaves residuals on its
    fellow points too, so the list is where to look, not a verdict; check points are only its victims). Empty
    when the check points fit as well or better."""
    rms = _check_rms(tab)
    if rms is None or not rms[1] > rms[0]:
        return []
    cand = (tab["role"] == "control").to_numpy() & ~tab["outlier"].to_numpy(bool)
    z = np.hypot(tab["norm_res_sample"].to_numpy(float), tab["norm_res_line"].to_numpy(float))
    z = np.where(cand, np.nan_to_num(z, nan=0.0), -np.inf)
    order = np.lexsort((np.arange(z.size), -z))[:min(n, int(cand.sum()))]   # ties: input order
    r = np.hypot(tab["res_sample_after"].to_numpy(float), tab["res_line_after"].to_numpy(float))
    ids, roles = tab["id"].astype(str).to_numpy(), tab["role"].astype(str).to_numpy()
    return [(ids[i], roles[i], float(r[i])) for i in order]


def _check_rms(tab) -> Optional[Tuple[float, float]]:
    """Planar rms (px) of the unflagged check points before and after compensation; None without any."""
    sel = (tab["role"] == "check").to_numpy() & ~tab["outlier"].to_numpy(bool)
    if not sel.any():
        return None
    return tuple(float(np.sqrt(np.mean(tab[f"res_sample_{w}"].to_numpy(float)[sel] ** 2
                                       + tab[f"res_line_{w}"].to_numpy(float)[sel] ** 2)))
                 for w in ("before", "after"))


def describe_suspects(suspects) -> str:
    """``g1 (control, 31.2 px), ...`` for a message."""
    return ", ".join(f"{i} ({role}, {r:.1f} px)" for i, role, r in suspects)


def _worse_check_warning(tab) -> List[str]:
    """Warnings when the check points disagree with the compensation: they fit worse after it than before
    (blunders suspected: the worst points named), or most of them are flagged as blunders."""
    chk = (tab["role"] == "check").to_numpy()
    if not chk.any():
        return []
    outl = tab["outlier"].to_numpy(bool)
    out: List[str] = []
    if 2 * int((chk & outl).sum()) > int(chk.sum()):
        out.append(f"{int((chk & outl).sum())} of the {int(chk.sum())} check points are flagged as blunders: the "
                   "check points disagree with the compensation; check the GCPs (wrong heights, other image) or the "
                   "model")
    rms = _check_rms(tab)
    if rms is not None and rms[1] > rms[0]:
        out.append(f"the {int((chk & ~outl).sum())} check points fit worse after compensation than before (planar "
                   f"rms {rms[0]:.3g} -> {rms[1]:.3g} px): blunders are suspected among the GCPs; the worst: "
                   f"{describe_suspects(suspected_blunders(tab))}; check or remove them, or choose a simpler model")
    return out


def _critical_value(threshold: float, dof: int) -> float:
    """Critical normalised residual, :func:`gdal_gf4cal.estimation.critical_value` (METHODS §4, §6)."""
    return critical_value(threshold, dof)


def _exceeds(norm_s, norm_l, threshold: float, dof: Tuple[int, int]) -> np.ndarray:
    """True where either axis' normalised residual exceeds its critical value (:func:`_critical_value`)."""
    return (np.abs(norm_s) > _critical_value(threshold, dof[0])) | \
        (np.abs(norm_l) > _critical_value(threshold, dof[1]))


def _normalised(a_s, a_l, y_s, y_l, w0, used):
    """LS on ``used``; normalised residuals of every point, a-posteriori sigma per axis, redundancy and the
    degrees of freedom ``(sample, line)`` of the sigma estimates."""
    wu = np.where(used, w0, 0.0)
    cs, ns, est_s = _solve_axis(a_s, y_s, wu, w0)
    cl, nl, est_l = _solve_axis(a_l, y_l, wu, w0)
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
    return norm_s, norm_l, cs, cl, ns, nl, sig_s, sig_l, min(red_s, red_l), dof


# ----------------------------------------------------------------------------------------------------------------
# applying
# ----------------------------------------------------------------------------------------------------------------
class CompensatedRPC(SensorModelMixin):
    """An RPC composed with an image-space correction: ``project = rpc.project + d(rpc.project)`` (METHODS §4).

    A :class:`~gdal_gf4cal.sensor.SensorModel` (``project``, ``project_jacobian``, ``localize``, ``localize_dem``,
    ``height_range``; GDAL pixel convention unless ``pixel_convention="rpc"``), so it can be refitted
    (METHODS §3), intersected (METHODS §7) or compared with a truth model. It is made of ``.rpc`` (the uncorrected
    :class:`~gdal_gf4cal.rpc.RPCModel`) and ``.result`` (the :class:`CompensationResult`) and forwards nothing
    to them: it has no writers. The only way from a correction to a file is :func:`apply_compensation` (exact
    fold or refit, its error reported), whose ``.rpc`` is written.
    """

    def __init__(self, rpc, result: CompensationResult):
        self.rpc = rpc
        self.result = result

    def __repr__(self) -> str:
        return f"CompensatedRPC(rpc={self.rpc!r}, model={getattr(self.result.model, 'name', self.result.model)!r})"

    @property
    def height_range(self) -> Tuple[float, float]:
        """The RPC's valid height range (m): the correction is image-space only."""
        return tuple(self.rpc.height_range)

    # -- SensorModelMixin hooks (flat arrays, GDAL convention) ------------------------------------------------
    def _project_gdal(self, lon, lat, h):
        s, l = self.rpc.project(lon, lat, h)
        ds, dl = self.result.correction(s, l)
        return np.asarray(s) + ds, np.asarray(l) + dl

    def _localize_gdal(self, sample, line, h):
        sp, lp = self.result.invert_correction(sample, line)
        return self.rpc.localize(sp, lp, h)

    # -- analytic Jacobian and the RPC's DEM fast path ---------------------------------------------------------
    def project_jacobian(self, lon, lat, h, *, pixel_convention: str = "gdal") -> np.ndarray:
        """``d(sample, line)/d(lon, lat, h)`` = ``(I + d correction) @ J_rpc``, shape ``(..., 2, 3)`` (METHODS §4)."""
        pixel_shift(pixel_convention)
        s, l = self.rpc.project(lon, lat, h)
        jac = np.asarray(self.rpc.project_jacobian(lon, lat, h), dtype=float)
        dcorr = self.result.correction_jacobian(s, l)
        return jac + dcorr @ jac

    def localize_dem(self, sample, line, dem, *, pixel_convention: str = "gdal", full_output: bool = False,
                     **kw):
        """Line of sight x DEM (METHODS §2, §4): the correction is inverted in the image, then the RPC's
        :meth:`~gdal_gf4cal.rpc.RPCModel.localize_dem` (its fast path) does the rest; same returns as it."""
        shift = pixel_shift(pixel_convention) - GDAL_PIXEL_OFFSET
        sample, line = np.broadcast_arrays(np.asarray(sample, dtype=float), np.asarray(line, dtype=float))
        sp, lp = self.result.invert_correction(sample - shift, line - shift)
        sp = np.asarray(sp, dtype=float).reshape(sample.shape)
        lp = np.asarray(lp, dtype=float).reshape(sample.shape)
        if sample.shape == ():
            sp, lp = float(sp), float(lp)
        return self.rpc.localize_dem(sp, lp, dem, full_output=full_output, **kw)


@dataclass
class AppliedCompensation:
    """A refined RPC and how it was made (METHODS §4.2).

    ``exact`` is True when the correction folded exactly into offsets/scales; otherwise the RPC was refitted on
    the corrected model and ``refit_max_px`` / ``refit_rms_px`` are its check errors (independent grid, METHODS §3).
    """

    rpc: Any
    exact: bool
    refit_max_px: float = 0.0
    refit_rms_px: float = 0.0
    fit_report: Any = None

    def to_dict(self) -> Dict[str, Any]:
        out = {"exact": bool(self.exact), "method": "fold" if self.exact else "refit",
               "refit_max_px": float(self.refit_max_px), "refit_rms_px": float(self.refit_rms_px)}
        if self.fit_report is not None:
            out["refit_notes"] = list(getattr(self.fit_report, "notes", ()))
        return out


def _fold(rpc, result: CompensationResult):
    """Fold translation + per-axis scale into SAMP/LINE_OFF and _SCALE (exact; METHODS §4.2)."""
    s0, ss, l0, ls = result.frame
    cs = dict(zip(result.model.terms[0], result.coef_sample))
    cl = dict(zip(result.model.terms[1], result.coef_line))
    # x_new = x' + a0 + a1 (x' - x0) / scale = c + m x'  with  m = 1 + a1/scale,  c = a0 - a1 x0/scale (GDAL px);
    # RPCModel.with_image_affine does the exact half-pixel bookkeeping of the raw RPC00B offsets.
    return rpc.with_image_affine(cs.get((0, 0), 0.0) - cs.get((1, 0), 0.0) * s0 / ss,
                                 cl.get((0, 0), 0.0) - cl.get((0, 1), 0.0) * l0 / ls,
                                 1.0 + cs.get((1, 0), 0.0) / ss, 1.0 + cl.get((0, 1), 0.0) / ls,
                                 pixel_convention="gdal")


def apply_compensation(rpc, result: CompensationResult, *, image_size: Optional[Tuple[int, int]] = None,
                       progress=None, **fit_kw) -> AppliedCompensation:
    """Write the correction into a new RPC (METHODS §4.2); the input RPC object is not modified.

    Translation and per-axis scale fold exactly into the offsets/scales (``RPCModel.with_image_affine``). Other
    terms are applied by refitting an RPC (METHODS §3, :func:`gdal_gf4cal.rpc_fit.fit_rpc_from_model`) on the
    composition of the RPC and the correction, over the image extent (``image_size`` = (width, height), default from
    the RPC offsets/scales) and the RPC's height range; the refit's check error (independent grid) is reported.
    """
    if result.model.foldable:
        return AppliedCompensation(rpc=_fold(rpc, result), exact=True)
    from .rpc_fit import fit_rpc_from_model
    comp = CompensatedRPC(rpc, result)
    size = tuple(image_size) if image_size is not None else tuple(rpc.image_size)
    fit_kw.setdefault("height_range", tuple(rpc.height_range))
    new_rpc, report = fit_rpc_from_model(comp, size=size, progress=progress, **fit_kw)
    return AppliedCompensation(rpc=new_rpc, exact=False, refit_max_px=float(report.max_px),
                               refit_rms_px=float(report.rms_px), fit_report=report)
