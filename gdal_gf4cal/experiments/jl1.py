"""Experiment of seed 003 (Jilin-1 KF01A wide-field camera): multi-CCD / band-to-band block calibration, Tables 3-6.

The paper's validation rebuilt on simulated truth (METHODS §8, §10) through the public API:

* **Calibration scene**: one simulated group (4 staggered CCDs x pan + 4 MS bands, :mod:`gdal_gf4cal.simulate.jl1`)
  with vendor-style RPCs fitted from the *nominal* camera (:func:`~gdal_gf4cal.rpc_fit.fit_rpc_from_model`), GCPs
  (``gcp_noise_px``) and tie points (``tie_noise_px``; between adjacent CCDs in their overlaps and between each band
  and the reference band) from :func:`~gdal_gf4cal.simulate.block_observations`, adjusted by
  :func:`gdal_gf4cal.block.adjust_block` (blue absolute, the other bands relative).
* **Table 3** (calibration accuracy): per CCD and band, the RMS across track (sample) and along track (line) of the
  recalibrated model against the true one on a grid over the image (px of that band), before and after; the floor
  the GCP and matching noise allow (RMS of the propagated 1-sigma of the correction,
  :func:`gdal_gf4cal.block.prediction_std`) and the check-GCP residuals.
* **Table 4** (band-to-band registration): per CCD, each band against the blue band: blue pixels carried into the
  band image by the models (blue model on the DEM, band model) minus the same by the true models, in px of the 3 m
  MS band (band px times ``r`` = band pixel / MS pixel, 0.25 for pan), RMS before and after.
* **Table 5** (10 orbits without control): the group's ``calibration.json`` (:func:`~gdal_gf4cal.block.
  calibration_dict`) applied (:func:`~gdal_gf4cal.block.calibrated_model`) to scenes of other orbits, each with its
  own random attitude error (N(0, 3.6 arcsec) per axis, simulator option ``orbit_seed``). Planar error of the pan
  images' grid points localised on the DEM, in metres; CE90 over all points of all orbits, against the **CE90 the
  attitude errors imply**: per point ``hypot(D roll, D pitch, x yaw)`` with ``D`` the satellite-to-ground distance
  (orbit radius - the point's geocentric radius: 545 km at 44 deg N for the 535 km orbit) and ``x`` the point's cross-track distance from the group centre (small angles, the
  roll/pitch/yaw of that orbit as drawn; the cross term pitch x yaw is dropped, it averages out across the swath),
  then its 90th percentile over the same points. Also the CE90 the error *distribution* implies:
  ``2.146 D sigma`` (Rayleigh, roll and pitch; the paper's < 20 m). Band-to-band after calibration per orbit.
* **Table 6** (5 scenes with 5 GCPs): other orbits again; per scene 5 well-spread GCPs over the four pan CCDs
  re-estimate the group's exterior (offsets and drifts) with the calibrated interiors held
  (:func:`~gdal_gf4cal.block.adjust_block` with ``calibration=``); the other GCPs (>= 10) are check points,
  localised on the DEM: planar RMS in metres at 0.75 m GSD (the paper: < 2 m).

Other scenes of the same group share the calibration scene's DEM (``make_scene(dem=...)``) and so its nominal
(current) camera: their vendor RPCs are the calibration scene's (checked, refitted otherwise).
"""
from __future__ import annotations

import math
import os
import time
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
import pandas as pd

from ..block import (adjust_block, calibrated_model, calibration_dict, corrected_model, prediction_std,
                     write_calibration)
from ..geodesy import metres_per_degree
from ..progress import report as _report
from ..report import write_report_json
from ..rpc_fit import fit_rpc_from_model
from ..simulate import block_observations, make_scene, simulate_gcps
from ..simulate.geodesy import geodetic_to_ecef
from ..simulate.jl1 import ORBIT_ATTITUDE_SIGMA_ARCSEC
from ..stats import ce90
from .zy3 import spread_order

BANDS = ("pan", "blue", "green", "red", "nir")
REFERENCE_BAND = "blue"
N_CCD = 4
GCP_NOISE_PX = 0.2
TIE_NOISE_PX = 0.1
N_ORBITS = 10
N_SCENES = 5
N_SCENE_GCPS = 5
#: CE90 of a 2-D isotropic normal error: 2.146 sigma (Rayleigh 90 % quantile sqrt(-2 ln 0.1)).
RAYLEIGH_90 = math.sqrt(-2.0 * math.log(0.1))
ARCSEC = math.pi / (180.0 * 3600.0)
#: The paper's numbers (METHODS §8): interior and band-to-band < 0.3 px, CE90 < 20 m, GCP check RMS < 2 m.
PAPER = {"interior_px": 0.3, "band_to_band_px": 0.3, "ce90_m": 20.0, "check_rms_m": 2.0}
DEFAULT_SIZE = (512, 256)


def _name(ccd: int, band: str) -> str:
    return f"ccd{ccd}" if band == "pan" else f"ccd{ccd}_{band}"


def _grid(size, n=(15, 7)):
    W, H = size
    S, L = np.meshgrid(np.linspace(0.5, W - 0.5, n[0]), np.linspace(0.5, H - 0.5, n[1]))
    return S.ravel(), L.ravel()


def _rms(x) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def _metres(lon, lat, h, lon0, lat0):
    """East and north differences (m) of ``(lon, lat)`` from ``(lon0, lat0)``."""
    mx, my = metres_per_degree(lat0, h)
    return (np.asarray(lon) - lon0) * mx, (np.asarray(lat) - lat0) * my


def _image_errors(model, im, dem, S, L):
    """(sample, line) error (px) of ``model`` against the true model at the true ground of image points ``S, L``."""
    lon, lat, h = im.true.localize_dem(S, L, dem)
    s, l = model.project(lon, lat, h)
    return np.asarray(s) - S, np.asarray(l) - L


def _band_to_band(models, scene, ccd: int, band: str) -> float:
    """RMS misregistration of ``band`` against the reference band of CCD ``ccd`` (px of the MS band): a grid of
    reference-band pixels is carried into the band image by the models (reference model on the DEM, then the band
    model) and by the true models; the difference, in px of the band times its pixel ratio ``r``."""
    ref = scene.image(_name(ccd, REFERENCE_BAND))
    im = scene.image(_name(ccd, band))
    S, L = _grid(ref.size)
    mlon, mlat, mh = models[ref.name].localize_dem(S, L, scene.dem)
    ms, ml = models[im.name].project(mlon, mlat, mh)
    tlon, tlat, th = ref.true.localize_dem(S, L, scene.dem)
    ts, tl = (np.asarray(v) for v in im.true.project(tlon, tlat, th))
    W, H = im.size
    inside = (ts >= 0) & (ts <= W) & (tl >= 0) & (tl <= H)
    r = im.gsd_m / ref.gsd_m
    return _rms(r * np.hypot(np.asarray(ms) - ts, np.asarray(ml) - tl)[inside])


def _orbit_scene(seed, size, dem, orbit_seed):
    return make_scene("jl1", seed=seed, size=size, dem=dem, options={"orbit_seed": int(orbit_seed)})


def _rpcs_for(scene, base_scene, base_rpcs):
    """The scene's vendor RPCs: the base scene's where the nominal (current) models agree, else refitted."""
    out = {}
    for im in scene.images:
        b = base_scene.image(im.name)
        W, H = im.size
        S, L = np.array([1.0, W - 1.0, W / 2.0]), np.array([1.0, H - 1.0, H / 2.0])
        h = np.full(3, float(np.mean(im.current.height_range)))
        lon, lat = im.current.localize(S, L, h)
        s, l = b.current.project(lon, lat, h)
        same = tuple(b.size) == tuple(im.size) and np.nanmax(np.hypot(s - S, l - L)) < 1e-6
        out[im.name] = base_rpcs[im.name] if same else fit_rpc_from_model(im.current, size=im.size)[0]
    return out


def _ground_errors(models, scene, names):
    """Planar ground error (east, north, m) of the models' localisation of true image positions on the DEM, and
    the points' ground (lon, lat, h) and cross-track distance (m) from the group centre."""
    out = {k: [] for k in ("de", "dn", "lon", "lat", "h", "x")}
    for n in names:
        im = scene.image(n)
        S, L = _grid(im.size)
        lon, lat, h = im.true.localize_dem(S, L, scene.dem)
        mlon, mlat, _ = models[n].localize_dem(S, L, scene.dem)
        de, dn = _metres(mlon, mlat, h, lon, lat)
        x = (im.info["cross_track_offset_pan_px"] + (S - im.size[0] / 2.0)) * im.gsd_m
        for k, v in (("de", de), ("dn", dn), ("lon", lon), ("lat", lat), ("h", h), ("x", x)):
            out[k].append(np.asarray(v, float))
    return {k: np.concatenate(v) for k, v in out.items()}


def _distance(scene, lon, lat, h) -> np.ndarray:
    """Satellite-to-ground distance ``D`` (m): orbit radius - geocentric radius of the ground points."""
    radius = float(scene.images[0].info["group"]["orbit"]["radius_m"])
    return radius - np.linalg.norm(np.asarray(geodetic_to_ecef(lon, lat, h)), axis=-1)


def _implied_errors(scene, D, x) -> np.ndarray:
    """Planar ground error (m) the orbit's attitude error implies at points at distance ``D`` and cross-track
    distance ``x`` (module docstring)."""
    err = scene.images[0].info["group"]["orbit_attitude_error"]
    return np.sqrt((D * err["roll_rad"]) ** 2 + (D * err["pitch_rad"]) ** 2 + (np.asarray(x) * err["yaw_rad"]) ** 2)


def run(out_dir, *, seed: int = 3, progress=None, size=DEFAULT_SIZE, gcp_noise_px: float = GCP_NOISE_PX,
        tie_noise_px: float = TIE_NOISE_PX, n_gcps: int = 30, n_ties: int = 40, n_orbits: int = N_ORBITS,
        n_scenes: int = N_SCENES, n_scene_gcps: int = N_SCENE_GCPS, write_files: bool = True,
        verbose: bool = True) -> Dict[str, Any]:
    """Run the Jilin-1 experiment; print Tables 3-6 and write ``report.json``, ``tables.txt`` and
    ``calibration.json`` into ``out_dir``.

    ``size``: (W, H) pan crop of every CCD (:func:`~gdal_gf4cal.simulate.make_scene`; None = full 8192 x 8192).
    Returns the report: ``table3`` (per image: ``before``/``after``/``floor``/``check`` across/along RMS px),
    ``table4`` (per CCD and band: band-to-band RMS before/after), ``table5`` (per orbit and ``summary``: CE90 measured
    and implied, ratio), ``table6`` (per scene and ``summary``: check planar RMS m), ``calibration`` (stages).
    """
    t0 = time.perf_counter()
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    size = None if size is None else (int(size[0]), int(size[1]))
    _report(progress, 0.0, "simulating the Jilin-1 group")
    terrain = make_scene("jl1", seed=seed, size=size).dem
    scene = make_scene("jl1", seed=seed, size=size, dem=terrain)
    names = [im.name for im in scene.images]
    ref_names = [_name(k, REFERENCE_BAND) for k in range(1, N_CCD + 1)]
    pan_names = [_name(k, "pan") for k in range(1, N_CCD + 1)]
    bands_of = {n: _name(scene.image(n).info["ccd"], REFERENCE_BAND) for n in names if n not in ref_names}
    rpcs, fit_max = _vendor_rpcs(scene, progress)
    _report(progress, 0.13, "GCPs and tie points")
    obs = block_observations(scene, n_gcps=n_gcps, gcp_noise_px=gcp_noise_px, n_overlap_ties=n_ties,
                             n_band_ties=n_ties, tie_noise_px=tie_noise_px, seed=seed)
    _report(progress, 0.2, "block adjustment")
    est = adjust_block(obs, rpcs, scene.dem, order=ref_names, bands_of=bands_of)
    cal = calibration_dict(est)
    corrected = {n: corrected_model(est, n, rpcs[n]) for n in names}
    _report(progress, 0.3, "Table 3: calibration accuracy")
    table3 = _table3(scene, est, rpcs, corrected)
    _report(progress, 0.35, "Table 4: band-to-band registration")
    table4 = {f"ccd{k}": {b: {"before": _band_to_band(rpcs, scene, k, b), "after": _band_to_band(corrected, scene,
                                                                                                 k, b)}
                          for b in BANDS if b != REFERENCE_BAND} for k in range(1, N_CCD + 1)}
    orbits, summary5 = _table5(scene, terrain, rpcs, cal, pan_names, seed=seed, size=size, n_orbits=n_orbits,
                               progress=progress)
    scenes = []
    for i in range(n_scenes):
        _report(progress, 0.75 + 0.2 * i / max(n_scenes, 1), f"Table 6: scene {i + 1} of {n_scenes} with GCPs")
        scenes.append(_table6_scene(scene, terrain, rpcs, cal, pan_names, ref_names, i, seed=seed, size=size,
                                    gcp_noise_px=gcp_noise_px, n_scene_gcps=n_scene_gcps))
    summary6 = {"n_scenes": len(scenes),
                "check_planar_rms_m": _rms([s["after"]["planar_rms_m"] for s in scenes]) if scenes else None,
                "max_check_planar_rms_m": max((s["after"]["planar_rms_m"] for s in scenes), default=None),
                "gsd_m": float(scene.image(pan_names[0]).gsd_m)}
    rep = _report_dict(seed=seed, size=size, gcp_noise_px=gcp_noise_px, tie_noise_px=tie_noise_px, fit_max=fit_max,
                       est=est, cal=cal, table3=table3, table4=table4, orbits=orbits, summary5=summary5,
                       scenes=scenes, summary6=summary6)
    rep["elapsed_s"] = time.perf_counter() - t0
    text = format_tables(rep)
    if write_files:
        write_calibration(cal, os.path.join(out_dir, "calibration.json"))
        with open(os.path.join(out_dir, "tables.txt"), "w", encoding="utf-8") as fh:
            fh.write(text + "\n")
        rep["files"] = ["report.json", "tables.txt", "calibration.json"]
        write_report_json(rep, os.path.join(out_dir, "report.json"))
    if verbose:
        print(text)
    _report(progress, 1.0, "done")
    return rep


def _vendor_rpcs(scene, progress):
    """Each image's vendor RPC fitted from its nominal (current) camera, and the largest fit error (px)."""
    rpcs: Dict[str, Any] = {}
    fit_max = 0.0
    for i, im in enumerate(scene.images):
        _report(progress, 0.02 + 0.1 * i / len(scene.images), f"fitting the RPC of {im.name}")
        rpcs[im.name], fit = fit_rpc_from_model(im.current, size=im.size)
        fit_max = max(fit_max, float(fit.max_px))
    return rpcs, fit_max


def _table3(scene, est, rpcs, corrected) -> Dict[str, Any]:
    """Table 3: calibration accuracy per CCD and band (px of the band): before, after, floor, check GCPs."""
    table3: Dict[str, Any] = {}
    tab = est.table
    for im in scene.images:
        n = im.name
        S, L = _grid(im.size)
        bs, bl = _image_errors(rpcs[n], im, scene.dem, S, L)
        a_s, a_l = _image_errors(corrected[n], im, scene.dem, S, L)
        fs, fl = prediction_std(est, n, S, L)
        chk = tab[(tab["image_id"] == n) & (tab["kind"] == "gcp") & (tab["role"] == "check") & ~tab["outlier"]]
        table3[n] = {"ccd": int(im.info["ccd"]), "band": im.info["band"], "gsd_m": float(im.gsd_m),
                     "before": {"across": _rms(bs), "along": _rms(bl)},
                     "after": {"across": _rms(a_s), "along": _rms(a_l), "max": float(np.nanmax(np.hypot(a_s, a_l)))},
                     "floor": {"across": _rms(fs), "along": _rms(fl)},
                     "check": {"n": int(len(chk)), "across": _rms(chk["res_sample_after"]),
                               "along": _rms(chk["res_line_after"])}}
    return table3


def _table5(scene, terrain, rpcs, cal, pan_names, *, seed, size, n_orbits, progress):
    """Table 5: the calibration applied to ``n_orbits`` other orbits without control; per orbit and summary."""
    names = [im.name for im in scene.images]
    orbits: List[Dict[str, Any]] = []
    all_err, all_implied, all_dist = [], [], []
    for i in range(n_orbits):
        _report(progress, 0.4 + 0.35 * i / max(n_orbits, 1), f"Table 5: orbit {i + 1} of {n_orbits} without control")
        osc = _orbit_scene(seed, size, terrain, 1000 + i)
        orpcs = _rpcs_for(osc, scene, rpcs)
        models = {n: calibrated_model(cal, n, orpcs[n]) for n in names}
        g = _ground_errors(models, osc, pan_names)
        err = np.hypot(g["de"], g["dn"])
        dist = _distance(osc, g["lon"], g["lat"], g["h"])
        implied = _implied_errors(osc, dist, g["x"])
        att = osc.images[0].info["group"]["orbit_attitude_error"]
        b2b = [_band_to_band(models, osc, k, b) for k in range(1, N_CCD + 1) for b in BANDS if b != REFERENCE_BAND]
        orbits.append({"orbit_seed": att["orbit_seed"],
                       "attitude_error_arcsec": {a: att[f"{a}_rad"] / ARCSEC for a in ("roll", "pitch", "yaw")},
                       "planar_rms_m": _rms(err), "ce90_m": ce90(err), "implied_ce90_m": ce90(implied),
                       "band_to_band_max_px": float(np.nanmax(b2b)), "band_to_band_rms_px": _rms(b2b)})
        all_err.append(err)
        all_implied.append(implied)
        all_dist.append(dist)
    summary5: Dict[str, Any] = {}
    if orbits:
        e, im_ = np.concatenate(all_err), np.concatenate(all_implied)
        summary5 = {"n_orbits": len(orbits), "n_points": int(e.size), "ce90_m": ce90(e), "implied_ce90_m": ce90(im_),
                    "expected_ce90_m": RAYLEIGH_90 * float(np.mean(np.concatenate(all_dist))) *
                    ORBIT_ATTITUDE_SIGMA_ARCSEC * ARCSEC,
                    "band_to_band_max_px": max(o["band_to_band_max_px"] for o in orbits)}
        summary5["ratio"] = summary5["ce90_m"] / summary5["implied_ce90_m"]
    return orbits, summary5


def _table6_scene(scene, terrain, rpcs, cal, pan_names, ref_names, i: int, *, seed, size, gcp_noise_px,
                  n_scene_gcps) -> Dict[str, Any]:
    """Table 6, scene ``i``: its exterior re-estimated from ``n_scene_gcps`` well-spread GCPs (interiors held);
    the other GCPs as check points, without and with those GCPs."""
    osc = _orbit_scene(seed, size, terrain, 2000 + i)
    orpcs = _rpcs_for(osc, scene, rpcs)
    per = max(4, -(-(n_scene_gcps + 12) // len(pan_names)))
    tables = simulate_gcps(osc, n_gcps=per, gcp_noise_px=gcp_noise_px, check_fraction=0.0, seed=seed + 7 * i)
    g = pd.concat([tables[n].assign(image=n, id=n + ":" + tables[n]["id"].astype(str)) for n in pan_names],
                  ignore_index=True)                   # drawn per image: ids made unique across images
    order = spread_order(g["lon"].to_numpy(float), g["lat"].to_numpy(float))
    ctrl = np.zeros(len(g), bool)
    ctrl[order[:n_scene_gcps]] = True
    # the scene's exterior from its 5 GCPs, the calibrated interiors held (adjust_block(calibration=...))
    ctrl_obs = g[ctrl].rename(columns={"id": "point_id", "image": "image_id"}).assign(kind="gcp")
    scene_models = {n: orpcs[n] for n in pan_names + ref_names}
    est_i = adjust_block(ctrl_obs[["point_id", "image_id", "kind", "sample", "line", "sigma", "role", "lon", "lat",
                                   "h"]], scene_models, osc.dem, calibration=cal)
    cal_i = calibration_dict(est_i)
    chk = g[~ctrl]
    res = {tag: _check_errors(c, chk, orpcs, osc.dem, pan_names) for tag, c in (("no_gcp", cal), ("gcps", cal_i))}
    return {"orbit_seed": 2000 + i, "n_control": int(ctrl.sum()), "n_check": int(len(chk)),
            "control_per_image": {n: int(((g["image"] == n) & ctrl).sum()) for n in pan_names},
            "control_rms_px": _rms(est_i.residuals), "exterior": cal_i["exterior"],
            "before": res["no_gcp"], "after": res["gcps"]}


def _check_errors(cal, chk, orpcs, dem, pan_names) -> Dict[str, float]:
    """Planar, east and north RMS (m) of the check points' true image positions localised on the DEM by the
    calibrated models."""
    de, dn = [], []
    for n in pan_names:
        r = chk[chk["image"] == n]
        m = calibrated_model(cal, n, orpcs[n])
        mlon, mlat, _ = m.localize_dem(r["truth_sample"].to_numpy(float), r["truth_line"].to_numpy(float), dem)
        a, b = _metres(mlon, mlat, r["h"].to_numpy(float), r["lon"].to_numpy(float), r["lat"].to_numpy(float))
        de.append(a)
        dn.append(b)
    de, dn = np.concatenate(de), np.concatenate(dn)
    return {"planar_rms_m": _rms(np.hypot(de, dn)), "east_rms_m": _rms(de), "north_rms_m": _rms(dn)}


def _report_dict(*, seed, size, gcp_noise_px, tie_noise_px, fit_max, est, cal, table3, table4, orbits, summary5,
                 scenes, summary6) -> Dict[str, Any]:
    """The experiment's report: its options, the calibration, Tables 3-6, their summary and notes."""
    interior_max = max(max(v["after"]["across"], v["after"]["along"]) for v in table3.values())
    floor_ratio = max(math.hypot(v["after"]["across"], v["after"]["along"]) /
                      max(math.hypot(v["floor"]["across"], v["floor"]["along"]), 1e-12) for v in table3.values())
    b2b_max = max(v["after"] for row in table4.values() for v in row.values())
    return {
        "experiment": "jl1", "seed": int(seed), "size": list(size) if size else None,
        "gcp_noise_px": float(gcp_noise_px), "tie_noise_px": float(tie_noise_px), "rpc_fit_max_px": fit_max,
        "paper": PAPER,
        "calibration": {"stages": est.stages, "sigma0": float(est.sigma0), "n_outliers": int(np.sum(est.outlier)),
                        "exterior": cal["exterior"]},
        "table3": table3, "table4": table4, "table5": {"orbits": orbits, "summary": summary5},
        "table6": {"scenes": scenes, "summary": summary6},
        "summary": {"interior_max_rms_px": interior_max, "interior_over_floor_max": floor_ratio,
                    "band_to_band_max_px": b2b_max, "ce90_m": summary5.get("ce90_m"),
                    "implied_ce90_m": summary5.get("implied_ce90_m"), "ce90_ratio": summary5.get("ratio"),
                    "check_planar_rms_m": summary6["max_check_planar_rms_m"]},
        "notes": ["Table 3: RMS of the model's (sample=across, line=along) error against the true model on a 15 x 7 "
                  "grid per image, px of the band; floor = RMS of the propagated 1-sigma of the correction",
                  "Table 4: blue pixels carried into the band by the models minus by the true models, px of the 3 m MS "
                  "band",
                  "Table 5: implied CE90 = 90th percentile of hypot(D roll, D pitch, x yaw) over the same points "
                  "(D = orbit radius - geocentric radius of the point, x = cross-track distance from the group centre, the orbit's drawn "
                  "attitude errors); expected = 2.146 D sigma (sigma = 3.6 arcsec per axis)",
                  "Table 6: 5 well-spread GCPs per scene over the 4 pan CCDs re-estimate the exterior (interiors "
                  "calibrated); the other GCPs are check points (localised on the DEM)"],
    }


def format_tables(rep: Dict[str, Any], bands: Optional[Sequence[str]] = None) -> str:
    """Tables 3-6 as text (module docstring)."""
    lines = [f"Jilin-1 KF01A group (simulated, seed {rep['seed']}, size {rep['size']}): GCP noise "
             f"{rep['gcp_noise_px']:g} px, tie noise {rep['tie_noise_px']:g} px", ""]
    lines.append("Table 3. Calibration accuracy per CCD and band vs the true model (RMS px of the band, "
                 "across / along track)")
    lines.append(f"{'image':12} {'before':>15} {'after':>15} {'floor':>15} {'check GCPs':>17}")
    for n, v in rep["table3"].items():
        c = v["check"]
        chk = f"{c['across']:7.3f}/{c['along']:<7.3f}({c['n']})" if c["n"] else "-"
        lines.append(f"{n:12} {v['before']['across']:7.2f}/{v['before']['along']:<7.2f} "
                     f"{v['after']['across']:7.3f}/{v['after']['along']:<7.3f} "
                     f"{v['floor']['across']:7.3f}/{v['floor']['along']:<7.3f} {chk:>17}")
    lines += ["", "Table 4. Band-to-band registration against blue (RMS px of the 3 m MS band, before / after)"]
    bands = list(bands or next(iter(rep["table4"].values())).keys())
    lines.append(f"{'CCD':6} " + " ".join(f"{b:>15}" for b in bands))
    for k, row in rep["table4"].items():
        lines.append(f"{k:6} " + " ".join(f"{row[b]['before']:7.2f}/{row[b]['after']:<7.3f}" for b in bands))
    t5 = rep["table5"]
    lines += ["", f"Table 5. {len(t5['orbits'])} orbits without control (calibration applied; pan grid points, m)",
              f"{'orbit':>6} {'roll/pitch/yaw (arcsec)':>24} {'RMS':>7} {'CE90':>7} {'implied':>8} {'b2b max px':>10}"]
    for o in t5["orbits"]:
        a = o["attitude_error_arcsec"]
        lines.append(f"{o['orbit_seed']:>6} {a['roll']:7.2f}/{a['pitch']:6.2f}/{a['yaw']:<8.2f} "
                     f"{o['planar_rms_m']:7.2f} {o['ce90_m']:7.2f} {o['implied_ce90_m']:8.2f} "
                     f"{o['band_to_band_max_px']:10.3f}")
    s = t5["summary"]
    if s:
        lines.append(f"{'all':>6} {'':24} {'':7} {s['ce90_m']:7.2f} {s['implied_ce90_m']:8.2f} "
                     f"{s['band_to_band_max_px']:10.3f}   CE90 / implied = {s['ratio']:.3f}; expected from "
                     f"3.6\" per axis: {s['expected_ce90_m']:.1f} m (paper < 20 m)")
    t6 = rep["table6"]
    lines += ["", f"Table 6. {len(t6['scenes'])} scenes with GCPs (exterior re-estimated; check points, m)",
              f"{'scene':>6} {'GCPs':>5} {'checks':>6} {'no GCP RMS':>10} {'RMS':>7} {'east':>7} {'north':>7}"]
    for sc in t6["scenes"]:
        a = sc["after"]
        lines.append(f"{sc['orbit_seed']:>6} {sc['n_control']:>5} {sc['n_check']:>6} "
                     f"{sc['before']['planar_rms_m']:10.2f} {a['planar_rms_m']:7.3f} {a['east_rms_m']:7.3f} "
                     f"{a['north_rms_m']:7.3f}")
    if t6["scenes"]:
        lines.append(f"{'all':>6} {'':5} {'':6} {'':10} {t6['summary']['check_planar_rms_m']:7.3f}   at "
                     f"{t6['summary']['gsd_m']:g} m GSD (paper < 2 m)")
    return "\n".join(lines)
