"""The simulated sensors (METHODS §10): GF4, ZY-3, HJ-1, Jilin-1 KF01A, GF7 -- each with a *current* and a *true*
rigorous model per image, a DEM and a record of every injected error.

* ``current``: the model the ground segment uses; the scene RPC is fitted from it (it carries the systematic
  errors relative to the truth).
* ``true``: the physical truth; GCP image positions and rendered pixels come from it.

GF4 (the look-angle calibration test bed, METHODS §5): both states share the exterior orientation exactly and
differ only by the camera, ``V_true = Rot(theta) V_current + t + D`` with ``D`` cubic in the detector numbers,
so the true camera is itself a cubic look-angle model and ``V_true(s, l) = V_current(s', l')`` holds exactly for
the true image point (s, l) and the current one (s', l') of any ground point.
"""
from __future__ import annotations

import uuid
from typing import Dict, Optional

import numpy as np

from ..dem import DEM
from ..errors import DEMError
from ..progress import report
from .cameras import camera_from_normalised_polys, crop_camera
from .geodesy import (GEO_RADIUS, WGS84_A, enu_basis, geodetic_to_ecef, rot_x)
from .models import CAMERA_TO_BODY, Attitude, FrameModel
from .terrain import synthetic_dem_array, write_dem_tif
from .building import (ARCSEC, SENSORS, SensorSpec, SimImage, SimScene, SimulationError, _align_orbit, _crop,  # noqa: F401
                       _linear_camera, _poly_px, _pushbroom, _scale_size, _yaw_steering)









# ------------------------------------------------------------------------------------------------ sensor specs






# ------------------------------------------------------------------------------------------------------- GF4
def _build_gf4(rng, center, size, h_mid):
    full = (10240, 10240)
    (W, H), (x0, y0) = _crop(full, size)
    sat_lon = 105.6
    sat = geodetic_to_ecef(sat_lon, 0.0, GEO_RADIUS - WGS84_A)
    target = geodetic_to_ecef(center[0], center[1], h_mid)
    z = target - sat
    z /= np.linalg.norm(z)
    east, _, _ = enu_basis(center[0], center[1])
    x = east - np.dot(east, z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    # Exterior orientation (identical in both states): the pointing as commanded, plus a small unknown yaw/
    # pitch/roll that the current camera file absorbs anyway (METHODS §5: exterior errors act like interior ones).
    R = np.column_stack([x, y, z])
    ifov = 50.0 / 35786e3                     # 50 m at the sub-satellite point
    hs, hl = full[0] / 2.0, full[1] / 2.0
    k3_model = 0.8                            # modelled radial distortion in the current camera (px at r = 1)

    def cur_x(u, v):
        return ifov * (hs * u + k3_model * u * (u * u + v * v))

    def cur_y(u, v):
        return ifov * (hl * v + k3_model * v * (u * u + v * v))

    theta = rng.choice([-1.0, 1.0]) * rng.uniform(3.0e-3, 3.4e-3)     # yaw: ~10 px RMS of rotation
    t_px = (rng.uniform(1.5, 3.0) * rng.choice([-1, 1]), rng.uniform(1.5, 3.0) * rng.choice([-1, 1]))
    kx, ky = rng.uniform(2.2, 2.5), rng.uniform(1.8, 2.1)             # per-axis scale (focal/pitch), px at edge
    k3 = rng.uniform(0.25, 0.4)                                       # unmodelled cubic radial, px at r = 1
    c, s_ = np.cos(theta), np.sin(theta)

    def true_x(u, v):
        return c * cur_x(u, v) - s_ * cur_y(u, v) + ifov * (t_px[0] + kx * u + k3 * u * (u * u + v * v))

    def true_y(u, v):
        return s_ * cur_x(u, v) + c * cur_y(u, v) + ifov * (t_px[1] + ky * v + k3 * v * (u * u + v * v))

    cam_cur = camera_from_normalised_polys(full, cur_x, cur_y, name="gf4-pms current")
    cam_true = camera_from_normalised_polys(full, true_x, true_y, name="gf4-pms true")
    if (x0, y0) != (0, 0) or (W, H) != full:
        cam_cur = crop_camera(cam_cur, (x0, y0), (W, H))
        cam_true = crop_camera(cam_true, (x0, y0), (W, H))
    current = FrameModel(cam_cur, sat, R, name="gf4 current")
    true = FrameModel(cam_true, sat, R, name="gf4 true")
    errors = {
        "description": "true look angles = Rot(theta) * current + ifov * (translation + scale + cubic radial), "
                       "exterior orientation identical (METHODS §5)",
        "rotation_rad": theta, "translation_px": list(t_px), "scale_px_at_edge": [kx, ky],
        "radial_cubic_px_at_edge": k3, "modelled_radial_cubic_px_at_edge": k3_model,
        "ifov_rad": ifov, "exterior_identical": True,
    }
    info = {"satellite_lon_deg": sat_lon, "orbit": "geostationary", "full_size": list(full), "crop_offset": [x0, y0]}
    return [SimImage("", current, true, 0.0, errors, info)]


# ---------------------------------------------------------------------------------------------- push-brooms
















def _build_zy3(rng, center, size, h_mid):
    alt, incl = 505e3, 97.42
    ref_full = (24576, 24576)
    views = [("nadir", (24576, 24576), 2.1, 0.0), ("fwd", (16384, 16384), 3.5, np.tan(np.radians(22.0))),
             ("bwd", (16384, 16384), 3.5, -np.tan(np.radians(22.0)))]
    nad_cam = _linear_camera(ref_full, 2.1 / alt, 0.0, 0.0, "zy3 nadir")
    orbit = _align_orbit(center, h_mid, alt, incl, nad_cam, CAMERA_TO_BODY, ref_full[0] / 2)
    # Yaw steering: compensates the Earth's rotation between the forward and backward looks so that the three
    # views cover the same ground (as ZY-3 does).
    yaw0 = _yaw_steering(orbit, center, h_mid, views[1][1], 3.5 / alt, views[1][3])
    att_cur = Attitude(yaw=(yaw0,))
    # Platform attitude errors (shared by the three cameras): bias + drift, about 1-6 px.
    att_true = Attitude(roll=(rng.normal(0, 3) * ARCSEC, rng.normal(0, 0.05) * ARCSEC),
                        pitch=(rng.normal(0, 3) * ARCSEC, rng.normal(0, 0.05) * ARCSEC),
                        yaw=(yaw0 + rng.normal(0, 10) * ARCSEC,))
    images = []
    for name, full, gsd, ty0 in views:
        slant = alt / np.cos(np.arctan(ty0)) * (1.0 + 0.02 * abs(ty0))
        ifov = gsd / slant
        cam_cur = _linear_camera(full, ifov, 0.0, ty0, f"zy3 {name} current")
        # Camera installation / interior errors per view: offsets, scale, slight CCD bending (a few px).
        ex = (rng.normal(0, 2), rng.normal(0, 1.0), 0.0, rng.normal(0, 0.5))
        ey = (rng.normal(0, 2), rng.normal(0, 0.5), rng.normal(0, 0.5), 0.0)
        cam_true = _linear_camera(full, ifov, 0.0, ty0, f"zy3 {name} true", _poly_px(ex), _poly_px(ey))
        s = _scale_size(full, size, ref_full) if name != "nadir" else size
        cur, tru, info = _pushbroom(f"zy3 {name}", full, s, cam_cur, cam_true, orbit, att_cur, att_true,
                                    CAMERA_TO_BODY, center, h_mid, gsd,
                                    None, {"view_tan_y": ty0, "ifov_rad": ifov})
        errors = {"camera_cross_track_px_poly": list(ex), "camera_along_track_px_poly": list(ey),
                  "poly_variable": "u = (s - W/2) / (W/2) of the full array"}
        images.append(SimImage(name, cur, tru, gsd, errors, info))
    shared = {"attitude_true": att_true.to_dict(), "attitude_current": att_cur.to_dict(), "orbit": orbit.to_dict()}
    for im in images:
        im.info.update(shared)
    return images




#: HJ-1 cross-track distortion (seed 002), in px of image displacement as a function of the normalised detector
#: position u in [-1, 1]: D(u) = c0 + c1 u + c2 (u² - 1/3) + c3 (u³ - 3u/5). The bracketed terms are orthogonal
#: to 1 and u over the swath, so c2, c3 are exactly what the basic (affine) model cannot absorb and c0, c1 (an
#: interior offset and scale) exactly what it does. Ranges of the draws (sign of c2 and c3 random):
HJ1_EVEN_PX = (88.0, 100.0)      # |c2|: 2/3 |c2| = 59-67 px at both edges, -1/3 c2 at the centre
HJ1_ODD_PX = (10.0, 22.0)        # |c3|: +-0.4 |c3| = 4-9 px more at one edge than at the other
HJ1_ROLL_WOBBLE_PX, HJ1_PITCH_WOBBLE_PX = 0.3, 0.5


def _build_hj1(rng, center, size, h_mid):
    alt, incl = 650e3, 97.95
    full = (12000, 12000)
    gsd, tilt = 30.0, np.radians(15.0)
    ifov = gsd * np.cos(tilt) ** 2 / alt
    install = rot_x(tilt) @ CAMERA_TO_BODY
    cam_cur = _linear_camera(full, ifov, 0.0, 0.0, "hj1 ccd current")
    # Cross-track distortion of the wide-field CCD (seed 002, Figs. 4-5; METHODS §10): the basic model leaves a
    # residual symmetric about the swath centre (~30 px of the other sign there) growing to ~50-75 px at both edges,
    # with a smaller cubic asymmetry (the paper's trend lines are cubics; it notes that the two halves of the tilted
    # camera's field behave differently). Shape and size are chosen for two constraints:
    # * the camera stays a cubic look-angle model, tan_x = ifov (s - W/2 - D(u)), so the true image position is
    #   s_true = s_nominal + D(u_true) exactly and a cubic detector polynomial models it (the correction, a
    #   function of the predicted position, is cubic up to ~0.1 px: D' D / (W/2) terms);
    # * an RPC must still represent the distorted camera (the corrected RPC a user writes, METHODS §3 target
    #   0.01 px max / 0.002 px RMS at full size). An even (u²) term costs the RPC nothing (1e-4 px at 100 px),
    #   but the u³ term does (70 px of u³ alone: 0.010 px max, 0.0030 px RMS, tilted or not), so the symmetric
    #   part carries the size and |c3| <= 22 px keeps every draw at <= 0.0038 px max, <= 0.0014 px RMS.
    # A purely odd (radial-like) shape with the same basic-model residual would need |c3| ~ 175 px: 0.02 px max.
    c2 = rng.choice([-1.0, 1.0]) * rng.uniform(*HJ1_EVEN_PX)
    c3 = rng.choice([-1.0, 1.0]) * rng.uniform(*HJ1_ODD_PX)
    c0, c1 = rng.normal(0, 3), rng.normal(0, 3)
    cx = (c0 - c2 / 3.0, c1 - 0.6 * c3, c2, c3)        # D(u) in ascending powers of u
    # Along-track CCD bending of a few px (the paper's 1.7 px along-track RMS after the basic model).
    cy = (rng.normal(0, 3), rng.normal(0, 1), rng.normal(4, 1), 0.0)
    cam_true = _linear_camera(full, ifov, 0.0, 0.0, "hj1 ccd true", _poly_px([-c for c in cx]), _poly_px(cy))
    orbit = _align_orbit(center, h_mid, alt, incl, cam_cur, install, full[0] / 2)
    # Attitude: biases and a drift (removed by the basic model: constant and linear in the image) and a small slow
    # roll/pitch oscillation (~0.2 px RMS left after the basic model; not a function of the detector position,
    # so no detector polynomial removes it). The paper judged the attitude stable on this scene.
    t_scene = full[1] * gsd / 6.7e3
    att_true = Attitude(roll=(rng.normal(0, 15) * ifov, rng.normal(0, 0.1) * ifov),
                        pitch=(rng.normal(0, 10) * ifov,), yaw=(rng.normal(0, 2e-4),),
                        jitter=[("roll", HJ1_ROLL_WOBBLE_PX * ifov, 1.3 / t_scene, rng.uniform(0, 2 * np.pi)),
                                ("pitch", HJ1_PITCH_WOBBLE_PX * ifov, 0.9 / t_scene, rng.uniform(0, 2 * np.pi))])
    cur, tru, info = _pushbroom("hj1", full, size, cam_cur, cam_true, orbit, Attitude(), att_true, install, center,
                                h_mid, gsd, None, {"tilt_deg": 15.0, "ifov_rad": ifov})
    info.update(attitude_true=att_true.to_dict(), orbit=orbit.to_dict())
    u = np.linspace(-1.0, 1.0, 401)
    d = np.polyval(cx[::-1], u)
    beyond_line = d - np.polyval(np.polyfit(u, d, 1), u)
    errors = {"cross_track_distortion_px_poly": list(cx), "along_track_distortion_px_poly": list(cy),
              "poly_variable": "u = (s - W/2) / (W/2) of the full array",
              "definition": "true camera tan_x = ifov * (s - W/2 - D(u)): true sample = nominal sample + D(u_true)",
              "even_px": c2, "odd_px": c3,
              "cross_track_edge_px": [float(d[0]), float(d[-1])],
              "cross_track_edge_beyond_line_px": [float(beyond_line[0]), float(beyond_line[-1])],
              "cross_track_centre_beyond_line_px": float(beyond_line[200]),
              "attitude": "biases + drift + small slow roll/pitch oscillation (see attitude_true)",
              "oscillation_amplitude_px": {"roll": HJ1_ROLL_WOBBLE_PX, "pitch": HJ1_PITCH_WOBBLE_PX}}
    return [SimImage("", cur, tru, gsd, errors, info)]


# The registry (building.SENSORS): the sensors of this module; jl1 and gf7 register themselves in their modules,
# which gdal_gf4cal.simulate imports.
SENSORS.update({
    "gf4": SensorSpec("gf4", "Gaofen-4 PMS, geostationary area array 10240 x 10240, 50 m nadir", (88.0, 31.0),
                      (3500.0, 6500.0), _build_gf4, ("",)),
    "zy3": SensorSpec("zy3", "ZiYuan-3 three-line push-broom: nadir 2.1 m 24576 px, fwd/bwd +-22 deg 3.5 m "
                      "16384 px", (121.7, 31.45), (0.0, 600.0), _build_zy3, ("nadir", "fwd", "bwd")),
    "hj1": SensorSpec("hj1", "HJ-1A CCD, push-broom tilted 15 deg, 360 km swath, 30 m, 12000 px", (117.5, 36.5),
                      (0.0, 1500.0), _build_hj1, ("",)),
})


# ------------------------------------------------------------------------------------------- scene assembly
def _footprint(images, heights):
    lons, lats = [], []
    for im in images:
        for model in (im.current, im.true):
            W, H = model.size
            e = np.linspace(0, 1, 9)
            s = np.concatenate([e * W, np.full(9, W), e[::-1] * W, np.zeros(9)])
            l = np.concatenate([np.zeros(9), e * H, np.full(9, H), e[::-1] * H])
            for h in heights:
                lo, la = model.localize(s, l, np.full(s.shape, h))
                lons.append(lo)
                lats.append(la)
    lons, lats = np.concatenate(lons), np.concatenate(lats)
    if not (np.all(np.isfinite(lons)) and np.all(np.isfinite(lats))):
        raise SimulationError("the simulated image does not see the Earth everywhere; choose a centre closer to "
                              "the sub-satellite point")
    return float(lons.min()), float(lats.min()), float(lons.max()), float(lats.max())


def _gsd(model):
    W, H = model.size
    s, l = np.array([W / 2, W / 2 + 1, W / 2]), np.array([H / 2, H / 2, H / 2 + 1])
    h = float(np.mean(model.height_range))
    P = geodetic_to_ecef(*model.localize(s, l, np.full(3, h)), np.full(3, h))
    return float(np.linalg.norm(P[1] - P[0])), float(np.linalg.norm(P[2] - P[0]))


def make_scene(sensor: str, *, seed: int = 0, center=None, size=None, dem=None, dem_path: Optional[str] = None,
               progress=None, options: Optional[Dict] = None) -> SimScene:
    """Build a simulated scene in memory (METHODS §10).

    Parameters
    ----------
    sensor : one of :data:`SENSORS` ("gf4", "zy3", "hj1", "jl1", "gf7").
    seed : seeds every random draw (errors, terrain).
    center : (lon, lat) of the scene centre (default: the sensor's, e.g. Tibet (88, 31) for GF4).
    size : (W, H) crop of the detector array around its centre (of the reference image for multi-image sensors;
        the other images get the crop of the same ground extent); geometry unchanged.
    dem : None (synthetic seeded fractal terrain), a path, a number or a :class:`gdal_gf4cal.dem.DEM`.
    dem_path : where to write the synthetic DEM (default: an in-memory ``/vsimem/`` file).
    options : sensor-specific keywords of :attr:`SensorSpec.options` (jl1: ``orbit_seed``, the per-orbit attitude
        error of validation scenes, :mod:`.jl1`).
    """
    spec, center, size, options = _scene_options(sensor, center, size, options)
    rng = np.random.default_rng(seed)
    report(progress, 0.0, "building sensor models")
    user_dem = DEM.from_user_input(dem)
    relief = spec.relief_m
    if user_dem is not None:
        h_mid = float(np.clip(user_dem.height(*center), -500, 9000)) if not user_dem.is_constant \
            else user_dem.constant_height
    else:
        h_mid = 0.5 * (relief[0] + relief[1])
    images = spec.build(rng, center, size, h_mid, **options)
    report(progress, 0.3, "terrain")
    if user_dem is None:
        # The terrain covers the full detector array's footprint even for a crop: a crop sees the same ground
        # (and the same slopes) as the full scene.
        full_images = images if size is None else spec.build(np.random.default_rng(seed), center, None, h_mid,
                                                                  **options)
        the_dem, path, (h_lo, h_hi), dem_info = _synthetic_dem(full_images, relief, seed, dem_path)
    else:
        the_dem = user_dem
        path = getattr(user_dem, "path", None)
        h_lo, h_hi = _user_dem_range(user_dem, images, h_mid)
        dem_info = {"type": "user", "path": path, "height_range_m": [h_lo, h_hi]}
    margin = max(50.0, 0.1 * (h_hi - h_lo))
    hr = (h_lo - margin, h_hi + margin)
    for im in images:
        im.current.height_range = hr
        im.true.height_range = hr
        gx, gy = _gsd(im.current)
        im.info["gsd_center_m"] = [gx, gy]
        if im.gsd_m == 0.0:
            im.gsd_m = 0.5 * (gx + gy)
    scene_truth = images[0].info.pop("scene_truth", {})          # sensor-level truth (jl1: the group's)
    truth = {"sensor": sensor, "description": spec.description, "seed": seed, "center": list(center),
             "size": list(size) if size else None, "dem": dem_info, "height_range_m": list(hr),
             "pixel_convention": "gdal (centre of the first pixel at 0.5, 0.5)",
             "images": {im.name or "scene": {"size": list(im.size), "gsd_m": im.gsd_m, "errors": im.errors,
                                             "info": im.info} for im in images}, **scene_truth}
    report(progress, 1.0, "scene built")
    return SimScene(sensor, seed, center, images, the_dem, path, truth)


def _scene_options(sensor: str, center, size, options):
    """``(spec, center, size, options)`` checked: a known sensor, a valid centre, the sensor's own options."""
    if sensor not in SENSORS:
        raise SimulationError(f"unknown sensor {sensor!r}; choose one of {', '.join(SENSORS)}")
    spec = SENSORS[sensor]
    center = tuple(float(v) for v in (center if center is not None else spec.default_center))
    if len(center) != 2 or not (-180 <= center[0] <= 360 and -90 <= center[1] <= 90):
        raise SimulationError(f"centre {center} is not a valid (lon, lat) in degrees")
    if size is not None:
        size = (int(size[0]), int(size[1]))
    options = dict(options or {})
    if set(options) - set(spec.options):
        raise SimulationError(f"{sensor} has no option {sorted(set(options) - set(spec.options))}; "
                              f"it takes {list(spec.options) or 'none'}")
    return spec, center, size, options


def _synthetic_dem(full_images, relief, seed: int, dem_path: Optional[str]):
    """Seeded fractal terrain over the full images' footprint (plus 10 %), written to ``dem_path`` (default an
    in-memory file): ``(DEM, path, (h_lo, h_hi), truth record)``."""
    bounds = _footprint(full_images, relief)
    mx, my = 0.1 * (bounds[2] - bounds[0]) + 0.01, 0.1 * (bounds[3] - bounds[1]) + 0.01
    bounds = (bounds[0] - mx, bounds[1] - my, bounds[2] + mx, bounds[3] + my)
    gsd_min = min(_nominal_gsd(im) for im in full_images)
    cell = max((bounds[2] - bounds[0]) / 1500, (bounds[3] - bounds[1]) / 1500, 4 * gsd_min / 111320.0)
    heights, gt = synthetic_dem_array(bounds, cell, seed + 7919, relief)
    path = dem_path or f"/vsimem/gf4cal_sim_{uuid.uuid4().hex}.tif"
    write_dem_tif(path, heights, gt)
    h_lo, h_hi = float(heights.min()), float(heights.max())
    dem_info = {"type": "synthetic fractal", "seed": seed + 7919, "bounds": list(bounds), "cell_deg": cell,
                "height_range_m": [h_lo, h_hi]}
    return DEM.from_file(path), path, (h_lo, h_hi), dem_info


def _user_dem_range(user_dem, images, h_mid: float):
    """``(h_lo, h_hi)`` of the user's DEM over the images' footprint (refused if it does not cover it)."""
    if user_dem.is_constant:
        return user_dem.constant_height, user_dem.constant_height
    bounds = _footprint(images, (h_mid,))
    g = np.linspace(0, 1, 60)
    lo, la = np.meshgrid(bounds[0] + g * (bounds[2] - bounds[0]), bounds[1] + g * (bounds[3] - bounds[1]))
    # Sampled with nodata="nan" (the footprint may overhang the DEM), through the DEM's geoid: the range
    # must be ellipsoidal like every height the models use.
    hh = np.asarray(user_dem.sample(lo, la, nodata="nan"))
    if not np.any(np.isfinite(hh)):
        raise DEMError(f"DEM {user_dem.path} does not cover the simulated footprint {bounds}; "
                       "use a DEM covering the scene or another --center")
    return float(np.nanmin(hh)), float(np.nanmax(hh))


def _nominal_gsd(im):
    return im.gsd_m if im.gsd_m > 0 else 50.0
