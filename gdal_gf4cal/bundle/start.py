"""Starting ground positions of the bundle's points and the a-priori weights (METHODS §7, §11).

Ties start at their multi-view intersection with the vendor RPCs (:func:`gdal_gf4cal.intersection.intersect`);
where it fails or the rays are nearly parallel (height standard deviation above :data:`PARALLEL_SIGMA_M` for 1 px
measurements) the DEM's (mean of the rays' line-of-sight intersections) when one is given. GCPs start at their
known ground. With a DEM every tie's height is observed ``DEM(lon, lat) ± dem_sigma_m`` (as ASP's
``--heights-from-dem``): along the epipolar direction a relative bias of the views is a height shift of all ties,
which ties alone cannot see; the DEM's absolute heights fix it. Without a DEM the views' priors hold the datum.
"""
from __future__ import annotations

from typing import List, Mapping, Tuple

import numpy as np

from ..intersection import intersect
from .model import BundleError, Rays, ViewLayout
from .solve import Weights, resample_dem

__all__ = ["PARALLEL_SIGMA_M", "DEFAULT_DEM_SIGMA_M", "start_ground", "base_weights"]

#: σ (m) of the DEM's height prior on every tie: a global DEM's typical absolute height accuracy (SRTM, Copernicus:
#: a few metres; ~5 m with the terrain's share).
DEFAULT_DEM_SIGMA_M = 5.0

#: Height standard deviation (m, for 1 px image noise) above which the rays of a tie are "nearly parallel": the DEM
#: gives its start (and its weak prior matters there).
PARALLEL_SIGMA_M = 100.0

#: The intersection start stops a point when its step is below this (m): the bundle's Gauss-Newton moves every tie
#: anyway (a vendor bias moves them by metres), a finer start costs one more projection of every ray.
START_TOL_M = 0.01


def _image_points(layout: ViewLayout, rays: Rays, sel: np.ndarray) -> np.ndarray:
    """(n_views, n_sel, 2) measurements of the points ``sel`` (NaN where a view does not see one)."""
    pos = np.full(rays.n_points, -1)
    pos[sel] = np.arange(sel.size)
    pts = np.full((len(layout.views), sel.size, 2), np.nan)
    r = np.flatnonzero(pos[rays.point] >= 0)
    pts[rays.view[r], pos[rays.point[r]]] = rays.meas[r]
    return pts


def _dem_start(models, layout: ViewLayout, rays: Rays, todo: np.ndarray, dem) -> np.ndarray:
    """Mean of the rays' DEM intersections of the points ``todo`` (n_points bool) -> (n_points, 3), NaN elsewhere."""
    acc = np.zeros((rays.n_points, 3))
    cnt = np.zeros(rays.n_points)
    for j, v in enumerate(layout.views):
        r = np.flatnonzero((rays.view == j) & todo[rays.point])
        if r.size == 0:
            continue
        lon, lat, h = models[v].localize_dem(rays.meas[r, 0], rays.meas[r, 1], dem)
        g = np.stack([lon, lat, h], axis=1)
        ok = np.all(np.isfinite(g), axis=1)
        np.add.at(acc, rays.point[r[ok]], g[ok])
        np.add.at(cnt, rays.point[r[ok]], 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return acc / cnt[:, None]


def start_ground(models: Mapping[str, object], layout: ViewLayout, rays: Rays, dem=None,
                 progress=None) -> Tuple[np.ndarray, np.ndarray, List[str]]:
    """``(ground (n_points, 3), parallel (n_points,) bool, notes)``: intersection, the DEM where rays are nearly
    parallel (``parallel``: those ties), GCPs as given."""
    ground = rays.ground.copy()
    notes: List[str] = []
    ties = np.flatnonzero(~rays.point_is_gcp)
    h0 = float(np.mean(models[layout.views[0]].height_range))
    if dem is not None:
        try:
            h0 = float(np.nanmean(dem.sample(np.atleast_1d(models[layout.views[0]].long_off),
                                             np.atleast_1d(models[layout.views[0]].lat_off))))
        except Exception:                                        # any failure: the RPC's mid height
            pass
    res = intersect([models[v] for v in layout.views], _image_points(layout, rays, ties), sigma_px=1.0,
                    h0=h0, progress=progress, tol_m=START_TOL_M, final_pass=False)   # σ_h: last step's
    g = np.stack([res.lon, res.lat, res.h], axis=1)
    weak = ~np.all(np.isfinite(g), axis=1) | ~(res.sigma_height_m <= PARALLEL_SIGMA_M)
    ground[ties] = g
    bad = np.zeros(rays.n_points, bool)
    bad[ties[weak]] = True
    if bad.any() and dem is not None:
        d = _dem_start(models, layout, rays, bad, dem)
        fill = bad & np.all(np.isfinite(d), axis=1)
        ground[fill] = d[fill]
        notes.append(f"{int(fill.sum())} tie(s) with nearly parallel rays started on the DEM")
    lost = ~np.all(np.isfinite(ground), axis=1)
    if lost.any():
        lon, lat = models[layout.views[0]].localize(np.zeros(1), np.zeros(1), h0)
        ground[lost] = [float(np.atleast_1d(lon)[0]), float(np.atleast_1d(lat)[0]), h0]
        notes.append(f"{int(lost.sum())} tie(s) could not be intersected; started at the scene centre")
    return ground, bad, notes


def base_weights(models, layout: ViewLayout, rays: Rays, ground: np.ndarray, dem=None, *,
                 gcp_sigma_m: float = 0.01, dem_sigma_m: float = DEFAULT_DEM_SIGMA_M) -> Weights:
    """A-priori weights: rays ``1 / sigma^2`` (control rows; check rows 0), control GCPs' ground ``1 /
    gcp_sigma_m^2``, with a DEM every tie's height ``1 / dem_sigma_m^2`` (the DEM's height at the tie's current
    ground, re-sampled as it moves: :func:`~gdal_gf4cal.bundle.solve.resample_dem`), the datum prior
    ``1 / prior^2``."""
    w_rays = np.where(rays.control, 1.0 / rays.sigma ** 2, 0.0)
    w_ground = np.zeros((rays.n_points, 3))
    obs = np.full((rays.n_points, 3), np.nan)
    ctrl_gcp = rays.point_is_gcp & rays.point_control
    w_ground[ctrl_gcp] = 1.0 / float(gcp_sigma_m) ** 2
    obs[rays.point_is_gcp] = rays.ground[rays.point_is_gcp]
    wts = Weights(rays=w_rays, ground=w_ground, prior=1.0 / layout.prior_px ** 2, ground_obs=obs)
    if dem is None:
        return wts
    if not (np.isfinite(dem_sigma_m) and dem_sigma_m > 0):
        raise BundleError(f"the DEM's height sigma must be a positive number of metres, got {dem_sigma_m!r}")
    ties = ~rays.point_is_gcp
    wts.dem, wts.dem_points = dem, ties
    wts = resample_dem(wts, ground)
    wts.ground[ties & np.isfinite(wts.ground_obs[:, 2]), 2] = 1.0 / float(dem_sigma_m) ** 2
    return wts
