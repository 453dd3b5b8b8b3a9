"""The GF4 test bed of the look-angle tests: a camera in geostationary orbit (105.6 E) looking at Tibet (88.5 E,
32.5 N) through the simulator's rigorous frame model, 10240 x 10240 detectors, a *current* and a *true* camera
(shared by tests/lookangle, tests/batch and the frozen numbers' copies)."""
from __future__ import annotations

import numpy as np

from gdal_gf4cal.camera import LookAngleModel
from gdal_gf4cal.simulate.geodesy import GEO_RADIUS, geodetic_to_ecef
from gdal_gf4cal.simulate.models import FrameModel

W = 10240


K = 1.30e-6                       # tan units per detector (~55 m at 36,000 km slant range)


HEIGHTS = (3000.0, 6500.0)


def frame_model(camera, target=(88.5, 32.5, 4500.0), sat_lon=105.6, yaw=0.0):
    """Rigorous frame model: geostationary camera whose boresight hits ``target``, x east-ish, y south-ish."""
    lam = np.radians(sat_lon)
    pos = GEO_RADIUS * np.array([np.cos(lam), np.sin(lam), 0.0])
    z = geodetic_to_ecef(*target) - pos
    z /= np.linalg.norm(z)
    lon, lat = np.radians(target[0]), np.radians(target[1])
    north = np.array([-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)])
    y = -(north - z * (north @ z))
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    c, s = np.cos(yaw), np.sin(yaw)
    x, y = c * x + s * y, -s * x + c * y
    return FrameModel(camera, pos, np.column_stack([x, y, z]), height_range=HEIGHTS)


def make_cameras():
    """Current camera (nominal + mild radial) and the true one (yaw 10 px at the edge, radial ~4 px, offsets)."""
    cur = LookAngleModel.from_nominal((W, W), 1.0, K, radial_k1=2.0, name="current")
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, W, 21), np.linspace(0, W, 21)))
    tx, ty = cur.tan_angles(S, L)
    th = 10.0 / 5120.0
    c, s = np.cos(th), np.sin(th)
    rx, ry = c * tx - s * ty + 3 * K, s * tx + c * ty - 2 * K
    r2 = rx * rx + ry * ry
    rx, ry = rx * (1 + 5.0 * r2) * (1 + 2e-4), ry * (1 + 5.0 * r2) * (1 + 2e-4)
    return cur, LookAngleModel.fit(S, L, rx, ry, size=(W, W), name="true")


def dense_check(model, n=50, seed=99):
    rng = np.random.default_rng(seed)
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(5, W - 5, n), np.linspace(5, W - 5, n)))
    H = rng.uniform(*HEIGHTS, S.size)
    lon, lat = model.localize(S, L, H)
    return lon, lat, H, S, L
