"""Building blocks shared by the simulated sensors (METHODS §10): the scene/image records, crops, orbits aligned
over a centre, linear cameras, yaw steering and the push-broom model pair (current, true) of one image.

:mod:`.sensors` (GF4, ZY-3, HJ-1 and the registry), :mod:`.jl1` and :mod:`.gf7` build on this module, which imports
none of them (no import cycle).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from ..errors import Gf4calError
from .cameras import PiecewiseCamera, camera_from_normalised_polys, crop_camera
from .geodesy import WGS84_A, enu_basis, geodetic_to_ecef
from .models import CAMERA_TO_BODY, Attitude, CircularOrbit, PushbroomModel

ARCSEC = np.pi / 180 / 3600


class SimulationError(Gf4calError, ValueError):
    """Invalid simulation parameters (unknown sensor, bad size or centre)."""


@dataclass
class SimImage:
    """One image of a simulated scene: its two rigorous models and what differs between them.

    ``name`` is the sub-folder ("" for single-image sensors); ``current``/``true`` are :class:`FrameModel` or
    :class:`PushbroomModel` objects with ``project``/``localize``/``localize_dem``/``look_angles``/``size``/
    ``height_range``/``camera``; ``errors`` describes the injected errors; ``gsd_m`` the nominal ground sample
    distance at the image centre.
    """

    name: str
    current: object
    true: object
    gsd_m: float
    errors: Dict = field(default_factory=dict)
    info: Dict = field(default_factory=dict)

    @property
    def size(self) -> Tuple[int, int]:
        return self.current.size

    def virtual_image_point(self, lon, lat, h):
        """The current rigorous model's image point of ground points: the exact analogue of ``RPC(B, L, H)``
        (METHODS §5 step 1). Same as ``current.project``."""
        return self.current.project(lon, lat, h)


@dataclass
class SimScene:
    """A simulated scene: images, DEM and the full truth record (``truth`` is what truth.json holds)."""

    sensor: str
    seed: int
    center: Tuple[float, float]
    images: List[SimImage]
    dem: object                      # gdal_gf4cal.dem.DEM
    dem_path: Optional[str]
    truth: Dict

    def image(self, name: str = "") -> SimImage:
        for im in self.images:
            if im.name == name:
                return im
        raise SimulationError(f"no image {name!r} in this {self.sensor} scene; "
                              f"choose one of {[im.name for im in self.images]}")

    @property
    def is_multi_image(self) -> bool:
        return len(self.images) > 1 or self.images[0].name != ""


@dataclass
class SensorSpec:
    name: str
    description: str
    default_center: Tuple[float, float]
    relief_m: Tuple[float, float]
    build: Callable
    images: Tuple[str, ...]
    options: Tuple[str, ...] = ()            # keyword options of ``build`` (make_scene(..., options={...}))
    #: ``write_observations(scene, out_dir, gcps, observation_options, written) -> truth record``: writes the
    #: sensor's long observation table (GCPs + tie points) beside the images (jl1), or None.
    write_observations: Optional[Callable] = None
    #: ``write_images(scene, results, *, render, reference, windows, workers, tile, progress, written) -> truth
    #: record``: writes the images itself, in place of the one-band render or placeholder of
    #: :func:`.scene.write_scene` (gf7: pan + 4-band MS, cover mask, true pan-MS field), or None.
    write_images: Optional[Callable] = None
    #: ``crop_windows(crop) -> {image name: (x0, y0, w, h)}``: the windows of each image's product that a crop
    #: ``(x0, y0, w, h)`` of the first image covers (``write_scene(crop=...)``; checked there), or None (no crops).
    crop_windows: Optional[Callable] = None


def _crop(full: Tuple[int, int], size: Optional[Tuple[int, int]]):
    if size is None:
        return tuple(full), (0, 0)
    W, H = int(size[0]), int(size[1])
    if W < 16 or H < 16:
        raise SimulationError(f"--size {W} {H} is too small; use at least 16 x 16 pixels")
    if W > full[0] or H > full[1]:
        raise SimulationError(f"--size {W} {H} exceeds the detector array {full[0]} x {full[1]}; "
                              "choose a smaller crop")
    return (W, H), ((full[0] - W) // 2, (full[1] - H) // 2)


def _scale_size(full, size, ref_full):
    """Crop of a secondary image matching a crop of the reference image in ground extent."""
    if size is None:
        return None
    return (max(16, int(round(size[0] * full[0] / ref_full[0]))), max(16, int(round(size[1] * full[1] / ref_full[1]))))


def _orbit_over(lon, lat, altitude, incl_deg):
    """Circular orbit whose sub-satellite point at t = 0 is near geodetic (lon, lat), descending."""
    phi_c = np.arctan((1 - 0.00669437999014) * np.tan(np.radians(lat)))
    i = np.radians(incl_deg)
    u = np.pi - np.arcsin(np.clip(np.sin(phi_c) / np.sin(i), -1, 1))
    raan = np.radians(lon) - np.arctan2(np.sin(u) * np.cos(i), np.cos(u))
    return CircularOrbit(WGS84_A + altitude, incl_deg, float(raan), float(u))


def _probe(orbit, attitude, install, camera):
    return PushbroomModel(camera, orbit, attitude, install, t_center=0.0, line_center=0.0, line_period=1.0)


def _align_orbit(center, h, altitude, incl, camera, install, s_ref):
    """Orbit such that detector ``s_ref`` of ``camera`` (mounted with ``install``) sees ``center`` at t = 0."""
    target = np.array(center, dtype=float)
    att = Attitude()
    for _ in range(6):
        orbit = _orbit_over(target[0], target[1], altitude, incl)
        lon, lat = _probe(orbit, att, install, camera).localize(s_ref, 0.0, h)
        target = target - (np.array([lon, lat]) - np.array(center))
    # Beyond the ground track's highest latitude (180 - inclination) _orbit_over clips, and the iteration above
    # chased an unreachable target into the other hemisphere (--center 0 85 gave a scene at lat -82 while truth.json
    # said 85): check that the orbit really sees the centre.
    lon, lat = _probe(orbit, att, install, camera).localize(s_ref, 0.0, h)
    d_lon = (lon - center[0] + 180.0) % 360.0 - 180.0
    if not (np.isfinite(lon) and np.isfinite(lat)) or abs(lat - center[1]) > 1e-3 or \
            abs(d_lon) * np.cos(np.radians(center[1])) > 1e-3:
        reach = 180.0 - incl if incl > 90.0 else incl
        raise SimulationError(f"the simulated orbit (inclination {incl:g} deg) cannot see the centre "
                              f"({center[0]:g}, {center[1]:g}): beyond the orbit's reach, its ground track covers "
                              f"latitudes -{reach:.1f} to {reach:.1f} deg; choose a centre with |lat| <= "
                              f"{np.floor(reach) - 2:g}")
    return orbit


def _center_time(orbit, install, camera, center, h, s_ref, attitude=None):
    """Time at which detector ``s_ref`` sees the along-track position of ``center``; and the ground speed."""
    probe = _probe(orbit, attitude or Attitude(), install, camera)
    C = geodetic_to_ecef(center[0], center[1], h)
    t = 0.0
    for _ in range(6):
        g0 = geodetic_to_ecef(*probe.localize(s_ref, t, h), h)
        g1 = geodetic_to_ecef(*probe.localize(s_ref, t + 1.0, h), h)
        v = g1 - g0
        speed = np.linalg.norm(v)
        t -= float(np.dot(g0 - C, v / speed) / speed)
    return t, speed


def _linear_camera(full, ifov, tx0, ty0, name, extra_x=None, extra_y=None):
    hs = full[0] / 2.0

    def fx(u, v):
        return tx0 + ifov * hs * u + (ifov * extra_x(u) if extra_x else 0.0)

    def fy(u, v):
        return ty0 + 0.0 * u + (ifov * extra_y(u) if extra_y else 0.0)

    return camera_from_normalised_polys(full, fx, fy, name=name)


def _poly_px(coeffs):
    """u -> sum c_k u^k (pixels), ascending coefficients."""
    return lambda u: np.polyval(list(coeffs)[::-1], u)


def _pushbroom(name, full, size, cam_cur, cam_true, orbit, att_cur, att_true, install, center, h_mid, gsd,
               errors, info):
    """Assemble one push-broom image (crop, timing) from full-array cameras."""
    (W, H), (x0, y0) = _crop(full, size)
    s_ref = full[0] / 2.0
    t_c, speed = _center_time(orbit, install, cam_cur, center, h_mid, s_ref, att_cur)
    period = gsd / speed
    if (W, H) != tuple(full):
        # Crops are centred on the scene centre's image point (the views of a stereo/pan-MS set see it at
        # slightly different detectors because the Earth turns between the looks).
        probe = PushbroomModel(cam_cur, orbit, att_cur, install, t_center=t_c, line_center=full[1] / 2.0,
                               line_period=period)
        s_c, l_c = probe.project(center[0], center[1], h_mid)
        x0 = int(np.clip(round(s_c - W / 2.0), 0, full[0] - W))
        y0 = int(np.clip(round(l_c - H / 2.0), 0, full[1] - H))
    if (x0, y0) != (0, 0) or (W, H) != full:
        cam_cur = _crop_any(cam_cur, (x0, y0), (W, H))
        cam_true = _crop_any(cam_true, (x0, y0), (W, H))
    line_center = full[1] / 2.0 - y0
    kw = dict(t_center=t_c, line_center=line_center, line_period=period)
    current = PushbroomModel(cam_cur, orbit, att_cur, install, name=f"{name} current", **kw)
    true = PushbroomModel(cam_true, orbit, att_true, install, name=f"{name} true", **kw)
    info = dict(info, full_size=list(full), crop_offset=[x0, y0], t_center_s=t_c, line_period_s=period,
                ground_speed_m_s=speed, line_center=line_center)
    return current, true, info


def _crop_any(cam, offset, size):
    if isinstance(cam, PiecewiseCamera):
        return PiecewiseCamera(size, [crop_camera(p, offset, size) for p in cam.pieces], cam.edges - offset[0],
                               cam.name, cam.notes)
    return crop_camera(cam, offset, size)


def _yaw_steering(orbit, center, h, full, ifov, ty0):
    """Constant yaw that makes a camera looking ``ty0`` along track see ``center`` with its central detector."""
    cam = _linear_camera(full, ifov, 0.0, ty0, "probe")
    C = geodetic_to_ecef(center[0], center[1], h)

    def offset(yaw):
        att = Attitude(yaw=(yaw,))
        t, _ = _center_time(orbit, CAMERA_TO_BODY, cam, center, h, full[0] / 2.0, att)
        probe = _probe(orbit, att, CAMERA_TO_BODY, cam)
        g0 = geodetic_to_ecef(*probe.localize(full[0] / 2.0, t, h), h)
        g1 = geodetic_to_ecef(*probe.localize(full[0] / 2.0 + 1.0, t, h), h)
        across = (g1 - g0) / np.linalg.norm(g1 - g0)
        return float(np.dot(g0 - C, across))

    yaw, d = 0.0, 1e-3
    for _ in range(5):
        f0 = offset(yaw)
        yaw -= f0 * d / (offset(yaw + d) - f0)
    return yaw


def _shift_center(center, orbit, cross_m):
    """The scene centre moved ``cross_m`` metres to the left of the flight direction (camera +x)."""
    pos, vel = orbit.inertial(0.0)
    east, north, _ = enu_basis(center[0], center[1])
    fwd = np.array([np.dot(vel, east), np.dot(vel, north)])
    fwd /= np.linalg.norm(fwd)
    left = np.array([-fwd[1], fwd[0]])
    lat_m = 111320.0
    return (center[0] + cross_m * left[0] / (lat_m * np.cos(np.radians(center[1]))),
            center[1] + cross_m * left[1] / lat_m)


#: The sensor registry: name -> :class:`SensorSpec`. :mod:`.sensors` registers gf4, zy3 and hj1, :mod:`.jl1` and
#: :mod:`.gf7` register themselves (``gdal_gf4cal.simulate`` imports all three, in that order).
SENSORS: Dict[str, SensorSpec] = {}
