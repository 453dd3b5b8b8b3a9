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

This module holds the model (:class:`CompensationModel`), the correction (:class:`CompensationResult`) and applying it
(:class:`CompensatedRPC`, :func:`apply_compensation` -> :class:`AppliedCompensation`); estimating is
:mod:`.solve` (:func:`fit_compensation`), reporting :mod:`.outputs`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..basis import detector_terms, monomial_derivatives, monomials, term_name
from ..errors import GCPError
from ..estimation import Estimate
from ..rpc_fit import fit_rpc_from_model
from ..sensor import GDAL_PIXEL_OFFSET, SensorModelMixin, pixel_shift
from .outputs import _f, accuracy_by_role, suspected_blunders

__all__ = ["MODEL_NAMES", "CompensationModel", "CompensationResult", "CompensatedRPC", "AppliedCompensation",
           "apply_compensation"]

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
    comp = CompensatedRPC(rpc, result)
    size = tuple(image_size) if image_size is not None else tuple(rpc.image_size)
    fit_kw.setdefault("height_range", tuple(rpc.height_range))
    new_rpc, report = fit_rpc_from_model(comp, size=size, progress=progress, **fit_kw)
    return AppliedCompensation(rpc=new_rpc, exact=False, refit_max_px=float(report.max_px),
                               refit_rms_px=float(report.rms_px), fit_report=report)
