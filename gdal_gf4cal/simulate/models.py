"""Rigorous sensor models of the simulator (METHODS §10): frame (area array) and push-broom cameras.

Both models implement the one sensor-model contract (:class:`gdal_gf4cal.sensor.SensorModel`, through
:class:`~gdal_gf4cal.sensor.SensorModelMixin`: the same verbs and keywords as :class:`gdal_gf4cal.RPCModel`, GDAL
pixel convention, centre of the first pixel at 0.5, scalars in and Python floats out):

``project(lon, lat, h) -> (sample, line)``          ground to image (push-broom: the line/time is solved)
``localize(sample, line, h) -> (lon, lat)``         image to ground at ellipsoidal height h
``localize_dem(sample, line, dem) -> (lon, lat, h)`` line of sight x DEM
``look_angles(lon, lat, h) -> (tan_x, tan_y)``      direction of the ground point in the camera frame (at its
                                                    imaging time): ``camera.tan_angles(project(...))`` exactly
``look_vectors(sample, line) -> (origin, direction)`` ECEF ray of an image point
``with_camera(camera)``                              the same exterior orientation with another camera
``size``, ``height_range``, ``camera``

Camera frame: ``z`` along the boresight (towards the Earth), ``x`` along increasing samples, ``y`` along increasing
lines; a detector ``(s, l)`` looks along ``(tan_x, tan_y, 1)`` with ``(tan_x, tan_y) = camera.tan_angles(s, l)``.
For push-brooms the camera has no ``l`` terms; ``line`` is time: ``t = t_center + (line - line_center) * period``.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import List, Sequence, Tuple

import numpy as np

from ..sensor import SensorModelMixin
from .geodesy import (GM_EARTH, OMEGA_EARTH, ecef_to_geodetic, geodetic_to_ecef, ray_height_intersection,
                      rot_x, rot_y, rot_z)


def _arr(*xs):
    return np.broadcast_arrays(*[np.asarray(x, dtype=float) for x in xs])


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class _ModelBase(SensorModelMixin):
    """The shared half of the simulator's models: the :class:`~gdal_gf4cal.sensor.SensorModel` contract through
    :class:`~gdal_gf4cal.sensor.SensorModelMixin` (scalars, shapes, pixel convention, ``full_output``,
    ``localize_dem`` through the localisation layer, numeric ``project_jacobian``)."""

    camera = None
    height_range: Tuple[float, float] = (0.0, 0.0)
    name: str = ""

    @property
    def size(self) -> Tuple[int, int]:
        return tuple(self.camera.size)

    def with_camera(self, camera):
        """A copy with another camera (same exterior orientation, METHODS §5: only the look angles change)."""
        m = copy.copy(self)
        m.camera = camera
        return m

    def _localize_gdal(self, sample, line, h):
        """Ground ``(lon, lat)`` of image points at ellipsoidal height ``h`` (flat arrays, GDAL convention)."""
        o, d = self.look_vectors(sample, line)
        t = ray_height_intersection(o, d, h)
        lon, lat, _ = ecef_to_geodetic(o + t[:, None] * d)
        return lon, lat

    def localize_dem(self, sample, line, dem, *, pixel_convention: str = "gdal", full_output: bool = False, **kw):
        """``(lon, lat, h)`` where the lines of sight meet ``dem`` (a DEM or a height); NaN where they miss.

        Uses :func:`gdal_gf4cal.localization.localize_dem` (``tol_m`` 1e-5 m by default); ``(lon, lat)`` is exactly
        ``localize(s, l, h)`` for the returned ``h``, so ``project`` of the result returns the input to round-off.
        """
        kw.setdefault("tol_m", 1e-5)
        return super().localize_dem(sample, line, dem, pixel_convention=pixel_convention, full_output=full_output,
                                    **kw)


class FrameModel(_ModelBase):
    """Area-array camera exposed at one instant (GF4 from geostationary orbit).

    Parameters
    ----------
    camera : LookAngleModel (detector numbers = image coordinates).
    position : satellite position, ECEF (3,), metres.
    rotation : (3, 3) camera-to-ECEF rotation (columns: camera x, y, z axes in ECEF).
    """

    def __init__(self, camera, position, rotation, height_range=(0.0, 0.0), name: str = "frame"):
        self.camera = camera
        self.position = np.asarray(position, dtype=float)
        self.rotation = np.asarray(rotation, dtype=float)
        self.height_range = tuple(float(v) for v in height_range)
        self.name = name

    def look_vectors(self, sample, line):
        tx, ty = self.camera.tan_angles(np.asarray(sample, float), np.asarray(line, float))
        d = np.stack(np.broadcast_arrays(tx, ty, 1.0), axis=-1)
        d = _unit(d) @ self.rotation.T
        return np.broadcast_to(self.position, d.shape), d

    def look_angles(self, lon, lat, h):
        """``(tan_x, tan_y)`` of ground points in the camera frame (NaN behind the camera)."""
        lon, lat, h = _arr(lon, lat, h)
        v = (geodetic_to_ecef(lon, lat, h) - self.position) @ self.rotation
        z = np.where(v[..., 2] > 0, v[..., 2], np.nan)
        return v[..., 0] / z, v[..., 1] / z

    def _project_gdal(self, lon, lat, h):
        """Image ``(sample, line)`` of ground points (flat arrays, GDAL convention)."""
        tx, ty = self.look_angles(lon, lat, h)
        s, l = self.camera.detector_of(tx, ty, tol_px=1e-11)
        return np.asarray(s, float), np.asarray(l, float)


@dataclass
class CircularOrbit:
    """Circular Keplerian orbit; inertial frame = ECEF at t = 0 (the Earth then rotates under it).

    ``u(t) = u0 + n t`` is the argument of latitude, ``raan`` the right ascension of the ascending node.
    """

    radius: float
    inclination_deg: float
    raan: float
    u0: float

    @property
    def mean_motion(self) -> float:
        return float(np.sqrt(GM_EARTH / self.radius ** 3))

    def inertial(self, t):
        """Position and velocity (..., 3) in the inertial frame at times ``t`` (s)."""
        t = np.asarray(t, dtype=float)
        n = self.mean_motion
        u = self.u0 + n * t
        i = np.radians(self.inclination_deg)
        cu, su = np.cos(u), np.sin(u)
        cO, sO, ci, si = np.cos(self.raan), np.sin(self.raan), np.cos(i), np.sin(i)
        r = self.radius
        pos = r * np.stack([cu * cO - su * ci * sO, cu * sO + su * ci * cO, su * si], axis=-1)
        vel = r * n * np.stack([-su * cO - cu * ci * sO, -su * sO + cu * ci * cO, cu * si], axis=-1)
        return pos, vel

    def to_dict(self):
        return {"type": "circular", "radius_m": self.radius, "altitude_m": self.radius - 6378137.0,
                "inclination_deg": self.inclination_deg, "raan_rad": self.raan, "u0_rad": self.u0}


@dataclass
class Attitude:
    """Body attitude relative to the orbital frame: roll/pitch/yaw polynomials in time (rad, rad/s, ...) + jitter.

    Body-to-orbital rotation ``Rz(yaw) Ry(pitch) Rx(roll)``. ``jitter`` is a list of
    ``(axis, amplitude_rad, frequency_hz, phase_rad)`` sinusoids added to the angles (axis in roll/pitch/yaw).
    """

    roll: Sequence[float] = (0.0,)
    pitch: Sequence[float] = (0.0,)
    yaw: Sequence[float] = (0.0,)
    jitter: List[Tuple[str, float, float, float]] = field(default_factory=list)

    def angles(self, t):
        t = np.asarray(t, dtype=float)
        out = {}
        for axis in ("roll", "pitch", "yaw"):
            c = list(getattr(self, axis))
            a = np.polyval(c[::-1], t) if c else np.zeros_like(t)
            for ax, amp, f, ph in self.jitter:
                if ax == axis:
                    a = a + amp * np.sin(2 * np.pi * f * t + ph)
            out[axis] = a + np.zeros_like(t)
        return out["roll"], out["pitch"], out["yaw"]

    def matrix(self, t):
        r, p, y = self.angles(t)
        return rot_z(y) @ rot_y(p) @ rot_x(r)

    def to_dict(self):
        return {"roll": list(self.roll), "pitch": list(self.pitch), "yaw": list(self.yaw),
                "jitter": [list(j) for j in self.jitter], "convention": "body->orbital = Rz(yaw) Ry(pitch) Rx(roll); "
                "angles in rad, polynomial coefficients in ascending powers of t (s)"}


#: Camera -> body (orbital) axes for a nadir push-broom: camera x = left of the flight direction (increasing
#: samples), camera y = flight direction (increasing lines), camera z = nadir.
CAMERA_TO_BODY = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


class PushbroomModel(_ModelBase):
    """Linear-array camera scanning with the orbit (ZY-3, HJ-1, JL1, GF7).

    Parameters
    ----------
    camera : LookAngleModel (l terms zero) or PiecewiseCamera; ``tan_x`` across track, ``tan_y`` along track.
    orbit : :class:`CircularOrbit`.
    attitude : :class:`Attitude` (polynomials in t, jitter).
    install : (3, 3) camera-to-body rotation (default :data:`CAMERA_TO_BODY`; a tilted camera premultiplies it).
    t_center, line_center, line_period : ``t(line) = t_center + (line - line_center) * line_period``.
    """

    def __init__(self, camera, orbit: CircularOrbit, attitude: Attitude, install=None, *, t_center=0.0,
                 line_center=0.0, line_period=1e-4, height_range=(0.0, 0.0), name: str = "pushbroom"):
        self.camera = camera
        self.orbit = orbit
        self.attitude = attitude
        self.install = CAMERA_TO_BODY if install is None else np.asarray(install, dtype=float)
        self.t_center = float(t_center)
        self.line_center = float(line_center)
        self.line_period = float(line_period)
        self.height_range = tuple(float(v) for v in height_range)
        self.name = name
        self._build_sample_table()

    def with_camera(self, camera):
        m = super().with_camera(camera)
        m._build_sample_table()
        return m

    def time_of_line(self, line):
        return self.t_center + (np.asarray(line, dtype=float) - self.line_center) * self.line_period

    def line_of_time(self, t):
        return self.line_center + (np.asarray(t, dtype=float) - self.t_center) / self.line_period

    def platform(self, t):
        """Satellite ECEF position (..., 3) and camera-to-ECEF rotation (..., 3, 3) at times ``t``."""
        t = np.asarray(t, dtype=float)
        pos, vel = self.orbit.inertial(t)
        z = -_unit(pos)
        y = -_unit(np.cross(pos, vel))
        x = np.cross(y, z)
        orb = np.stack([x, y, z], axis=-1)                     # orbital -> inertial (columns)
        earth = rot_z(-OMEGA_EARTH * t)                        # inertial -> ECEF
        R = earth @ orb @ self.attitude.matrix(t) @ self.install
        return np.einsum("...ij,...j->...i", earth, pos), R

    def look_vectors(self, sample, line):
        s, l = _arr(sample, line)
        tx, ty = self.camera.tan_angles(s, np.zeros_like(s))
        d = _unit(np.stack([tx, ty, np.ones_like(tx)], axis=-1))
        pos, R = self.platform(self.time_of_line(l))
        return pos, np.einsum("...ij,...j->...i", R, d)

    def look_angles_at(self, lon, lat, h, line):
        """Camera-frame ``(tan_x, tan_y)`` of ground points at the time of image line ``line``."""
        lon, lat, h, line = _arr(lon, lat, h, line)
        pos, R = self.platform(self.time_of_line(line))
        v = np.einsum("...ji,...j->...i", R, geodetic_to_ecef(lon, lat, h) - pos)
        z = np.where(v[..., 2] > 0, v[..., 2], np.nan)
        return v[..., 0] / z, v[..., 1] / z

    # --------------------------------------------------------------- 1-D inversion of the detector line
    def _build_sample_table(self):
        W = self.camera.size[0]
        s = np.linspace(0.0, W, 257)
        tx, _ = self.camera.tan_angles(s, np.zeros_like(s))
        order = np.argsort(tx)
        self._tab_tx, self._tab_s = tx[order], s[order]

    def sample_of_tan(self, tx):
        """Detector number whose ``tan_x`` equals ``tx`` (1-D Newton from a table; extrapolates linearly)."""
        tx = np.asarray(tx, dtype=float)
        tab_tx, tab_s = self._tab_tx, self._tab_s
        slope = (tab_s[-1] - tab_s[0]) / (tab_tx[-1] - tab_tx[0])
        s = np.interp(tx, tab_tx, tab_s)
        s = np.where(tx < tab_tx[0], tab_s[0] + (tx - tab_tx[0]) * slope, s)
        s = np.where(tx > tab_tx[-1], tab_s[-1] + (tx - tab_tx[-1]) * slope, s)
        zero = np.zeros_like(s)
        for _ in range(6):
            cx, _ = self.camera.tan_angles(s, zero)
            J = self.camera.jacobian(s, zero)
            s = s + (tx - cx) / J[..., 0, 0]
        return s

    def _project_gdal(self, lon, lat, h, tol_px: float = 1e-8, max_iter: int = 30):
        """Image ``(sample, line)`` of ground points (flat arrays, GDAL convention): Newton on the line (time) at
        which the ground point lies in the plane of view of its detector. NaN where it does not converge."""
        P = geodetic_to_ecef(lon, lat, h)
        n = P.shape[0]
        line = np.full(n, self.line_center)
        sample = np.full(n, np.nan)
        ok = np.zeros(n, dtype=bool)
        idx = np.arange(n)
        dl = 1.0

        def residual(ii, ll):
            pos, R = self.platform(self.time_of_line(ll))
            v = np.einsum("...ji,...j->...i", R, P[ii] - pos)
            tx, ty = v[:, 0] / v[:, 2], v[:, 1] / v[:, 2]
            s = self.sample_of_tan(tx)
            _, ty_cam = self.camera.tan_angles(s, np.zeros_like(s))
            return ty - ty_cam, s

        for _ in range(max_iter):
            f0, s0 = residual(idx, line[idx])
            f1, _ = residual(idx, line[idx] + dl)
            step = -f0 * dl / (f1 - f0)
            line[idx] += step
            sample[idx] = s0
            done = np.abs(step) < tol_px
            bad = ~np.isfinite(step)
            if np.any(done):
                # One more evaluation so the sample corresponds to the final line.
                _, s_fin = residual(idx[done], line[idx[done]])
                sample[idx[done]] = s_fin
                ok[idx[done]] = True
            idx = idx[~done & ~bad]
            if idx.size == 0:
                break
        sample[~ok], line[~ok] = np.nan, np.nan
        return sample, line

    def look_angles(self, lon, lat, h):
        """Camera-frame ``(tan_x, tan_y)`` of ground points at their imaging time (= camera.tan_angles(project))."""
        lon, lat, h = _arr(lon, lat, h)
        _, line = self.project(lon, lat, h)
        return self.look_angles_at(lon, lat, h, line)
