"""Separate views of one area with known per-view biases: the test bed of bundle adjustment (METHODS §10, §11).

Each view is an RPC00B built directly from a viewing geometry (no orbit integration, so 10 views cost nothing):
image axes rotated by ``azimuth_deg`` from east/south, a parallax of ``tan(incidence)`` pixels per metre of height
along and across track, a ground sample distance, and a mild quadratic distortion, all written as the RPC's
numerator polynomials (constant denominators), so the RPC is the view's exact *vendor* model. The truth is the
vendor model plus an image-space bias per view (:class:`~gdal_gf4cal.compensation.CompensationResult`, the bases
of METHODS §4.1: a translation of a few pixels plus a small affine), evaluated at the vendor-predicted coordinates
as the bundle adjustment models it. Tie points are ground points on a smooth terrain seen by the views whose image
contains them, measured at their true image position plus Gaussian noise; GCPs likewise, with known ground.

Geometries: ``tri-stereo`` (forward / nadir / backward along track, one pass), ``stereo`` (two along-track views),
``multi-date`` (views from different passes: across-track incidences and small azimuth changes, footprints shifted
so the ties do not cover every image). Every draw comes from ``numpy.random.default_rng(seed)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import pandas as pd

from ..compensation import CompensationResult
from ..geodesy import metres_per_degree
from ..rpc import RPCModel
from .building import SimulationError

__all__ = ["ViewGeometry", "SimViews", "view_rpc", "view_geometries", "simulate_views"]


@dataclass(frozen=True)
class ViewGeometry:
    """One view: ``name``; ``incidence_along_deg`` / ``incidence_across_deg`` (parallax per metre of height is
    ``tan`` of them, in ground metres); ``azimuth_deg`` (image axes' rotation from east / south); ``offset_m``
    (footprint centre from the scene centre, east and north); ``size`` (width, height) px; ``gsd_m``;
    ``quadratic_px`` (distortion at the image corners, px)."""

    name: str
    incidence_along_deg: float = 0.0
    incidence_across_deg: float = 0.0
    azimuth_deg: float = 0.0
    offset_m: Tuple[float, float] = (0.0, 0.0)
    size: Tuple[int, int] = (8000, 8000)
    gsd_m: float = 0.7
    quadratic_px: float = 2.0


def view_rpc(geom: ViewGeometry, center: Tuple[float, float], h0: float = 100.0, h_scale: float = 500.0) -> RPCModel:
    """The RPC00B of one view (module docstring): exact, with a constant denominator."""
    lon0, lat0 = (float(c) for c in center)
    mx, my = (float(v) for v in metres_per_degree(lat0, h0))
    w, h = (int(v) for v in geom.size)
    half_x, half_y = 0.5 * w * geom.gsd_m, 0.5 * h * geom.gsd_m
    lon_c = lon0 + geom.offset_m[0] / mx
    lat_c = lat0 + geom.offset_m[1] / my
    lon_scale, lat_scale = 1.2 * half_x / mx, 1.2 * half_y / my
    az = np.radians(geom.azimuth_deg)
    # image x (samples) along the rotated east axis, y (lines) along the rotated south axis, in metres per
    # normalised ground unit; heights add tan(incidence) metres of apparent displacement per metre.
    e_l, n_p = lon_scale * mx, lat_scale * my
    ts, tl = np.tan(np.radians(geom.incidence_across_deg)), np.tan(np.radians(geom.incidence_along_deg))
    xs = np.array([np.cos(az) * e_l, np.sin(az) * n_p, ts * h_scale]) / geom.gsd_m   # d sample / d (L, P, H)
    yl = np.array([np.sin(az) * e_l, -np.cos(az) * n_p, tl * h_scale]) / geom.gsd_m  # d line / d (L, P, H)
    samp_num, line_num = np.zeros(20), np.zeros(20)
    s_scale, l_scale = 0.5 * w, 0.5 * h
    samp_num[1:4], line_num[1:4] = xs / s_scale, yl / l_scale
    q = geom.quadratic_px
    samp_num[7], samp_num[4] = q / s_scale / 1.44, 0.5 * q / s_scale / 1.44        # L^2, LP
    line_num[8], line_num[6] = q / l_scale / 1.44, 0.2 * q / l_scale               # P^2, PH
    den = np.zeros(20)
    den[0] = 1.0
    return RPCModel(line_off=0.5 * h - 0.5, samp_off=0.5 * w - 0.5, lat_off=lat_c, long_off=lon_c, height_off=h0,
                    line_scale=l_scale, samp_scale=s_scale, lat_scale=lat_scale, long_scale=lon_scale,
                    height_scale=h_scale, line_num=line_num, line_den=den, samp_num=samp_num, samp_den=den.copy(),
                    source=f"simulated view {geom.name}")


def view_geometries(kind: str, n_views: Optional[int] = None, *, size: Tuple[int, int] = (8000, 8000),
                    gsd_m: float = 0.7, seed: int = 0) -> List[ViewGeometry]:
    """The views of one acquisition pattern: ``stereo`` (2), ``tri-stereo`` (3) or ``multi-date`` (``n_views``,
    default 5)."""
    if kind == "stereo":
        angles = [(12.0, "fwd"), (-12.0, "bwd")]
    elif kind == "tri-stereo":
        angles = [(15.0, "fwd"), (0.0, "nadir"), (-15.0, "bwd")]
    elif kind == "multi-date":
        rng = np.random.default_rng(seed + 7919)
        n = 5 if n_views is None else int(n_views)
        if n < 2:
            raise SimulationError(f"multi-date needs 2 or more views, got {n}")
        half = 0.5 * min(size) * gsd_m
        return [ViewGeometry(f"d{k + 1:02d}", incidence_along_deg=float(rng.uniform(-10, 10)),
                             incidence_across_deg=float(rng.uniform(-25, 25)), azimuth_deg=float(rng.uniform(-8, 8)),
                             offset_m=tuple(float(v) for v in rng.uniform(-0.25 * half, 0.25 * half, 2)),
                             size=size, gsd_m=gsd_m) for k in range(n)]
    else:
        raise SimulationError(f"unknown view geometry {kind!r}; choose stereo, tri-stereo or multi-date")
    if n_views is not None and int(n_views) != len(angles):
        raise SimulationError(f"{kind} has {len(angles)} views, not {n_views}")
    return [ViewGeometry(name, incidence_along_deg=a, size=size, gsd_m=gsd_m) for a, name in angles]


@dataclass
class SimViews:
    """A simulated set of views (:func:`simulate_views`).

    ``models``: view -> vendor RPC (what the adjustment is given); ``truth``: view -> the true image-space bias
    (:class:`CompensationResult`, true image = vendor(ground) + bias(vendor(ground))); ``sizes``: view -> (w, h);
    ``observations``: the observation table (ties and GCPs, ``true_sample, true_line`` kept); ``points``: the true
    ground of every point (``point_id, kind, lon, lat, h``); ``geometries``; ``center``, ``h0``."""

    models: Dict[str, RPCModel]
    truth: Dict[str, CompensationResult]
    sizes: Dict[str, Tuple[int, int]]
    observations: pd.DataFrame
    points: pd.DataFrame
    geometries: List[ViewGeometry] = field(default_factory=list)
    center: Tuple[float, float] = (0.0, 0.0)
    h0: float = 0.0

    def true_image(self, view: str, lon, lat, h) -> Tuple[np.ndarray, np.ndarray]:
        """True image position (GDAL convention) of ground points in ``view``."""
        s, l = self.models[view].project(lon, lat, h)
        ds, dl = self.truth[view].correction(s, l)
        return np.asarray(s) + ds, np.asarray(l) + dl


def _terrain(lon, lat, center, h0, relief_m):
    mx, my = metres_per_degree(center[1], h0)
    e, n = (lon - center[0]) * mx, (lat - center[1]) * my
    return h0 + relief_m * (0.6 * np.sin(e / 900.0) * np.cos(n / 1300.0) + 0.4 * np.sin((e + n) / 2100.0))


def _biases(views: Sequence[str], sizes, rng, translation_px: float, affine_px: float):
    out = {}
    for v in views:
        w, h = sizes[v]
        cs = np.concatenate([rng.normal(0.0, translation_px, 1), rng.normal(0.0, affine_px, 2)])
        cl = np.concatenate([rng.normal(0.0, translation_px, 1), rng.normal(0.0, affine_px, 2)])
        out[v] = CompensationResult.from_coefficients("affine", (0.5 * w, 0.5 * w, 0.5 * h, 0.5 * h), cs, cl)
    return out


def _ground(rng, n, center, h0, relief_m, extent_m):
    mx, my = metres_per_degree(center[1], h0)
    e, nn = rng.uniform(-extent_m, extent_m, (2, n))
    lon, lat = center[0] + e / mx, center[1] + nn / my
    return lon, lat, _terrain(lon, lat, center, h0, relief_m)


def _observe(sim: SimViews, ids, kind, lon, lat, h, rng, sigma, min_views, role="control"):
    """Rows of the points seen (inside the image, 5 px margin) by >= ``min_views`` views."""
    rows = []
    seen = np.zeros(len(ids), int)
    per_view = {}
    for v in sim.models:
        s, l = sim.true_image(v, lon, lat, h)
        w, hh = sim.sizes[v]
        inside = (s > 5) & (s < w - 5) & (l > 5) & (l < hh - 5)
        per_view[v] = (s, l, inside)
        seen += inside
    keep = seen >= min_views
    roles = np.broadcast_to(np.asarray(role, dtype=object), (len(ids),))
    for v, (s, l, inside) in per_view.items():
        m = inside & keep
        k = int(m.sum())
        sig = float(sigma[v])
        rows.append(pd.DataFrame({
            "point_id": np.asarray(ids)[m], "image_id": v, "kind": kind,
            "sample": s[m] + rng.normal(0.0, sig, k), "line": l[m] + rng.normal(0.0, sig, k), "sigma": sig,
            "role": roles[m], "lon": lon[m] if kind == "gcp" else np.nan, "lat": lat[m] if kind == "gcp" else np.nan,
            "h": h[m] if kind == "gcp" else np.nan, "true_sample": s[m], "true_line": l[m]}))
    return pd.concat(rows, ignore_index=True), keep


def simulate_views(kind: str = "tri-stereo", n_views: Optional[int] = None, *, n_ties: int = 300, n_gcps: int = 0,
                   n_check: int = 0, noise_px=0.2, translation_px: float = 2.0, affine_px: float = 0.3,
                   size: Tuple[int, int] = (8000, 8000), gsd_m: float = 0.7, center=(5.27, 44.17),
                   h0: float = 800.0, relief_m: float = 300.0, seed: int = 0) -> SimViews:
    """Views, true biases and observations (module docstring) with fixed seeds.

    ``noise_px``: tie/GCP measurement noise, one value or one per view (the table's ``sigma`` is the true one);
    ``translation_px`` / ``affine_px``: standard deviations of the true biases' constant and slope terms (px at the
    image edge). GCPs (``n_gcps`` control, ``n_check`` check) are ground points seen by one view or more.
    """
    rng = np.random.default_rng(seed)
    geoms = view_geometries(kind, n_views, size=size, gsd_m=gsd_m, seed=seed)
    models = {g.name: view_rpc(g, center, h0) for g in geoms}
    sizes = {g.name: tuple(int(v) for v in g.size) for g in geoms}
    truth = _biases(list(models), sizes, rng, translation_px, affine_px)
    sigma = {v: float(np.broadcast_to(np.asarray(noise_px, float), (len(geoms),))[k])
             for k, v in enumerate(models)}
    sim = SimViews(models, truth, sizes, pd.DataFrame(), pd.DataFrame(), geoms, tuple(center), float(h0))
    extent = 0.55 * min(size) * gsd_m
    lon, lat, h = _ground(rng, int(n_ties * 1.6) + 10, center, h0, relief_m, extent)
    ids = np.array([f"t{i:06d}" for i in range(lon.size)], dtype=object)
    ties, keep = _observe(sim, ids, "tie", lon, lat, h, rng, sigma, 2)
    first = ids[keep][:n_ties]
    ties = ties[ties["point_id"].isin(set(first))]
    pts = [pd.DataFrame({"point_id": ids[keep][:n_ties], "kind": "tie", "lon": lon[keep][:n_ties],
                         "lat": lat[keep][:n_ties], "h": h[keep][:n_ties]})]
    tables = [ties]
    if n_gcps + n_check:
        g_lon, g_lat, g_h = _ground(rng, 4 * (n_gcps + n_check) + 10, center, h0, relief_m, 0.8 * extent)
        g_ids = np.array([f"g{i:04d}" for i in range(g_lon.size)], dtype=object)
        role = np.where(np.arange(g_lon.size) % 2 == 0, "control", "check")
        gcps, gkeep = _observe(sim, g_ids, "gcp", g_lon, g_lat, g_h, rng, sigma, 1, role)
        take = set(g_ids[gkeep & (role == "control")][:n_gcps]) | set(g_ids[gkeep & (role == "check")][:n_check])
        tables.append(gcps[gcps["point_id"].isin(take)])
        sel = np.isin(g_ids, list(take))
        pts.append(pd.DataFrame({"point_id": g_ids[sel], "kind": "gcp", "lon": g_lon[sel], "lat": g_lat[sel],
                                 "h": g_h[sel]}))
    sim.observations = pd.concat(tables, ignore_index=True)
    sim.points = pd.concat(pts, ignore_index=True)
    return sim
