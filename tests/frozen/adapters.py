"""Adapters: the ONLY place where tests/frozen touches result objects (issue 10, item 1).

Each function takes a result object of today's public API and returns plain numbers (float, int, bool, lists of
them, dicts of them). When a refactor changes a result class, re-point the body of the matching adapter here; the
frozen JSON fixtures and the comparisons stay as they are.
"""
from __future__ import annotations

from typing import Any, Dict, List

import numpy as np


def _floats(x) -> List[float]:
    return [float(v) for v in np.asarray(x, float).ravel()]


# ------------------------------------------------------------------------------------ compensation (METHODS §4)
def comp_params(result) -> Dict[str, float]:
    """Estimated coefficients by name (px), e.g. ``{'sample_1': .., 'line_v': ..}``."""
    return {k: float(v) for k, v in result.parameters.items()}


def comp_param_std(result) -> Dict[str, float]:
    """A-posteriori standard deviations of the coefficients by name (px)."""
    return {k: float(v) for k, v in result.parameter_std.items()}


def comp_sigma0(result) -> List[float]:
    """A-posteriori sigma of unit weight ``[sample, line]``."""
    return [float(result.sigma0_px[0]), float(result.sigma0_px[1])]


def comp_redundancy(result) -> int:
    return int(result.redundancy)


def comp_outlier_flags(result) -> List[bool]:
    """Outlier flag per input GCP, in input order."""
    return [bool(v) for v in result.gcps["outlier"].to_numpy(bool)]


def comp_rms(result) -> Dict[str, float]:
    """Control/check RMS (px) per axis before/after, flagged outliers left out: ``{'control_after_sample': ..}``."""
    acc = result.accuracy()
    out = {}
    for role in ("control", "check"):
        for when in ("before", "after"):
            for axis in ("sample", "line"):
                v = acc[role][when][axis]["rms"]
                out[f"{role}_{when}_{axis}"] = None if v is None else float(v)
    return out


# ------------------------------------------------------------------------------------ look angles (METHODS §5)
def la_coefficients(calib) -> Dict[str, List[float]]:
    """New camera coefficients ``x`` (a0..a9), ``y`` (b0..b9) (tan units)."""
    return {"x": _floats(calib.camera.x), "y": _floats(calib.camera.y)}


def la_tan_grid(calib, n: int = 5) -> Dict[str, List[float]]:
    """Tan-angles of the new camera on an ``n x n`` grid over the array (pixel edges, GDAL convention)."""
    w, h = (float(v) for v in calib.camera.size)
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, w, n), np.linspace(0, h, n)))
    tx, ty = calib.camera.tan_angles(S, L)
    return {"tan_x": _floats(tx), "tan_y": _floats(ty)}


def la_precision(calib) -> Dict[str, float]:
    p = calib.precision_px()
    return {f"{axis}_{k}": float(p[axis][k]) for axis in ("sample", "line") for k in ("rms", "max")}


def la_outlier_flags(calib) -> List[bool]:
    return [bool(v) for v in np.asarray(calib.outliers, bool)]


def la_residual_rms(calib) -> Dict[str, float]:
    """RMS (px) of the residuals after calibration per axis, over non-outlier GCPs; plus sigma0."""
    r = np.asarray(calib.residuals_after, float)
    keep = ~np.asarray(calib.outliers, bool)
    return {"sample": float(np.sqrt(np.mean(r[keep, 0] ** 2))), "line": float(np.sqrt(np.mean(r[keep, 1] ** 2))),
            "sigma0": float(calib.sigma0), "n_outliers": int(calib.n_outliers)}


# ------------------------------------------------------------------------------------ intersection (METHODS §7)
def ix_coordinates(res) -> Dict[str, List[float]]:
    return {"lon": _floats(res.lon), "lat": _floats(res.lat), "h": _floats(res.h)}


def ix_sigmas(res) -> Dict[str, List[float]]:
    return {"sigma_planar_m": _floats(res.sigma_planar_m), "sigma_height_m": _floats(res.sigma_height_m),
            "sigma0": _floats(res.sigma0)}


def ix_covariance(res) -> List[float]:
    """``cov_enu_m2`` flattened (N*9 values, m^2)."""
    return _floats(res.cov_enu_m2)


# ------------------------------------------------------------------------------------ RPC fit (METHODS §3)
def rpcfit_errors(report) -> Dict[str, float]:
    """Fit and check errors (px) of :func:`fit_rpc_from_model`."""
    out = {}
    for name, e in (("fit", report.fit), ("check", report.check)):
        for k in ("rms_sample_px", "rms_line_px", "rms_px", "max_sample_px", "max_line_px", "max_px"):
            out[f"{name}_{k}"] = float(getattr(e, k))
    return out


# ------------------------------------------------------------------------------------ experiments (METHODS §8-10)
_SKIP_KEYS = {"elapsed_s", "time", "outputs", "files"}


def experiment_numbers(rep: Any, prefix: str = "") -> Dict[str, Any]:
    """Flatten an experiment report into ``{'table3/rpc/sample/rms': 0.61, ...}`` (numbers, bools, None only)."""
    out: Dict[str, Any] = {}
    if isinstance(rep, dict):
        for k, v in rep.items():
            if str(k) in _SKIP_KEYS:
                continue
            out.update(experiment_numbers(v, f"{prefix}{k}/"))
    elif isinstance(rep, (list, tuple)):
        for i, v in enumerate(rep):
            out.update(experiment_numbers(v, f"{prefix}{i}/"))
    elif isinstance(rep, (bool, np.bool_)):
        out[prefix.rstrip("/")] = bool(rep)
    elif isinstance(rep, (int, float, np.integer, np.floating)) or rep is None:
        out[prefix.rstrip("/")] = None if rep is None else float(rep)
    return out
