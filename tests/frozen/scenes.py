"""Seeded scenes and the computations whose numbers tests/frozen freezes (issue 10, item 1).

Every ``compute_*`` function runs today's public API on a fixed-seed scene and returns plain numbers through
:mod:`.adapters` only. ``make_frozen.py`` writes their output to ``data/*.json``; the tests recompute and compare.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Dict

import numpy as np
import pandas as pd

from gdal_gf4cal import RPCModel
from gdal_gf4cal.camera import LookAngleModel
from gdal_gf4cal.compensation import CompensatedRPC, CompensationModel, CompensationResult, fit_compensation
from gdal_gf4cal.intersection import intersect
from gdal_gf4cal.lookangle import calibrate_lookangle
from gdal_gf4cal.rpc_fit import fit_rpc_from_model
from gdal_gf4cal.simulate.geodesy import GEO_RADIUS, geodetic_to_ecef
from gdal_gf4cal.simulate.models import FrameModel

from . import adapters as ad

TESTS = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data"
COMP_DATA = TESTS / "data" / "compensation"

# ------------------------------------------------------------------------------------------------ compensation
# (model name, order, along, true sample coefficients, true line coefficients) in the RPC's normalised frame.
COMP_CASES = {
    "translation": ("translation", None, None, [4.3], [-2.7]),
    "shift-drift": ("shift-drift", None, None, [4.3, 1.8], [-2.7, -1.2]),
    "affine": ("affine", None, None, [4.3, 1.8, -0.9], [-2.7, 0.6, -1.2]),
    "poly2": ("poly2", None, None, [4.3, 1.8, -0.9, 0.8, -0.6, 0.4], [-2.7, 0.6, -1.2, -0.5, 0.7, 0.3]),
    "detector-poly1": ("detector-poly", 1, None, [4.3, 6.0], [-2.7]),
    "detector-poly2": ("detector-poly", 2, None, [4.3, 6.0, -3.0], [-2.7]),
    "detector-poly3": ("detector-poly", 3, None, [4.3, 6.0, -3.0, 5.0], [-2.7]),
    "detector-poly3-affine": ("detector-poly", 3, "affine", [4.3, 6.0, 0.7, -3.0, 5.0], [-2.7, 0.6, -1.2]),
}
N_GCP, N_CONTROL, SIGMA_PX = 60, 40, 0.3
BLUNDERS = {3: (18.0, -7.0), 11: (-6.0, 14.0), 27: (25.0, 3.0)}   # control index -> (ds, dl) px


def _frame_of(rpc):
    return (rpc.samp_off + 0.5, rpc.samp_scale, rpc.line_off + 0.5, rpc.line_scale)


def wv3_rpc():
    return RPCModel.from_file(COMP_DATA / "md_dg.RPB")


def comp_truth(rpc, key):
    """The true sensor: the WV3 RPC composed with the true correction of case ``key``."""
    name, order, along, cs, cl = COMP_CASES[key]
    model = CompensationModel.from_name(name, order=order, along=along)
    return CompensatedRPC(rpc, CompensationResult.from_coefficients(model, _frame_of(rpc), cs, cl)), model


def comp_gcps(truth, rpc, seed: int, blunders: bool) -> pd.DataFrame:
    """GCP simulator #4 (same recipe as tests/test_compensation.py::simulate_gcps) + optional planted blunders."""
    rng = np.random.default_rng(seed)
    n = N_GCP
    w, h = rpc.image_size
    s, l = rng.uniform(0, w, n), rng.uniform(0, h, n)
    hh = rng.uniform(*rpc.height_range, n)
    lon, lat = truth.localize(s, l, hh)
    ms, ml = s + rng.normal(0, SIGMA_PX, n), l + rng.normal(0, SIGMA_PX, n)
    if blunders:
        for i, (ds, dl) in BLUNDERS.items():
            ms[i] += ds
            ml[i] += dl
    return pd.DataFrame({"id": [f"g{i}" for i in range(n)], "lon": lon, "lat": lat, "h": hh, "sample": ms,
                         "line": ml, "role": np.where(np.arange(n) < N_CONTROL, "control", "check")})


def compute_compensation(key: str, blunders: bool) -> Dict[str, Any]:
    rpc = wv3_rpc()
    truth, model = comp_truth(rpc, key)
    seed = 1000 + list(COMP_CASES).index(key)
    gcps = comp_gcps(truth, rpc, seed, blunders)
    res = fit_compensation(rpc, gcps, model)
    return {"params": ad.comp_params(res), "param_std": ad.comp_param_std(res), "sigma0": ad.comp_sigma0(res),
            "redundancy": ad.comp_redundancy(res), "outliers": ad.comp_outlier_flags(res), "rms": ad.comp_rms(res)}


# ------------------------------------------------------------------------------------------------ GF4 look angles
W = 10240
K = 1.30e-6
HEIGHTS = (3000.0, 6500.0)


def frame_model(camera, target=(88.5, 32.5, 4500.0), sat_lon=105.6):
    """Geostationary frame camera (as tests/test_lookangle.py::frame_model, yaw 0)."""
    lam = np.radians(sat_lon)
    pos = GEO_RADIUS * np.array([np.cos(lam), np.sin(lam), 0.0])
    z = geodetic_to_ecef(*target) - pos
    z /= np.linalg.norm(z)
    lon, lat = np.radians(target[0]), np.radians(target[1])
    north = np.array([-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)])
    y = -(north - z * (north @ z))
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    return FrameModel(camera, pos, np.column_stack([x, y, z]), height_range=HEIGHTS)


def gf4_cameras():
    cur = LookAngleModel.from_nominal((W, W), 1.0, K, radial_k1=2.0, name="current")
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, W, 21), np.linspace(0, W, 21)))
    tx, ty = cur.tan_angles(S, L)
    th = 10.0 / 5120.0
    c, s = np.cos(th), np.sin(th)
    rx, ry = c * tx - s * ty + 3 * K, s * tx + c * ty - 2 * K
    r2 = rx * rx + ry * ry
    rx, ry = rx * (1 + 5.0 * r2) * (1 + 2e-4), ry * (1 + 5.0 * r2) * (1 + 2e-4)
    return cur, LookAngleModel.fit(S, L, rx, ry, size=(W, W), name="true")


def gf4_gcps(true_model, n=200, sigma=0.5, seed=7, n_blunders=8):
    """GCP simulator #1 (as tests/test_lookangle.py::make_gcps) with a fixed number of blunders."""
    rng = np.random.default_rng(seed)
    s, l = rng.uniform(0, W, n), rng.uniform(0, W, n)
    h = rng.uniform(*HEIGHTS, n)
    lon, lat = true_model.localize(s, l, h)
    ms, ml = s + rng.normal(0, sigma, n), l + rng.normal(0, sigma, n)
    idx = rng.choice(n, n_blunders, replace=False)
    mag, ang = rng.uniform(10, 50, idx.size), rng.uniform(0, 2 * np.pi, idx.size)
    ms[idx] += mag * np.cos(ang)
    ml[idx] += mag * np.sin(ang)
    return pd.DataFrame({"id": [f"g{i}" for i in range(n)], "lon": lon, "lat": lat, "h": h, "sample": ms,
                         "line": ml, "role": "control", "sigma": sigma})


def gf4_scene():
    cur, true = gf4_cameras()
    m_cur, m_true = frame_model(cur), frame_model(true)
    rpc, rep = fit_rpc_from_model(m_cur, height_range=HEIGHTS)
    return cur, true, m_cur, m_true, rpc, rep


def compute_lookangle(scene=None) -> Dict[str, Any]:
    cur, true, m_cur, m_true, rpc, _ = scene or gf4_scene()
    calib = calibrate_lookangle(rpc, gf4_gcps(m_true), cur)
    return {"coefficients": ad.la_coefficients(calib), "tan_grid": ad.la_tan_grid(calib),
            "precision_px": ad.la_precision(calib), "outliers": ad.la_outlier_flags(calib),
            "residual_rms": ad.la_residual_rms(calib)}


def compute_rpc_fit(scene=None) -> Dict[str, Any]:
    """RPC fit errors for two simulated sensors: the GF4 frame camera with the current and the true camera."""
    cur, true, m_cur, m_true, _, rep_cur = scene or gf4_scene()
    _, rep_true = fit_rpc_from_model(m_true, height_range=HEIGHTS)
    return {"gf4_current": ad.rpcfit_errors(rep_cur), "gf4_true": ad.rpcfit_errors(rep_true)}


# ------------------------------------------------------------------------------------------------ intersection
LEFT = COMP_DATA / "RPC_P1BP--2017092838284574CP.XML"
RIGHT = COMP_DATA / "RPC_P1BP--2017092838319324CP.XML"


def compute_intersection(n=40, sigma=0.5, seed=5) -> Dict[str, Any]:
    """Pleiades stereo pair (2 real RPCs): seeded ground points, noisy image points, forward intersection.

    Point 0 is observed in the left image only (exercises the NaN path).
    """
    pair = RPCModel.from_file(LEFT), RPCModel.from_file(RIGHT)
    rng = np.random.default_rng(seed)
    w, h = pair[0].image_size
    s, l = rng.uniform(0.1 * w, 0.9 * w, n), rng.uniform(0.1 * h, 0.9 * h, n)
    hh = rng.uniform(50, 800, n)
    lon, lat = pair[0].localize(s, l, hh)
    pts = np.stack([np.column_stack(m.project(lon, lat, hh)) for m in pair])
    pts = pts + rng.normal(0, sigma, pts.shape)
    pts[1, 0] = np.nan
    res = intersect(pair, pts, sigma_px=sigma)
    return {"coordinates": ad.ix_coordinates(res), "sigmas": ad.ix_sigmas(res), "cov_enu_m2": ad.ix_covariance(res)}


# ------------------------------------------------------------------------------------------------ experiments
def compute_experiment(name: str, out_dir) -> Dict[str, Any]:
    """``gf4cal experiment <name>`` through its Python entry point, numbers only (flattened report)."""
    from gdal_gf4cal.experiments import gf4, hj1, zy3
    mod = {"gf4": gf4, "hj1": hj1, "zy3": zy3}[name]
    rep = mod.run(out_dir, write_files=False, verbose=False)
    return ad.experiment_numbers(rep)
