"""Multi-image least-squares forward intersection with RPC models (METHODS §7).

A ground point seen in two or more images is the ``(lon, lat, h)`` minimising the weighted image residuals
``measured - model.project(lon, lat, h)`` over all images that observe it. The models are anything with
``project`` (and preferably ``project_jacobian``) in the GDAL pixel convention: plain RPCs or RPCs with their
compensation (:class:`gdal_gf4cal.compensation.CompensatedRPC`). Gauss-Newton runs on all points at once, with the
unknowns in local metres (east, north, up) so that the 3x3 normal equations are well conditioned and their inverse
is directly the covariance in m^2.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional, Sequence

import numpy as np

from .errors import DegenerateGeometryError, GCPError
from .geodesy import metres_per_degree
from .estimation import Estimate, solve_with_points, unit_weight_sigma
from .progress import report as _report
from .stats import axis_stats, ce90, le90, planar_stats
from .stats import model_jacobian as _jacobian

__all__ = ["IntersectionResult", "intersect", "ground_errors_m", "intersection_accuracy"]


def _radii(lat_deg, h):
    """Metres per degree of longitude and of latitude (:func:`gdal_gf4cal.geodesy.metres_per_degree`)."""
    return metres_per_degree(lat_deg, h)


def ground_errors_m(lon, lat, h, lon_ref, lat_ref, h_ref):
    """East, north, up differences (m) of ``(lon, lat, h)`` from a reference (small-offset local frame)."""
    lon, lat, h, lon_ref, lat_ref, h_ref = (np.asarray(a, dtype=float) for a in (lon, lat, h, lon_ref, lat_ref, h_ref))
    mx, my = _radii(lat_ref, h_ref)
    dlon = (lon - lon_ref + 180.0) % 360.0 - 180.0
    return dlon * mx, (lat - lat_ref) * my, h - h_ref


@dataclass
class IntersectionResult:
    """Intersected ground points and their quality (METHODS §7).

    Attributes
    ----------
    lon, lat, h : ndarray (N,)
        Ground coordinates (deg, deg, ellipsoidal m); NaN where fewer than 2 images observe the point or
        Gauss-Newton did not converge.
    residuals : ndarray (n_images, N, 2)
        ``(sample, line)`` residuals, measured - predicted (px); NaN where not observed.
    n_images : ndarray (N,) of int
        Images observing each point.
    cov_enu_m2 : ndarray (N, 3, 3)
        Covariance of (east, north, up) in m^2 for image-measurement sigma ``sigma_px`` (a-priori).
    sigma0 : ndarray (N,)
        A-posteriori RMS of weighted residuals per point (redundancy = 2 n_images - 3), NaN without redundancy.
    converged : ndarray (N,) of bool
    redundancy : ndarray (n_images, N, 2)
        Redundancy numbers ``1 - w a^T N^-1 a`` of the observations (0 where not observed or not converged).
    weights : ndarray (n_images, N, 2)
        ``1 / sigma_px^2`` of the observations (0 where not observed).
    """

    lon: np.ndarray
    lat: np.ndarray
    h: np.ndarray
    residuals: np.ndarray
    n_images: np.ndarray
    cov_enu_m2: np.ndarray
    sigma0: np.ndarray
    converged: np.ndarray
    redundancy: Optional[np.ndarray] = None
    weights: Optional[np.ndarray] = None

    def estimate(self, i: int):
        """Point ``i`` as the one result class :class:`gdal_gf4cal.estimation.Estimate` (METHODS §4, §7).

        One block ``enu`` (``east_m, north_m, up_m``): the intersection's local frame at the solution, so ``x`` is
        zero and ``cov`` is :attr:`cov_enu_m2` ``[i]`` (a-priori, unchanged); observations are the point's
        ``(sample, line)`` per image, in image order (``residuals`` NaN, weight 0 where an image does not see
        it); ``sigma0`` and ``dof = 2 n_images - 3`` as in :attr:`sigma0`, normalised residuals
        ``v / (sigma0 sqrt(r / w))``.
        """
        res = self.residuals[:, i].reshape(-1)
        w = (np.zeros_like(res) if self.weights is None else self.weights[:, i].reshape(-1))
        red = np.zeros_like(res) if self.redundancy is None else self.redundancy[:, i].reshape(-1)
        s0 = float(self.sigma0[i])
        with np.errstate(divide="ignore", invalid="ignore"):
            norm = np.where((w > 0) & (red > 1e-12) & np.isfinite(s0),
                            res / (s0 * np.sqrt(red / np.where(w > 0, w, 1.0))), np.nan)
        return Estimate(names=["east_m", "north_m", "up_m"], x=np.zeros(3), cov=np.array(self.cov_enu_m2[i]),
                        sigma0=s0, dof=int(2 * self.n_images[i] - 3), redundancy=red, residuals=res,
                        normalised=norm, weights=w, blocks={"enu": slice(0, 3)}, iterations=0)

    @property
    def sigma_planar_m(self) -> np.ndarray:
        """Predicted planar standard error sqrt(var_e + var_n) (m)."""
        return np.sqrt(self.cov_enu_m2[:, 0, 0] + self.cov_enu_m2[:, 1, 1])

    @property
    def sigma_height_m(self) -> np.ndarray:
        """Predicted height standard error (m)."""
        return np.sqrt(self.cov_enu_m2[:, 2, 2])


def intersect(models: Sequence[Any], image_points, *, sigma_px=1.0, h0: Optional[float] = None,
              max_iter: int = 30, tol_m: float = 1e-4, progress=None, final_pass: bool = True) -> IntersectionResult:
    """Least-squares forward intersection from ``>= 2`` images (METHODS §7).

    Parameters
    ----------
    models : sequence of RPCModel / CompensatedRPC
        One ground-to-image model per image (GDAL pixel convention).
    image_points : array_like (n_images, N, 2)
        ``(sample, line)`` of each point in each image (GDAL convention); NaN where an image does not see it.
    sigma_px : float or array_like (n_images,) or (n_images, N)
        Image measurement standard deviation (px) -> weights and the a-priori covariance.
    h0 : float, optional
        Starting height (default: the first model's height offset, else 0).
    final_pass : bool
        False: no last linearisation at the solution (one projection of every ray fewer): the covariance is
        that of each point's last step (linearised within ``tol_m`` of the solution), residuals NaN, redundancy
        and ``sigma0`` not computed (zeros, NaN).

    Returns
    -------
    IntersectionResult
    """
    models = list(models)
    pts = np.asarray(image_points, dtype=float)
    if pts.ndim == 2 and pts.shape[-1] == 2:
        pts = pts[:, None, :]
    if pts.ndim != 3 or pts.shape[0] != len(models) or pts.shape[2] != 2:
        raise GCPError(f"image_points must have shape (n_images={len(models)}, N, 2), got {pts.shape}")
    if len(models) < 2:
        raise DegenerateGeometryError("forward intersection needs at least 2 images; give two or more RPCs")
    n_img, n_pts = pts.shape[:2]
    obs = np.all(np.isfinite(pts), axis=2)                        # (n_img, N)
    n_obs = obs.sum(axis=0)
    sig = np.broadcast_to(np.asarray(sigma_px, dtype=float).reshape(
        (n_img, -1) if np.ndim(sigma_px) >= 1 else (1, 1)), (n_img, n_pts))
    wgt = np.where(obs, 1.0 / sig ** 2, 0.0)
    if h0 is None:
        h0 = float(np.mean(models[0].height_range))     # the RPC's HEIGHT_OFF; any SensorModel has height_range
    lon, lat, h = _start(models, pts, obs, float(h0))
    active = (n_obs >= 2) & np.isfinite(lon) & np.isfinite(lat)
    converged = np.zeros(n_pts, bool)
    cov = np.full((n_pts, 3, 3), np.nan)

    for it in range(max_iter):
        _report(progress, it / max_iter, "intersecting")
        idx = np.flatnonzero(active & ~converged)
        if idx.size == 0:
            break
        r, w, jac, mx, my = _linearise(models, pts, obs, wgt, (lon, lat, h), idx)
        # The ground point of each tie point is a point block: solved (eliminated) per point (estimation.schur).
        sol = solve_with_points(jac, r, w, det_min=1e-30, covariance=not final_pass)
        step = sol.dx_points
        bad = ~sol.ok | ~np.all(np.isfinite(step), axis=1)
        active[idx[bad]] = False
        good = ~bad
        g = idx[good]
        if not final_pass:
            cov[g] = sol.cov_points[good]
        lon[g] += step[good, 0] / mx[good]
        lat[g] += step[good, 1] / my[good]
        h[g] += step[good, 2]
        converged[g] = np.linalg.norm(step[good], axis=1) < tol_m
    fin = active & converged
    cov[~fin] = np.nan
    res = np.full((n_img, n_pts, 2), np.nan)
    redundancy = np.zeros((n_img, n_pts, 2))
    sigma0 = np.full(n_pts, np.nan)
    if final_pass:
        sigma0 = _final_pass(models, pts, obs, wgt, (lon, lat, h), fin, res, cov, redundancy)
    lon = np.where(fin, lon, np.nan)
    lat = np.where(fin, lat, np.nan)
    h = np.where(fin, h, np.nan)
    _report(progress, 1.0, "intersected")
    return IntersectionResult(lon=lon, lat=lat, h=h, residuals=res, n_images=n_obs.astype(int),
                              cov_enu_m2=cov, sigma0=sigma0, converged=fin, redundancy=redundancy,
                              weights=np.repeat(wgt[..., None], 2, axis=2))


def _final_pass(models, pts, obs, wgt, llh, fin, res, cov, redundancy) -> np.ndarray:
    """Residuals, covariance and redundancy at the solution of the points ``fin`` (in place); returns ``sigma0``."""
    n_img = len(models)
    idx = np.flatnonzero(fin)
    if idx.size:
        r, w, jac, _, _ = _linearise(models, pts, obs, wgt, llh, idx)
        res[:, idx] = r.reshape(idx.size, n_img, 2).transpose(1, 0, 2)
        cov[idx] = solve_with_points(jac, r, w, det_min=-1.0).cov_points
        q = np.einsum("nri,nij,nrj->nr", jac, cov[idx], jac)
        redundancy[:, idx] = np.where(w > 0, 1.0 - w * q, 0.0).reshape(idx.size, n_img, 2).transpose(1, 0, 2)
    wr2 = np.nansum(wgt[..., None] * np.nan_to_num(res) ** 2, axis=(0, 2))
    return np.where(fin, unit_weight_sigma(wr2, 2 * obs.sum(axis=0) - 3), np.nan)   # redundancy 2 n_images - 3


def _start(models, pts, obs, h0: float):
    """Start: each point localised in the first image observing it, at height ``h0``."""
    n_img, n_pts = pts.shape[:2]
    lon = np.full(n_pts, np.nan)
    lat = np.full(n_pts, np.nan)
    h = np.full(n_pts, h0)
    for k in range(n_img):
        todo = np.isnan(lon) & obs[k]
        if todo.any():
            lo, la = models[k].localize(pts[k, todo, 0], pts[k, todo, 1], h[todo])
            lon[todo], lat[todo] = lo, la
    return lon, lat, h


def _linearise(models, pts, obs, wgt, llh, idx):
    """Residuals (n, 2 n_img), weights and d(sample, line)/d(east, north, up) (n, 2 n_img, 3) in px/m of the
    points ``idx`` at ``llh = (lon, lat, h)``, and the metres per degree ``mx, my``."""
    lon, lat, h = (a[idx] for a in llh)
    n_img = len(models)
    mx, my = _radii(lat, h)
    to_m = np.stack([mx, my, np.ones_like(mx)], -1)
    res_k = np.full((idx.size, n_img, 2), np.nan)                # NaN / 0 where an image does not see a point
    jac_k = np.zeros((idx.size, n_img, 2, 3))
    for k in range(n_img):
        sel = np.flatnonzero(obs[k, idx])                          # only the rays that exist are projected
        if sel.size == 0:
            continue
        s, l = models[k].project(lon[sel], lat[sel], h[sel])
        res_k[sel, k, 0] = pts[k, idx[sel], 0] - s
        res_k[sel, k, 1] = pts[k, idx[sel], 1] - l
        jac_k[sel, k] = _jacobian(models[k], lon[sel], lat[sel], h[sel]) / to_m[sel, None, :]
    w = np.repeat(wgt[:, idx].T, 2, axis=1)
    return res_k.reshape(idx.size, 2 * n_img), w, jac_k.reshape(idx.size, 2 * n_img, 3), mx, my


def intersection_accuracy(result: IntersectionResult, lon_true, lat_true, h_true) -> Dict[str, Any]:
    """Planar and height errors (m) of intersected points against known ground truth (METHODS §6, §7).

    Returns ``n``, per-axis ``east/north/height`` mean/rms/max, ``planar_rms_m`` (sqrt(mean(e^2 + n^2))),
    ``height_rms_m``, ``ce90_m`` and ``le90_m``.
    """
    e, n, u = ground_errors_m(result.lon, result.lat, result.h, lon_true, lat_true, h_true)
    ok = np.isfinite(e) & np.isfinite(n) & np.isfinite(u)
    e, n, u = e[ok], n[ok], u[ok]
    if not ok.any():
        return {"n": 0, "planar_rms_m": None, "height_rms_m": None, "ce90_m": None, "le90_m": None}

    def ax(x):
        return {k: v for k, v in axis_stats(x).items() if k in ("mean", "rms", "max")}

    return {"n": int(ok.sum()), "east": ax(e), "north": ax(n), "height": ax(u),
            "planar_rms_m": planar_stats(e, n)["rms"], "height_rms_m": axis_stats(u)["rms"],
            "ce90_m": ce90(e, n), "le90_m": le90(u)}
