"""Jilin-1 KF01A wide-field camera group: the multi-CCD / multi-band block-calibration test bed (METHODS §8, §10).

One group = 4 TDI CCDs (pan 0.75 m, 8192 detectors each) mechanically staggered in two rows 0.6 s apart along track,
each with four MS bands (3 m, 2048 detectors: blue, green, red, nir) at their own along-track focal-plane offsets.
The platform is yaw-steered (as ZY-3) so that the Earth's rotation during the stagger does not skew the two CCD rows
apart: adjacent CCDs overlap by ~200 pan pixels at every latitude.

Truth (every term recorded in ``truth.json``):

* interior per CCD and band: image displacement ``true - current`` cubic in the normalised detector position
  ``u = (s - W/2) / (W/2)``, ``I_s(u) = sum a_j u^j``, ``I_l(u) = sum b_j u^j`` (px of that band), drawn so that the
  seams between adjacent CCDs (offset of the true positions relative to the current ones, CCD k+1 minus CCD k, in
  their overlap) are 2-5 px;
* exterior per group (shared by every CCD and band): constant roll/pitch/yaw offsets and roll/pitch drift
  (METHODS §8: ``phi(t) = phi_u + phi_v t``, ``omega(t) = omega_u + omega_v t``, ``kappa = kappa_u``; ``t`` in s
  from the orbit reference time 0);
* optionally (``orbit_seed``) a per-orbit random attitude error, N(0, 3.6 arcsec) per axis, for validation scenes:
  10 orbits without control then give CE90 ~ 20 m;
* focal-plane positions ``X_k(u) = X0 + (W/2) u`` (cross-track) and ``Y_k`` (along-track), in px of the band.

``size=(W, H)`` crops shorten the CCDs to W pan detectors (MS: W/4) and the scene to H lines while keeping the
group's layout (stagger, band offsets, GSD, yaw steering) and the overlap between adjacent CCDs (200 pan px, or W/4
for W < 800): a cropped group is a small group of the same camera, so tests stay fast and keep every overlap.

:func:`block_observations` draws the long observation table (GCPs and tie points, METHODS §8) that
:func:`gdal_gf4cal.simulate.write_scene` writes as ``observations.csv``.
"""
from __future__ import annotations

import copy
import os
from typing import Any, Dict, List, Optional

import numpy as np
import pandas as pd

from .models import Attitude
from .scene import _write_csv, simulate_gcps
from .building import (ARCSEC, SENSORS, SensorSpec, CAMERA_TO_BODY, SimImage, SimulationError, _align_orbit, _crop_any, _linear_camera,
                      _poly_px, _pushbroom, _shift_center, _yaw_steering)

ALTITUDE_M = 535e3
INCLINATION_DEG = 97.5
PAN_GSD_M = 0.75
MS_GSD_M = 3.0
MS_FACTOR = 4                         # pan pixels per MS pixel
CCD_PX = 8192                         # pan detectors per CCD (MS: CCD_PX / MS_FACTOR)
N_CCD = 4
OVERLAP_PX = 200                      # nominal overlap of adjacent CCDs, pan px
STAGGER_S = 0.6                       # time between the two CCD rows
NOMINAL_SPEED_M_S = 7.0e3
MS_BANDS = ("blue", "green", "red", "nir")
BANDS = ("pan",) + MS_BANDS
#: Along-track focal-plane offset of each band from the pan line of its CCD, in pan pixels (angle / pan ifov).
BAND_OFFSET_PAN_PX = {"pan": 0.0, "blue": -1400.0, "green": -1000.0, "red": 1000.0, "nir": 1400.0}
#: Per-orbit random attitude error (validation scenes), per axis: CE90 ~ 20 m at 535 km (METHODS §8).
ORBIT_ATTITUDE_SIGMA_ARCSEC = 3.6
#: Seam magnitude drawn per adjacent pair and band, px of the band (the issue asks for 2-5 px).
SEAM_RANGE_PX = (2.5, 4.5)
#: Farthest latitude of a scene centre: the 97.5 deg orbit reaches 82.5 deg; keep the group's swath under it.
MAX_ABS_LAT_DEG = 80.0
REFERENCE_BAND = "blue"

IMAGE_NAMES = tuple(f"ccd{k + 1}" for k in range(N_CCD)) + tuple(
    f"ccd{k + 1}_{b}" for k in range(N_CCD) for b in MS_BANDS)


def image_name(ccd: int, band: str) -> str:
    """Image name of CCD ``ccd`` (1-based) and ``band``: ``ccd2`` (pan), ``ccd2_blue`` (MS)."""
    return f"ccd{ccd}" if band == "pan" else f"ccd{ccd}_{band}"


def _overlap_px(W: int) -> int:
    return OVERLAP_PX if W >= 4 * OVERLAP_PX else max(8, W // 4)


def build_jl1(rng, center, size, h_mid, *, orbit_seed: Optional[int] = None) -> List[SimImage]:
    """The 20 images (4 CCDs x pan + 4 MS bands) of one Jilin-1 group (METHODS §8, §10).

    Parameters
    ----------
    rng : numpy Generator (interior and exterior truth).
    center : (lon, lat) of the group's centre; |lat| <= :data:`MAX_ABS_LAT_DEG`.
    size : None (8192 x 8192 pan per CCD) or (W, H): W pan detectors per CCD, H pan lines (MS: W/4, H/4).
    h_mid : mean terrain height (m).
    orbit_seed : None (calibration scene) or a seed of the per-orbit attitude error (validation scenes).
    """
    W, H = _ccd_size(center, size)
    full_pan = (W, max(H, CCD_PX))
    overlap = _overlap_px(W)
    alt = ALTITUDE_M
    ifov = PAN_GSD_M / alt
    dty = STAGGER_S * NOMINAL_SPEED_M_S / alt
    ref = _linear_camera((CCD_PX, CCD_PX), ifov, 0.0, 0.0, "jl1 ref")
    orbit = _align_orbit(center, h_mid, alt, INCLINATION_DEG, ref, CAMERA_TO_BODY, CCD_PX / 2)
    # Yaw steering: the yaw that makes the leading row (looking dty/2 forward) see the centre with its central
    # detector; the trailing row then sees the same ground tracks, so the rows' CCDs overlap as designed.
    yaw0 = _yaw_steering(orbit, center, h_mid, (CCD_PX, CCD_PX), ifov, dty / 2)
    att_cur = Attitude(yaw=(yaw0,))
    ext = _exterior_error(rng)
    orbit_err = _orbit_attitude_error(orbit_seed)
    # The camera (interior, seams) is drawn against the group's exterior alone; the orbit's error is added last.
    att_group = Attitude(roll=(ext["roll_rad"], ext["roll_drift_rad_s"]), pitch=(ext["pitch_rad"],
                         ext["pitch_drift_rad_s"]), yaw=(yaw0 + ext["yaw_rad"],))
    att_true = Attitude(roll=(ext["roll_rad"] + orbit_err["roll_rad"], ext["roll_drift_rad_s"]),
                        pitch=(ext["pitch_rad"] + orbit_err["pitch_rad"], ext["pitch_drift_rad_s"]),
                        yaw=(yaw0 + ext["yaw_rad"] + orbit_err["yaw_rad"],))
    images: Dict[tuple, SimImage] = {}
    interior: Dict[tuple, list] = {}
    seams: Dict[str, list] = {}
    for band in BANDS:
        f = 1 if band == "pan" else MS_FACTOR
        gsd = PAN_GSD_M * f
        band_size = None if size is None else (max(16, W // f), max(16, H // f))
        for k in range(N_CCD):
            off = (k - (N_CCD - 1) / 2.0) * (W - overlap)                    # pan px
            tx0 = ifov * off
            row = 1.0 if k % 2 == 0 else -1.0
            ty0 = row * dty / 2 + ifov * BAND_OFFSET_PAN_PX[band]
            i_s = [rng.normal(0, 2), rng.normal(0, 1), rng.normal(0, 0.8), rng.normal(0, 1.2)]
            i_l = [rng.normal(0, 2), rng.normal(0, 1), rng.normal(0, 0.8), rng.normal(0, 0.4)]
            name = image_name(k + 1, band)
            full, cam_cur = _band_camera(band, W, full_pan[1], ifov, tx0, ty0, None, None, f"jl1 {name} current")
            _, cam_true = _band_camera(band, W, full_pan[1], ifov, tx0, ty0, i_s, i_l, f"jl1 {name} true")
            cur, tru, info = _pushbroom(f"jl1 {name}", full, band_size, cam_cur, cam_true, orbit, att_cur, att_group,
                                        CAMERA_TO_BODY, _shift_center(center, orbit, off * PAN_GSD_M), h_mid, gsd,
                                        None, {"ccd": k + 1, "band": band, "ifov_rad": ifov * f,
                                               "overlap_pan_px": overlap,
                                               "cross_track_offset_pan_px": off, "view_tan_y": ty0})
            Wb = full[0]
            info["focal_plane"] = {"X_px_poly": [tx0 / (ifov * f), Wb / 2.0], "Y_px": ty0 / (ifov * f),
                                   "definition": "X_k(u) = X0 + (W/2) u cross-track, Y_k along-track: focal-plane "
                                                 "position of the detector (tan angle / ifov), px of this band"}
            images[(k, band)] = SimImage(name, cur, tru, gsd, {}, info)
            interior[(k, band)] = [i_s, i_l]
        seams.update(_set_seams(images, interior, band, rng, h_mid, W, full_pan[1], ifov, overlap))
    _set_errors(images, interior, att_true)
    group = {"exterior": ext, "orbit_attitude_error": orbit_err, "yaw_steering_rad": yaw0,
             "attitude_current": att_cur.to_dict(), "attitude_true": att_true.to_dict(), "orbit": orbit.to_dict(),
             "overlap_pan_px": overlap, "stagger_s": STAGGER_S, "reference_band": REFERENCE_BAND,
             "band_offset_pan_px": dict(BAND_OFFSET_PAN_PX), "n_ccd": N_CCD, "bands": list(BANDS),
             "ccd_pan_px": W, "seams_px": seams,
             "seam_definition": "(true - current) image position of CCD k+1 minus that of CCD k at the same ground "
                                "point in their overlap, px of the band (sample, line), as designed (to ~0.05 px)"}
    out = [images[(k, "pan")] for k in range(N_CCD)] + [images[(k, b)] for k in range(N_CCD) for b in MS_BANDS]
    for im in out:
        im.info.update(group=group)
    out[0].info["scene_truth"] = {"block": group}
    return out


def _ccd_size(center, size):
    """(W, H) pan pixels of each CCD image; refuses a centre beyond the orbit's reach and a size out of range."""
    if abs(center[1]) > MAX_ABS_LAT_DEG:
        raise SimulationError(f"jl1: centre latitude {center[1]} is beyond the orbit's reach; "
                              f"choose |lat| <= {MAX_ABS_LAT_DEG:g}")
    if size is None:
        return CCD_PX, CCD_PX
    W, H = int(size[0]), int(size[1])
    if W < 64 or H < 16 or W > CCD_PX:
        raise SimulationError(f"jl1: --size {W} {H} must have 64 <= W <= {CCD_PX} and H >= 16")
    return W, H


def _exterior_error(rng) -> Dict[str, float]:
    """The group's exterior truth: attitude offsets and drifts of random sign (drawn in this order)."""
    sign = lambda: rng.choice([-1.0, 1.0])                                   # noqa: E731
    return {"roll_rad": sign() * rng.uniform(2.0, 6.0) * ARCSEC,
            "roll_drift_rad_s": sign() * rng.uniform(0.5, 1.5) * ARCSEC,
            "pitch_rad": sign() * rng.uniform(2.0, 6.0) * ARCSEC,
            "pitch_drift_rad_s": sign() * rng.uniform(0.5, 1.5) * ARCSEC,
            "yaw_rad": sign() * rng.uniform(20.0, 60.0) * ARCSEC,
            "t0_s": 0.0}


def _orbit_attitude_error(orbit_seed: Optional[int]) -> Dict[str, Any]:
    """The orbit's own attitude error, N(0, ORBIT_ATTITUDE_SIGMA_ARCSEC) per axis from ``orbit_seed`` (none for
    the calibration scene)."""
    if orbit_seed is None:
        return {"orbit_seed": None, "roll_rad": 0.0, "pitch_rad": 0.0, "yaw_rad": 0.0, "sigma_arcsec": 0.0}
    orng = np.random.default_rng(int(orbit_seed) + 8191)
    d = orng.normal(0.0, ORBIT_ATTITUDE_SIGMA_ARCSEC, 3) * ARCSEC
    return {"orbit_seed": int(orbit_seed), "roll_rad": float(d[0]), "pitch_rad": float(d[1]),
            "yaw_rad": float(d[2]), "sigma_arcsec": ORBIT_ATTITUDE_SIGMA_ARCSEC}


def _band_camera(band: str, W: int, full_h: int, ifov: float, tx0: float, ty0: float, i_s, i_l, name: str):
    """``(full size, camera)`` of one CCD of ``band``: linear look angles at ``(tx0, ty0)``, plus the interior
    polynomials ``i_s, i_l`` (px) of a true camera."""
    f = 1 if band == "pan" else MS_FACTOR
    full = (W // f, full_h // f)
    extra = (None, None) if i_s is None else (_poly_px([-c for c in i_s]), _poly_px([-c for c in i_l]))
    return full, _linear_camera(full, ifov * f, tx0, ty0, name, *extra)


def _set_seams(images, interior, band: str, rng, h_mid: float, W: int, full_h: int, ifov: float,
               overlap: int) -> Dict[str, list]:
    """Set each CCD's constant interior term of ``band`` so that the seam with its left neighbour is 2-5 px;
    returns the seams as designed."""
    seams = {}
    for k in range(1, N_CCD):
        a, b = images[(k - 1, band)], images[(k, band)]
        S = _seam_vector(a, b, h_mid)
        target = rng.uniform(*SEAM_RANGE_PX)
        norm = float(np.hypot(*S))
        direction = S / norm if norm > 1e-6 else np.array([np.cos(t := rng.uniform(0, 2 * np.pi)), np.sin(t)])
        delta = direction * target - S
        i_s, i_l = interior[(k, band)]
        i_s[0] += float(delta[0])
        i_l[0] += float(delta[1])
        tx0 = ifov * (k - (N_CCD - 1) / 2.0) * (W - overlap)
        ty0 = b.info["view_tan_y"]
        _, cam_true = _band_camera(band, W, full_h, ifov, tx0, ty0, i_s, i_l, f"jl1 {b.name} true")
        b.true = b.true.with_camera(_crop_any(cam_true, tuple(b.info["crop_offset"]), b.size))
        b.true.name = f"jl1 {b.name} true"
        seams[f"{a.name}|{b.name}"] = [float(v) for v in direction * target]
    return seams


def _set_errors(images, interior, att_true: Attitude) -> None:
    """The true models get the orbit's attitude; each image's ``errors`` its interior truth."""
    for (k, band), im in images.items():
        i_s, i_l = interior[(k, band)]
        im.true = copy.copy(im.true)
        im.true.attitude = att_true
        im.errors = {"interior_sample_px_poly": list(map(float, i_s)), "interior_line_px_poly": list(map(float, i_l)),
                     "poly_variable": "u = (s - W/2) / (W/2) of this CCD image (full CCD length)",
                     "definition": "true image position = current + I(u_true) + exterior effects (METHODS §8)",
                     "focal_plane": im.info["focal_plane"]}


def _seam_vector(left: SimImage, right: SimImage, h, n_lines: int = 5):
    """Mean seam (sample, line) in px of the band: (true - current) position of ``right`` minus that of ``left`` at
    ground points (height ``h``) in the middle of their overlap, on ``n_lines`` lines of ``right``. Points whose
    projection leaves a push-broom crop's time range (NaN, or far outside: tiny crops of the MS bands, 32 x 16 px,
    where the along-track band offset and a few px of interior move the ground past the crop) are left out; more
    lines are tried when none is left, and ``(0, 0)`` is returned when no line works."""
    W, H = right.size
    f = 1 if right.info.get("band", "pan") == "pan" else MS_FACTOR
    ov = right.info.get("overlap_pan_px", OVERLAP_PX) / f
    for n in (n_lines, 8 * n_lines):
        s = np.full(n, 0.5 * ov)
        l = (np.arange(n) + 0.5) * H / n
        hh = np.full(n, float(h))
        lon, lat = right.current.localize(s, l, hh)
        rs, rl = right.true.project(lon, lat, hh)
        ts, tl = left.true.project(lon, lat, hh)
        cs, cl = left.current.project(lon, lat, hh)
        ds, dl = (rs - s) - (ts - cs), (rl - l) - (tl - cl)
        ok = np.isfinite(ds) & np.isfinite(dl) & (np.abs(ds) < W) & (np.abs(dl) < H)
        if ok.any():
            return np.array([np.mean(ds[ok]), np.mean(dl[ok])])
    return np.zeros(2)


def overlap_width_px(left: SimImage, right: SimImage, h, n_lines: int = 7, model: str = "true"):
    """Overlap of two adjacent CCD images, in px of the band, on ``n_lines`` lines of ``right``: how far ``left``'s
    image extends past ``right``'s first detector (``left.W - s_left(ground of right's sample 0)``)."""
    mr, ml = getattr(right, model), getattr(left, model)
    W, H = mr.size
    l = (np.arange(n_lines) + 0.5) * H / n_lines
    lon, lat = mr.localize(np.zeros(n_lines), l, np.full(n_lines, h))
    s, _ = ml.project(lon, lat, np.full(n_lines, h))
    return ml.size[0] - s


# --------------------------------------------------------------------------------------- observations
OBSERVATION_COLUMNS = ["point_id", "image_id", "kind", "sample", "line", "sigma", "role", "lon", "lat", "h",
                       "truth_sample", "truth_line", "truth_lon", "truth_lat", "truth_h", "truth_outlier"]


def _inside(model, s, l):
    W, H = model.size
    return np.isfinite(s) & np.isfinite(l) & (s >= 0) & (s <= W) & (l >= 0) & (l <= H)


def _rows(pid, image, kind, s, l, sigma, role, lon, lat, h, ts, tl, tlon, tlat, th):
    n = len(pid)
    return {"point_id": np.asarray(pid, dtype=object), "image_id": np.full(n, image, dtype=object),
            "kind": np.full(n, kind, dtype=object), "sample": s, "line": l, "sigma": np.full(n, float(sigma)),
            "role": np.broadcast_to(np.asarray(role, dtype=object), (n,)).copy(), "lon": lon, "lat": lat, "h": h,
            "truth_sample": ts, "truth_line": tl, "truth_lon": tlon, "truth_lat": tlat, "truth_h": th,
            "truth_outlier": np.zeros(n, dtype=bool)}


def block_observations(scene, *, gcps=None, n_gcps: int = 50, gcp_noise_px: float = 0.2, check_fraction: float = 0.3,
                       n_overlap_ties: int = 40, n_band_ties: int = 40, tie_noise_px: float = 0.1,
                       tie_outlier_fraction: float = 0.0, tie_outlier_range_px=(5.0, 50.0),
                       reference_band: str = REFERENCE_BAND, seed: Optional[int] = None):
    """The long observation table of a Jilin-1 group (METHODS §8): GCPs and tie points with known truth.

    Parameters
    ----------
    scene : a ``jl1`` :class:`~gdal_gf4cal.simulate.SimScene`.
    gcps : ``{image name: GeoDataFrame}`` from :func:`~gdal_gf4cal.simulate.simulate_gcps` (their rows are used as
        they are); None draws them here with ``n_gcps`` (per image), ``gcp_noise_px``, ``check_fraction``.
    n_overlap_ties : tie points per pair of adjacent CCDs and per band, in their overlap (own density).
    n_band_ties : tie points per CCD between the reference band and every other band of that CCD (pan included).
    tie_noise_px : Gaussian matching noise of tie points, px of each image per axis (own noise).
    tie_outlier_fraction : fraction of tie points given a wrong match: one of their observations (not the first)
        moved by ``tie_outlier_range_px`` (5-50 px) in a random direction; ``truth_outlier`` marks that row.
    seed : seeds the draws (default: the scene's seed).

    Returns
    -------
    pandas.DataFrame with :data:`OBSERVATION_COLUMNS`: one row per observation of a point in an image; ``kind`` is
    ``gcp`` or ``tie``; ``sample, line`` measured (GDAL pixel convention), ``truth_sample, truth_line`` error-free
    (true model); ``lon, lat, h`` the ground coordinates of GCPs (NaN for ties: unknowns of the adjustment);
    ``truth_lon, truth_lat, truth_h`` the true ground point of every row. Tie points share ``point_id`` across
    images (``T...`` overlap ties, ``B...`` band ties); GCP ids are ``G...``.
    """
    _check_tie_options(scene, reference_band, tie_noise_px, n_overlap_ties, n_band_ties, tie_outlier_fraction)
    rng = np.random.default_rng((scene.seed if seed is None else seed) + 524287)
    if gcps is None:
        gcps = simulate_gcps(scene, n_gcps=n_gcps, gcp_noise_px=gcp_noise_px, check_fraction=check_fraction,
                             seed=seed)
    rows = _gcp_rows(gcps)
    draws = _TieDraws(rng, tie_noise_px)
    if n_overlap_ties:
        rows += _overlap_tie_rows(scene, draws, n_overlap_ties)
    if n_band_ties:
        rows += _band_tie_rows(scene, draws, n_band_ties, reference_band)
    df = pd.concat([pd.DataFrame(r) for r in rows], ignore_index=True)[OBSERVATION_COLUMNS]
    if tie_outlier_fraction > 0:
        _add_tie_outliers(df, rng, tie_outlier_fraction, tie_outlier_range_px)
    return df


def _check_tie_options(scene, reference_band: str, tie_noise_px: float, n_overlap_ties: int, n_band_ties: int,
                       tie_outlier_fraction: float) -> None:
    if scene.sensor != "jl1":
        raise SimulationError(f"block observations are for jl1 scenes, not {scene.sensor}; use simulate_gcps")
    if reference_band not in MS_BANDS:
        raise SimulationError(f"reference band {reference_band!r} unknown; choose one of {', '.join(MS_BANDS)}")
    if tie_noise_px < 0 or n_overlap_ties < 0 or n_band_ties < 0 or not 0 <= tie_outlier_fraction < 1:
        raise SimulationError("need tie_noise_px, n_overlap_ties, n_band_ties >= 0 and 0 <= tie_outlier_fraction < 1")


def _gcp_rows(gcps) -> list:
    """Observation rows of the GCP tables (their measurements, sigma and outlier truth as they are)."""
    rows = []
    for name, g in gcps.items():
        lon, lat, h = (g[c].to_numpy(float) for c in ("lon", "lat", "h"))
        rows.append(_rows(g["id"].to_numpy(object), name, "gcp", g["sample"].to_numpy(float),
                          g["line"].to_numpy(float), 0.0, g["role"].to_numpy(object), lon, lat, h,
                          g["truth_sample"].to_numpy(float), g["truth_line"].to_numpy(float), lon, lat, h))
        rows[-1]["sigma"] = g["sigma"].to_numpy(float)
        if "truth_outlier" in g:
            rows[-1]["truth_outlier"] = g["truth_outlier"].to_numpy(bool)
    return rows


class _TieDraws:
    """The tie points' random draws from one generator, in order: matching noise and running point ids."""

    def __init__(self, rng, tie_noise_px: float):
        self.rng, self.noise, self.count = rng, tie_noise_px, 0
        self.sigma = max(tie_noise_px, 1e-3)

    def noisy(self, v):
        return v + (self.rng.normal(0.0, self.noise, v.shape) if self.noise > 0 else 0.0)

    def ids(self, prefix: str, n: int):
        out = np.array([f"{prefix}{self.count + i + 1:06d}" for i in range(n)], dtype=object)
        self.count += n
        return out

    def rows(self, pid, im, ts, tl, lon, lat, h) -> dict:
        """Rows of tie observations in ``im``: true positions ``ts, tl`` plus noise; ground unknown (NaN)."""
        nan = np.full(len(pid), np.nan)
        return _rows(pid, im.name, "tie", self.noisy(ts), self.noisy(tl), self.sigma, "control", nan, nan.copy(),
                     nan.copy(), ts, tl, lon, lat, h)


def _overlap_tie_rows(scene, draws: _TieDraws, n_ties: int) -> list:
    """Tie points between adjacent CCDs, per band, in their overlap (``T...`` ids)."""
    by_name = {im.name: im for im in scene.images}
    n_ccd = max(int(im.info["ccd"]) for im in scene.images)
    rows = []
    for band in BANDS:
        for k in range(1, n_ccd):
            left, right = by_name[image_name(k, band)], by_name[image_name(k + 1, band)]
            ov = float(np.nanmax(overlap_width_px(left, right, float(np.mean(right.true.height_range)))))
            m = 4 * n_ties
            s = draws.rng.uniform(0.0, max(ov, 1.0), m)
            l = draws.rng.uniform(0.0, right.size[1], m)
            lon, lat, h = right.true.localize_dem(s, l, scene.dem)
            ls, ll = left.true.project(lon, lat, h)
            rs, rl = right.true.project(lon, lat, h)
            ok = _inside(left.true, ls, ll) & _inside(right.true, rs, rl) & np.isfinite(h)
            sel = np.flatnonzero(ok)[:n_ties]
            pid = draws.ids("T", sel.size)
            for im, ts, tl in ((left, ls, ll), (right, rs, rl)):
                rows.append(draws.rows(pid, im, ts[sel], tl[sel], lon[sel], lat[sel], h[sel]))
    return rows


def _band_tie_rows(scene, draws: _TieDraws, n_ties: int, reference_band: str) -> list:
    """Tie points between the reference band and every other band of the same CCD (one point, up to five rays;
    ``B...`` ids)."""
    by_name = {im.name: im for im in scene.images}
    n_ccd = max(int(im.info["ccd"]) for im in scene.images)
    rows = []
    for k in range(1, n_ccd + 1):
        refim = by_name[image_name(k, reference_band)]
        m = 2 * n_ties
        W, H = refim.size
        s, l = draws.rng.uniform(0.0, W, m), draws.rng.uniform(0.0, H, m)
        lon, lat, h = refim.true.localize_dem(s, l, scene.dem)
        others = [by_name[image_name(k, b)] for b in BANDS if b != reference_band]
        proj = [im.true.project(lon, lat, h) for im in others]
        inside = np.array([_inside(im.true, ps, pl) for im, (ps, pl) in zip(others, proj)])
        rs, rl = refim.true.project(lon, lat, h)
        ok = np.isfinite(h) & inside.any(axis=0) & _inside(refim.true, rs, rl)
        sel = np.flatnonzero(ok)[:n_ties]
        pid = draws.ids("B", sel.size)
        for im, (ts, tl), ins in [(refim, (rs, rl), np.ones(rs.shape, bool))] + list(zip(others, proj, inside)):
            use = ins[sel]
            j = sel[use]
            rows.append(draws.rows(pid[use], im, ts[j], tl[j], lon[j], lat[j], h[j]))
    return rows


def _add_tie_outliers(df, rng, fraction: float, range_px) -> None:
    """Give ``fraction`` of the tie points a wrong match: the last observation of each chosen point (never its
    first, so the point keeps a correct ray) moved by ``range_px`` in a random direction; ``truth_outlier`` set."""
    tie = df["kind"].to_numpy() == "tie"
    pids = df.loc[tie, "point_id"].unique()
    bad = rng.permutation(pids)[:int(round(fraction * pids.size))]
    last = df[tie & df["point_id"].isin(bad).to_numpy()].groupby("point_id").tail(1).index.to_numpy()
    mag = rng.uniform(*range_px, last.size)
    ang = rng.uniform(0.0, 2 * np.pi, last.size)
    df.loc[last, "sample"] += mag * np.cos(ang)
    df.loc[last, "line"] += mag * np.sin(ang)
    df.loc[last, "truth_outlier"] = True


def write_observations(scene, out_dir, gcps, observation_options, written) -> dict:
    """Write ``observations.csv`` (:func:`block_observations`, atomic) into ``out_dir``; return its truth record.

    ``written`` (list) receives the path, so that a failing :func:`~gdal_gf4cal.simulate.write_scene` removes it.
    """
    opts = dict(observation_options or {})
    allowed = {"n_overlap_ties", "n_band_ties", "tie_noise_px", "tie_outlier_fraction", "reference_band", "seed"}
    if set(opts) - allowed:
        raise SimulationError(f"unknown observation option(s) {sorted(set(opts) - allowed)}; "
                              f"use {sorted(allowed)}")
    obs = block_observations(scene, gcps=gcps, **opts)
    path = os.path.join(out_dir, "observations.csv")
    written.append(path)
    _write_csv(obs, path)
    ties = obs[obs["kind"] == "tie"]
    settings = {"n_overlap_ties": 40, "n_band_ties": 40, "tie_noise_px": 0.1, "tie_outlier_fraction": 0.0,
                "tie_outlier_range_px": [5.0, 50.0], "reference_band": REFERENCE_BAND}
    settings.update(opts)
    return dict(settings, n_rows=int(len(obs)), n_gcp_rows=int((obs["kind"] == "gcp").sum()),
                n_tie_points=int(ties["point_id"].nunique()), n_tie_rows=int(len(ties)),
                columns=list(obs.columns), pixel_convention="gdal",
                measured="tie: truth (true model) + N(0, tie_noise_px) per axis; gcp: the rows of gcps.csv",
                tie_ids="T: between adjacent CCDs of one band in their overlap; B: reference band and the other "
                        "bands of one CCD")


SENSORS["jl1"] = SensorSpec(
    "jl1", "Jilin-1 KF01A wide-field group: 4 staggered TDI CCDs (8192 px, 0.75 m pan, 0.6 s apart, yaw-steered) "
    "x 4 MS bands (3 m)", (125.3, 43.9), (150.0, 700.0), build_jl1,
    tuple(f"ccd{k}" for k in range(1, 5)) + tuple(f"ccd{k}_{b}" for k in range(1, 5) for b in ("blue", "green", "red", "nir")),
    ("orbit_seed",), write_observations=write_observations)
