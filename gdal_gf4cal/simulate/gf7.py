"""Gaofen-7 backward camera simulator for pan-to-multispectral registration (METHODS §9, §10).

The scene has two push-broom images on one platform, ``pan`` (30720 px, 0.65 m) and ``ms`` (7680 px, 2.6 m,
4 bands), looking 5° backward, the MS ``look_time_s`` (default 0.117 s, METHODS §9) after the pan. The satellite is
yaw-steered so that the pan and MS detectors of one focal-plane column see the same ground line despite the Earth
turning between the two looks: the pan sub-CCD edges then fall on the MS ones up to the misregistration itself
(< 1 MS px; no extra discontinuities; ``yaw_steering=False`` puts them ~19 MS px apart at 0.117 s).

Truth (only in the *true* models; the *current* models, from which the RPCs are fitted, are smooth):

* **sub-CCDs**: 3 per band; each piece k displaces the image by a quartic ``D_k(u_k)`` in its own normalised
  column ``u_k`` in [-1, 1] (both axes; pieces not joined: jumps at the edges). Drawn from ``camera_seed`` only,
  so scenes with the same ``camera_seed`` share the sub-CCD truth exactly (the reuse mode of METHODS §9);
* **linear** (attitude/installation) truth of the MS relative to the pan: offset + scale (sample), offset +
  rotation (line) in the MS camera, a relative roll/pitch drift in time (the ``l`` terms); drawn from ``seed``;
* **jitter**: sinusoids of the shared platform attitude ``a(t)``, seen in pan-MS differentially,
  ``a(t) - a(t - dt)`` (gain ``2 |sin(pi f dt)|``); each component's differential amplitude is 0.015-0.045 MS px;
  frequencies/amplitudes from ``camera_seed`` (the platform), phases from ``seed``; ``jitter=False`` removes it;
* **cover**: clouds and water in chosen shares of the MS footprint, a ground-space field (so pan and MS see the
  same areas), rendered flat and texture-less.

The TRUE misregistration field (:func:`true_misregistration`) is METHODS §9's nabla: at an MS pixel ``p'``, the
ground point ``P`` it shows (MS true model on the DEM), seen by the pan at ``pan.true(P)``, localised on the DEM
with the pan RPC (the current model) and projected with the MS RPC gives ``p''``; ``delta = p' - p''`` in MS
pixels per axis. :func:`write_misregistration_truth` writes it on the MS grid (what a correction.tif is checked
against); :func:`write_gf7_scene` writes a complete scene (RPCs, GCPs, rendered pan and 4-band MS, truth).

Use :func:`make_gf7_scene` for the options; ``make_scene("gf7", ...)`` / ``gf4cal simulate --sensor gf7`` build
the default camera (``camera_seed=4``, seed 004 of the project).
"""
from __future__ import annotations

from contextlib import closing, contextmanager
import contextvars
from dataclasses import asdict, dataclass, fields, replace
import os
from typing import Optional

import numpy as np
from osgeo import gdal
from scipy.interpolate import RectBivariateSpline

from .._gdal import with_gdal_exceptions
from ..atomic import atomic_output
from ..outputs import gtiff_options
from ..progress import report, scaled
from .building import SENSORS, SensorSpec, SimImage, _align_orbit, _linear_camera, _pushbroom, _scale_size
from .building import _center_time, _probe, SimulationError
from .cameras import write_json_atomic
from .geodesy import geodetic_to_ecef
from .models import CAMERA_TO_BODY, Attitude
from .render import BAND_ROWS, _bounded_map, _DemGrid, _Reference, ground_of_pixels, mercator_xy, model_bounds
from .render import texture_of_mercator, value_noise_salts
from .scene import set_crop_origin, write_placeholder_tif, write_scene
from .sensors import make_scene

#: Full detector arrays (W, H), GSD (m) of the two images.
PAN_FULL, MS_FULL = (30720, 30720), (7680, 7680)
PAN_GSD_M, MS_GSD_M = 0.65, 2.6
RATIO = 4
ALTITUDE_M, INCLINATION_DEG, BACKWARD_DEG = 505e3, 97.4, 5.0
#: MS band names and reflectance model ``gain * v + offset`` of the ground texture ``v``; water reflectance.
MS_BANDS = ("blue", "green", "red", "nir")
_BAND_GAIN = (0.55, 0.7, 0.8, 0.9)
_BAND_OFFSET = (0.2, 0.12, 0.08, 0.06)
_WATER = (0.14, 0.11, 0.07, 0.02)
_CLOUD = 0.93


@dataclass(frozen=True)
class GF7Options:
    """Options of the GF7 builder (METHODS §9).

    look_time_s : MS look time minus pan look time for the same ground (s).
    jitter : simulate the platform jitter.
    camera_seed : seeds the sub-CCD truth and the jitter spectrum (the camera/platform); scenes sharing it share
        the piecewise truth.
    yaw_steering : compensate the Earth rotation between the pan and MS looks (edges on the same MS column).
    clouds, water : shares (0..1) of the MS footprint covered by clouds / water.
    crop_center_ms_px : with ``size``: centre the crop on this column of the full MS array (default: the scene
        centre, i.e. the middle column 3840), e.g. 2560 to see the first sub-CCD edge in a small crop.
    """

    look_time_s: float = 0.117
    jitter: bool = True
    camera_seed: int = 4
    yaw_steering: bool = True
    clouds: float = 0.0
    water: float = 0.0
    crop_center_ms_px: Optional[float] = None


_OPTIONS: contextvars.ContextVar = contextvars.ContextVar("gf7_options", default=None)


@contextmanager
def gf7_options(**kw):
    """Context in which ``make_scene("gf7")`` / ``write_scene("gf7")`` use these :class:`GF7Options`."""
    opt = GF7Options(**kw)
    _check_options(opt)
    token = _OPTIONS.set(opt)
    try:
        yield opt
    finally:
        _OPTIONS.reset(token)


def _check_options(opt: GF7Options):
    if not (0.0 < abs(opt.look_time_s) <= 2.0):
        raise SimulationError(f"look_time_s {opt.look_time_s} must be non-zero and at most 2 s (GF7: 0.117 s)")
    if not (0.0 <= opt.clouds < 1.0 and 0.0 <= opt.water < 1.0 and opt.clouds + opt.water < 0.95):
        raise SimulationError("clouds and water must be shares in [0, 1) with clouds + water < 0.95")
    if opt.crop_center_ms_px is not None and not (0 <= opt.crop_center_ms_px <= MS_FULL[0]):
        raise SimulationError(f"crop_center_ms_px must be within 0..{MS_FULL[0]}")


# --------------------------------------------------------------------------------------------------- camera
class SubCCDCamera:
    """Push-broom camera of one GF7 band: a straight linear array plus per-sub-CCD quartic displacements.

    A ground point at ``tan_x`` is imaged at full-array detector ``S`` with
    ``tan_x = tx0 + ifov (S - W/2 - Dx(S))``, ``tan_y = ty0 - ifov Dy(S)``: the true image point is the nominal
    one displaced by ``D = (Dx, Dy)`` pixels, ``D(S) = lin(u) + P_k(u_k)`` with ``u = (S - W/2) / (W/2)``,
    ``lin = c0 + c1 u`` and ``P_k`` a quartic (ascending coefficients) in ``u_k = (S - mid_k) / half_k`` for ``S``
    in sub-CCD ``k`` (METHODS §9). ``offset`` is the crop's first full-array detector (image sample ``s = S -
    offset``). ``piece`` fixes one sub-CCD's polynomial everywhere (its smooth extension, for interpolation).
    """

    model_name = "gf7-subccd-quartic"

    def __init__(self, size, full_size, ifov, tx0, ty0, edges, coef_x, coef_y, lin_x=(0.0, 0.0),
                 lin_y=(0.0, 0.0), offset=0.0, piece: Optional[int] = None, name: str = "", notes: str = ""):
        self.size = (int(size[0]), int(size[1]))
        self.full_size = (int(full_size[0]), int(full_size[1]))
        self.ifov, self.tx0, self.ty0 = float(ifov), float(tx0), float(ty0)
        self.edges = np.asarray(edges, dtype=float)
        self.coef_x = np.asarray(coef_x, dtype=float).reshape(-1, 5)
        self.coef_y = np.asarray(coef_y, dtype=float).reshape(-1, 5)
        self.lin_x = tuple(float(v) for v in lin_x)
        self.lin_y = tuple(float(v) for v in lin_y)
        self.offset = float(offset)
        self.piece = piece
        self.name, self.notes = name, notes

    @property
    def n_pieces(self) -> int:
        return self.coef_x.shape[0]

    def piece_index(self, s):
        """Sub-CCD index (0-based) of image samples ``s``."""
        S = np.asarray(s, dtype=float) + self.offset
        if self.piece is not None:
            return np.full(S.shape, self.piece, dtype=np.intp)
        return np.clip(np.searchsorted(self.edges, S, side="right") - 1, 0, self.n_pieces - 1)

    def displacement(self, s):
        """``(Dx, Dy, dDx/ds, dDy/ds)`` in pixels at image samples ``s`` (vectorised)."""
        S = np.asarray(s, dtype=float) + self.offset
        k = self.piece_index(s)
        half_full = self.full_size[0] / 2.0
        u = (S - half_full) / half_full
        mid = 0.5 * (self.edges[k] + self.edges[k + 1])
        half = 0.5 * (self.edges[k + 1] - self.edges[k])
        uk = (S - mid) / half
        out = []
        for coef, lin in ((self.coef_x, self.lin_x), (self.coef_y, self.lin_y)):
            c = coef[k]                                    # (..., 5)
            val = c[..., 4]
            der = 4 * c[..., 4]
            for j in (3, 2, 1):
                val = val * uk + c[..., j]
                der = der * uk + j * c[..., j]
            val = val * uk + c[..., 0]
            out.append((lin[0] + lin[1] * u + val, lin[1] / half_full + der / half))
        return out[0][0], out[1][0], out[0][1], out[1][1]

    def tan_angles(self, s, l):
        s, l = np.broadcast_arrays(np.asarray(s, dtype=float), np.asarray(l, dtype=float))
        dx, dy, _, _ = self.displacement(s)
        S = s + self.offset
        tx = self.tx0 + self.ifov * (S - self.full_size[0] / 2.0 - dx)
        ty = self.ty0 - self.ifov * dy + 0.0 * l
        if s.shape == ():
            return float(tx), float(ty)
        return tx, ty

    def jacobian(self, s, l):
        s, l = np.broadcast_arrays(np.asarray(s, dtype=float), np.asarray(l, dtype=float))
        _, _, ddx, ddy = self.displacement(s)
        J = np.zeros(s.shape + (2, 2))
        J[..., 0, 0] = self.ifov * (1.0 - ddx)
        J[..., 1, 0] = -self.ifov * ddy
        return J

    def _copy(self, **kw):
        d = dict(size=self.size, full_size=self.full_size, ifov=self.ifov, tx0=self.tx0, ty0=self.ty0,
                 edges=self.edges, coef_x=self.coef_x, coef_y=self.coef_y, lin_x=self.lin_x, lin_y=self.lin_y,
                 offset=self.offset, piece=self.piece, name=self.name, notes=self.notes)
        d.update(kw)
        return SubCCDCamera(**d)

    def piece_camera(self, k: int) -> "SubCCDCamera":
        """The smooth camera of sub-CCD ``k`` extended over the whole array."""
        return self._copy(piece=int(k))

    def cropped(self, offset, size) -> "SubCCDCamera":
        """The camera of a crop starting at image detector ``offset = (x0, y0)`` with ``size``."""
        return self._copy(offset=self.offset + float(offset[0]), size=size)

    def piece_ranges(self) -> list:
        """Image sample range ``[a, b)`` of every sub-CCD within this image (clipped; may be empty)."""
        W = self.size[0]
        e = np.clip(self.edges - self.offset, 0, W)
        return [(float(e[k]), float(e[k + 1])) for k in range(self.n_pieces)]

    def edges_in_image(self) -> list:
        """Sub-CCD edges strictly inside this image, in image samples."""
        W = self.size[0]
        return [float(e - self.offset) for e in self.edges[1:-1] if 0 < e - self.offset < W]

    def to_dict(self) -> dict:
        return {"model": self.model_name, "size": list(self.size), "full_size": list(self.full_size),
                "ifov_rad": self.ifov, "tx0": self.tx0, "ty0": self.ty0, "edges_full_px": self.edges.tolist(),
                "coef_x_px": self.coef_x.tolist(), "coef_y_px": self.coef_y.tolist(), "lin_x_px": list(self.lin_x),
                "lin_y_px": list(self.lin_y), "offset_px": self.offset, "piece": self.piece,
                "definition": "tan_x = tx0 + ifov (S - W/2 - Dx(S)), tan_y = ty0 - ifov Dy(S), S = s + offset; "
                              "D = lin0 + lin1 u + sum_j coef[k][j] u_k^j, u = (S - W/2)/(W/2), "
                              "u_k = (S - mid_k)/half_k in sub-CCD k",
                "pixel_convention": "gdal", "name": self.name, "notes": self.notes}

    @classmethod
    def from_dict(cls, d: dict) -> "SubCCDCamera":
        return cls(d["size"], d["full_size"], d["ifov_rad"], d["tx0"], d["ty0"], d["edges_full_px"],
                   d["coef_x_px"], d["coef_y_px"], d["lin_x_px"], d["lin_y_px"], d["offset_px"], d.get("piece"),
                   d.get("name", ""), d.get("notes", ""))

    def to_json(self, path, overwrite: bool = False) -> str:
        return write_json_atomic(path, self.to_dict(), overwrite=overwrite)


# -------------------------------------------------------------------------------------------------- builder
def _sub_ccd_truth(camera_seed: int, n: int = 3):
    """Per-sub-CCD quartic displacements (ascending coefficients, px of the band) of pan and MS (camera_seed)."""
    rng = np.random.default_rng(camera_seed + 70001)
    # MS (MS px): placement offsets ~0.1-0.2 px, a tilt and a bending of a few hundredths to a tenth.
    sd_x = np.array([0.12, 0.06, 0.05, 0.03, 0.03])
    sd_y = np.array([0.2, 0.1, 0.05, 0.03, 0.03])
    ms_x, ms_y = rng.normal(0, 1, (n, 5)) * sd_x, rng.normal(0, 1, (n, 5)) * sd_y
    # Pan (pan px): the reference band; smaller in MS px (1/4).
    pan_x, pan_y = rng.normal(0, 1, (n, 5)) * 0.8 * sd_x, rng.normal(0, 1, (n, 5)) * 0.8 * sd_y
    return {"pan": (pan_x, pan_y), "ms": (ms_x, ms_y)}


def _jitter_spectrum(camera_seed: int, look_time_s: float, ms_ifov: float, rng_phase):
    """Attitude jitter ``[(axis, amp_rad, f_hz, phase)]``: 3 roll + 3 pitch sines whose differential amplitude
    ``2 |sin(pi f dt)| amp / ifov`` is 0.015-0.045 MS px (frequency from the platform, phase from the scene)."""
    rng = np.random.default_rng(camera_seed + 90001)
    f_max = min(6.0, 0.4 / abs(look_time_s))          # keep the gain away from its zero at f = 1/dt
    comps = []
    for axis in ("roll", "roll", "roll", "pitch", "pitch", "pitch"):
        f = float(rng.uniform(0.5, f_max))
        diff_px = float(rng.uniform(0.015, 0.045))
        gain = 2.0 * abs(np.sin(np.pi * f * look_time_s))
        comps.append((axis, diff_px * ms_ifov / gain, f, diff_px))
    phases = rng_phase.uniform(0, 2 * np.pi, len(comps))
    return [(a, amp, f, float(ph)) for (a, amp, f, _), ph in zip(comps, phases)], [c[3] for c in comps]


def _cross_track_gap_m(orbit, yaw, cams, center, h):
    """Cross-track distance (m) between the ground points of the pan and MS reference detectors at the times
    they see the along-track position of ``center``."""
    att = Attitude(yaw=(yaw,))
    g = []
    for cam, s_ref in cams:
        t, _ = _center_time(orbit, CAMERA_TO_BODY, cam, center, h, s_ref, att)
        probe = _probe(orbit, att, CAMERA_TO_BODY, cam)
        g.append((geodetic_to_ecef(*probe.localize(s_ref, t, h), h), geodetic_to_ecef(*probe.localize(
            s_ref + 1.0, t, h), h), t))
    across = g[0][1] - g[0][0]
    across /= np.linalg.norm(across)
    return float(np.dot(g[1][0] - g[0][0], across)), g[1][2] - g[0][2]


def build_gf7(rng, center, size, h_mid, **options):
    """GF7 builder for :func:`gdal_gf4cal.simulate.make_scene` (METHODS §9, §10); options: the keywords of
    :class:`GF7Options` (``make_scene(..., options={...})``) over those of :func:`gf7_options` (default
    :class:`GF7Options`)."""
    opt = _OPTIONS.get() or GF7Options()
    opt = replace(opt, **options) if options else opt
    _check_options(opt)
    alt = ALTITUDE_M + rng.uniform(-1500.0, 1500.0)           # orbit differs a little between scenes
    incl = INCLINATION_DEG
    back = -np.tan(np.radians(BACKWARD_DEG))
    pan_ifov = PAN_GSD_M * np.cos(np.arctan(back)) ** 2 / alt
    ref = _linear_camera(PAN_FULL, pan_ifov, 0.0, back, "ref")
    orbit = _align_orbit(center, h_mid, alt, incl, ref, CAMERA_TO_BODY, PAN_FULL[0] / 2)
    # One focal plane and lens: an MS detector is exactly RATIO pan detectors wide (in tan_x), so the nominal pan
    # and MS sub-CCD edges are the same look angles.
    ms_ifov = RATIO * pan_ifov
    dty, yaw, gap_m, dt = _ms_view(opt, orbit, ref, back, ms_ifov, alt, center, h_mid)
    att_cur = Attitude(yaw=(yaw,))
    # Shared exterior errors (scene seed): attitude biases ~6 MS px, a slow drift; cancel mostly in pan-MS.
    t_half = MS_FULL[1] / 2 * MS_GSD_M / 6.9e3
    shared = dict(roll=(rng.normal(0, 6) * ms_ifov, rng.normal(0, 0.05) * ms_ifov),
                  pitch=(rng.normal(0, 6) * ms_ifov,), yaw=(yaw + rng.normal(0, 2e-5),))
    jit, jit_px = _jitter_spectrum(opt.camera_seed, opt.look_time_s, ms_ifov, rng)
    jit = jit if opt.jitter else []
    lin = _ms_linear_truth(rng)
    att_pan = Attitude(roll=shared["roll"], pitch=shared["pitch"], yaw=shared["yaw"], jitter=list(jit))
    rate_r = lin["sample_drift_px_at_end"] * ms_ifov / t_half
    rate_p = lin["line_drift_px_at_end"] * ms_ifov / t_half
    att_ms = Attitude(roll=(shared["roll"][0], shared["roll"][1] + rate_r), pitch=(shared["pitch"][0], rate_p),
                      yaw=shared["yaw"], jitter=list(jit))
    truth = _sub_ccd_truth(opt.camera_seed)
    crop_center = center
    if size is not None and opt.crop_center_ms_px is not None:
        # The ground point that the full MS array's column crop_center_ms_px sees at the scene centre's time.
        ms_cam = _linear_camera(MS_FULL, ms_ifov, 0.0, back + dty, "ms probe")
        probe, _, _ = _pushbroom("probe", MS_FULL, None, ms_cam, ms_cam, orbit, att_cur, att_cur, CAMERA_TO_BODY,
                                 center, h_mid, MS_GSD_M, None, {})
        crop_center = probe.localize(opt.crop_center_ms_px, MS_FULL[1] / 2.0, h_mid)
    images = []
    for name, full, gsd, ty0, ifov, att_true in (("pan", PAN_FULL, PAN_GSD_M, back, pan_ifov, att_pan),
                                                  ("ms", MS_FULL, MS_GSD_M, back + dty, ms_ifov, att_ms)):
        im = _gf7_image(name, full, gsd, ty0, ifov, att_true, att_cur, orbit, truth[name],
                        lin if name == "ms" else None, size, crop_center, h_mid, opt)
        if name == "ms":
            im.errors.update(linear_truth=lin, jitter_differential_px=jit_px if opt.jitter else [],
                             look_time_s=float(dt), look_time_requested_s=opt.look_time_s,
                             yaw_steering_rad=float(yaw) if opt.yaw_steering else 0.0,
                             pan_ms_cross_track_gap_m=gap_m, options=asdict(opt), bands=list(MS_BANDS))
        images.append(im)
    ms = images[1]
    ms.errors["cover"] = _cover_params(opt, ms.true, h_mid, seed_salt=int(rng.integers(0, 2 ** 31)))
    return images


def _ms_view(opt, orbit, ref, back: float, ms_ifov: float, alt: float, center, h_mid: float):
    """The MS view angle for the look-time difference and the yaw steering, alternated (each depends on the
    other): ``(dty, yaw, pan-MS cross-track gap m, look time s)``."""
    dty = -opt.look_time_s * 6.9e3 / alt
    yaw = 0.0
    for _ in range(4):
        ms_probe = _linear_camera(MS_FULL, ms_ifov, 0.0, back + dty, "ms probe")
        cams = [(ref, PAN_FULL[0] / 2), (ms_probe, MS_FULL[0] / 2)]
        if opt.yaw_steering:
            y0, d = yaw, 1e-3
            for _ in range(4):
                f0, _ = _cross_track_gap_m(orbit, y0, cams, center, h_mid)
                f1, _ = _cross_track_gap_m(orbit, y0 + d, cams, center, h_mid)
                y0 -= f0 * d / (f1 - f0)
                d = max(1e-6, min(1e-3, abs(f0 * d / (f1 - f0))))
            yaw = y0
        gap_m, dt = _cross_track_gap_m(orbit, yaw, cams, center, h_mid)
        dty *= opt.look_time_s / dt
    ms_probe = _linear_camera(MS_FULL, ms_ifov, 0.0, back + dty, "ms probe")
    gap_m, dt = _cross_track_gap_m(orbit, yaw, [(ref, PAN_FULL[0] / 2), (ms_probe, MS_FULL[0] / 2)], center,
                                   h_mid)
    return dty, yaw, gap_m, dt


def _ms_linear_truth(rng) -> dict:
    """Linear truth of the MS relative to the pan (scene seed): camera offset/scale, offset/rotation (px at the
    edge of the array), relative roll/pitch drift (px at the end of the full scene).

    The sample offset is negative: the geometry itself leaves ~ -0.2 px (shared attitude biases seen 0.117 s
    apart), so "before" is ~0.6 px in sample whatever the seed (METHODS §9)."""
    sgn = rng.choice([-1.0, 1.0], 6)
    return {"sample_offset_px": -rng.uniform(0.35, 0.5), "sample_scale_px_at_edge": sgn[1] * rng.uniform(
        0.1, 0.2), "sample_drift_px_at_end": sgn[2] * rng.uniform(0.05, 0.1),
        "line_offset_px": sgn[3] * rng.uniform(0.15, 0.25), "line_rotation_px_at_edge": sgn[4] * rng.uniform(
        0.08, 0.15), "line_drift_px_at_end": sgn[5] * rng.uniform(0.05, 0.1)}


def _gf7_image(name: str, full, gsd: float, ty0: float, ifov: float, att_true, att_cur, orbit, sub_ccd, lin,
               size, crop_center, h_mid: float, opt):
    """One GF7 band image: a linear current camera, the true sub-CCD camera (quartics per sub-CCD, plus the MS
    linear truth ``lin``), the crop and its error record."""
    cam_cur = _linear_camera(full, ifov, 0.0, ty0, f"gf7 {name} current")
    edges = np.linspace(0, full[0], 4)
    cx, cy = sub_ccd
    lx = (lin["sample_offset_px"], lin["sample_scale_px_at_edge"]) if lin is not None else (0.0, 0.0)
    ly = (lin["line_offset_px"], lin["line_rotation_px_at_edge"]) if lin is not None else (0.0, 0.0)
    cam_true = SubCCDCamera(full, full, ifov, 0.0, ty0, edges, cx, cy, lx, ly, name=f"gf7 {name} true")
    s = _scale_size(full, size, PAN_FULL) if name != "pan" else size
    cur, tru, info = _pushbroom(f"gf7 {name}", full, s, cam_cur, cam_cur, orbit, att_cur, att_true,
                                CAMERA_TO_BODY, crop_center, h_mid, gsd, None,
                                {"view_tan_y": ty0, "ifov_rad": ifov})
    tru = tru.with_camera(cam_true.cropped(info["crop_offset"], cur.size))
    info.update(attitude_true=att_true.to_dict(), attitude_current=att_cur.to_dict(), orbit=orbit.to_dict())
    errors = {"sub_ccd_edges_full_px": edges.tolist(), "sub_ccd_quartic_x_px": cx.tolist(),
              "sub_ccd_quartic_y_px": cy.tolist(),
              "poly_variable": "u_k = (S - mid_k) / half_k of the full band's sub-CCD k",
              "camera_seed": opt.camera_seed, "jitter": [list(j) for j in att_true.jitter]}
    return SimImage(name, cur, tru, gsd, errors, info)


# ---------------------------------------------------------------------------------------------------- cover
_merc = mercator_xy


def _cover_fields(lon, lat, p, xy=None):
    x, y = _merc(lon, lat) if xy is None else xy
    wl = p["wavelength_m"]
    c0, w0 = value_noise_salts(x, y, wl, (p["salt"], p["salt"] + 2))
    c1, w1 = value_noise_salts(x, y, wl / 3.3, (p["salt"] + 1, p["salt"] + 3))
    return 0.7 * c0 + 0.3 * c1, 0.7 * w0 + 0.3 * w1


def _cover_params(opt, ms_true, h, seed_salt):
    W, H = ms_true.size
    s, l = np.meshgrid((np.arange(64) + 0.5) * W / 64, (np.arange(64) + 0.5) * H / 64)
    lon, lat = ms_true.localize(s.ravel(), l.ravel(), np.full(s.size, h))
    p = {"cloud_share": opt.clouds, "water_share": opt.water, "salt": seed_salt % 100000 + 12000,
         "wavelength_m": max(W, H) * MS_GSD_M / 4.0, "edge": 0.01,
         "classes": {"0": "clear", "1": "cloud", "2": "water"},
         "definition": "ground-space fields (value noise in spherical-Mercator metres); cloud where the cloud "
                       "field > cloud_threshold, else water where the water field > water_threshold"}
    cloud, water = _cover_fields(lon, lat, p)
    p["cloud_threshold"] = float(np.quantile(cloud, 1.0 - opt.clouds)) if opt.clouds > 0 else 2.0
    clear = cloud <= p["cloud_threshold"]
    q = 1.0 - opt.water / max(1e-9, clear.mean())
    p["water_threshold"] = float(np.quantile(water[clear], np.clip(q, 0, 1))) if opt.water > 0 else 2.0
    return p


def cover_weights(scene, lon, lat, xy=None):
    """Soft cloud and water weights in [0, 1] at ground points (METHODS §9's cloudy cells); ``xy``: their
    :func:`~.render.mercator_xy` if already computed."""
    p = scene.image("ms").errors["cover"]
    cloud, water = _cover_fields(lon, lat, p, xy)
    wc = np.clip((cloud - p["cloud_threshold"]) / p["edge"] + 0.5, 0.0, 1.0)
    ww = np.clip((water - p["water_threshold"]) / p["edge"] + 0.5, 0.0, 1.0) * (1.0 - wc)
    return wc, ww


def _no_cover(scene) -> bool:
    """True if no point can get a cloud or water weight: both fields are < 1 and both thresholds (2.0 without
    clouds / water) are more than half an edge above 1, so :func:`cover_weights` would be exactly 0 everywhere."""
    p = scene.image("ms").errors["cover"]
    return min(p["cloud_threshold"], p["water_threshold"]) - 0.5 * p["edge"] > 1.01


def cover_class(scene, lon, lat):
    """0 clear, 1 cloud, 2 water at ground points (uint8; any cloud or water weight counts, so clear pixels are
    untouched by either)."""
    wc, ww = cover_weights(scene, lon, lat)
    return np.where(wc > 0.0, 1, np.where(ww > 0.0, 2, 0)).astype(np.uint8)


# ------------------------------------------------------------------------------------------- scene builders
def make_gf7_scene(*, seed: int = 0, camera_seed: int = 4, look_time_s: float = 0.117, jitter: bool = True,
                   yaw_steering: bool = True, clouds: float = 0.0, water: float = 0.0, center=None, size=None,
                   crop_center_ms_px: Optional[float] = None, dem=None, dem_path: Optional[str] = None,
                   progress=None):
    """A GF7 pan + MS scene in memory (METHODS §9, §10): :func:`gdal_gf4cal.simulate.make_scene` with the
    :class:`GF7Options`. ``seed`` seeds the exterior (orbit, attitude, linear truth, jitter phases, terrain);
    ``camera_seed`` the sub-CCD truth and jitter spectrum (scenes sharing it share the piecewise truth)."""
    with gf7_options(look_time_s=look_time_s, jitter=jitter, camera_seed=camera_seed, yaw_steering=yaw_steering,
                     clouds=clouds, water=water, crop_center_ms_px=crop_center_ms_px):
        return make_scene("gf7", seed=seed, center=center, size=size, dem=dem, dem_path=dem_path,
                          progress=progress)


# ---------------------------------------------------------------------------------------------- truth field
def _models(scene, piece=None, pan_model=None, ms_model=None):
    pan, ms = scene.image("pan"), scene.image("ms")
    ms_true, pan_true = ms.true, pan.true
    if piece is not None:
        ms_true = ms_true.with_camera(ms_true.camera.piece_camera(piece))
        pan_true = pan_true.with_camera(pan_true.camera.piece_camera(piece))
    return pan_true, ms_true, pan_model or pan.current, ms_model or ms.current


def true_misregistration(scene, sample, line, *, pan_model=None, ms_model=None, piece: Optional[int] = None,
                         at: str = "ms"):
    """The TRUE pan-MS misregistration at MS image points (METHODS §9's nabla), MS pixels per axis.

    ``delta = p' - p''``: ``p' = (sample, line)`` is where the MS image shows the ground point ``P`` (the MS
    true model on the scene DEM); ``p''`` is where the pan, the DEM and the MS RPC predict it: the pan point
    ``pan.true(P)`` localised on the DEM with ``pan_model`` (default the pan current model, the exact analogue of
    the pan RPC; pass an :class:`~gdal_gf4cal.RPCModel` to use the fitted RPC) and projected with ``ms_model``
    (default the MS current model). GDAL pixel convention. ``piece`` evaluates sub-CCD ``piece``'s smooth
    extension (pan and MS) everywhere (used to interpolate without crossing the jumps).
    ``at="predicted"``: ``(sample, line)`` are predicted points ``p''`` instead (what resampling the MS onto the
    pan needs): ``delta`` such that the MS shows the ground at ``p'' + delta`` (fixed point ``p' = p'' +
    delta(p')``, 5 iterations; the field's gradient is ~1e-4 px/px away from the edges).

    Returns ``(delta_sample, delta_line)`` arrays of the input shape (NaN off the DEM).
    """
    s, l = np.broadcast_arrays(np.asarray(sample, dtype=float), np.asarray(line, dtype=float))
    if at == "predicted":
        ps, pl = s, l
        for _ in range(5):
            ds, dl = true_misregistration(scene, ps, pl, pan_model=pan_model, ms_model=ms_model, piece=piece)
            ps, pl = s + ds, l + dl
        return ds, dl
    if at != "ms":
        raise ValueError(f"at={at!r}: use 'ms' (MS image points) or 'predicted' (predicted points)")
    pan_true, ms_true, pan_cur, ms_cur = _models(scene, piece, pan_model, ms_model)
    lon, lat, h = ms_true.localize_dem(s, l, scene.dem)
    ps, pl = pan_true.project(lon, lat, h)
    lon2, lat2, h2 = pan_cur.localize_dem(ps, pl, scene.dem)
    s2, l2 = ms_cur.project(lon2, lat2, h2)
    return s - np.asarray(s2), l - np.asarray(l2)


def misregistration_nodes(scene, step: float = 16.0, window=None):
    """Per MS sub-CCD: node columns and rows (MS pixel centres, a regular grid incl. the piece's first and last
    pixel centres) and ``delta`` on them from :func:`true_misregistration` (that piece's smooth extension).
    ``window = (x0, y0, w, h)``: only the MS pixels of that window (image pixels; default the whole image).

    Returns a list of ``(k, a, b, cols, rows, d_sample, d_line)``, ``[a, b)`` the piece's image columns (within
    the window), everything in image pixels."""
    ms = scene.image("ms")
    x0, y0, W, H = window if window is not None else (0, 0) + tuple(ms.size)
    rows = y0 + np.linspace(0.5, H - 0.5, max(4, int(np.ceil((H - 1) / step)) + 1))
    out = []
    for k, (a, b) in enumerate(ms.true.camera.piece_ranges()):
        a, b = max(int(round(a)), x0), min(int(round(b)), x0 + W)
        if b <= a:
            continue
        cols = np.linspace(a + 0.5, b - 0.5, max(4, int(np.ceil((b - a - 1) / step)) + 1))
        S, L = np.meshgrid(cols, rows)
        ds, dl = true_misregistration(scene, S, L, piece=k)
        out.append((k, a, b, cols, rows, ds, dl))
    return out


def _spline(cols, rows, values):
    v = np.where(np.isfinite(values), values, np.nanmean(values))
    kx, ky = min(3, rows.size - 1), min(3, cols.size - 1)
    return RectBivariateSpline(rows, cols, v, kx=kx, ky=ky)


@with_gdal_exceptions
def write_misregistration_truth(scene, path, *, step: float = 8.0, tile: int = 512, window=None) -> str:
    """Write the TRUE misregistration field on the MS image grid: 2-band float32 GeoTIFF (band 1 delta sample,
    band 2 delta line, MS pixels, at every MS pixel centre, GDAL convention) -- what a ``correction.tif`` is
    checked against (METHODS §9). Per sub-CCD, bicubic from :func:`misregistration_nodes` (exact at the nodes;
    between them the terrain's fine structure in the line axis -- the pan and MS rays are 0.094° apart along
    track -- is interpolated: max ~0.004 px, RMS ~0.001 px at ``step`` 8, 0.001 / 0.0003 px at 4; the jumps
    stay sharp at the MS sub-CCD edges). The pan's own jump, which lands within ~1 MS px of the MS edge (the
    misregistration there), is put at the MS edge: within that pixel the grid may differ from
    :func:`true_misregistration` by the pan jump (~0.1 px). Written tile by tile, atomically.
    ``window = (x0, y0, w, h)`` (MS image pixels): the field of that crop only, on its grid, with the crop's
    origin as a pixel-unit geotransform (:func:`.scene.set_crop_origin`)."""
    ms = scene.image("ms")
    wx, wy, W, H = window if window is not None else (0, 0) + tuple(ms.size)
    nodes = misregistration_nodes(scene, step, window)
    splines = [(a - wx, b - wx, _spline(c, r, ds), _spline(c, r, dl)) for _, a, b, c, r, ds, dl in nodes]
    path = os.fspath(path)
    with atomic_output(path) as tmp:
        ds_ = gdal.GetDriverByName("GTiff").Create(tmp, W, H, 2, gdal.GDT_Float32,
                                               gtiff_options(tile=tile, predictor=3))
        for band, desc in ((1, "delta_sample_ms_px"), (2, "delta_line_ms_px")):
            ds_.GetRasterBand(band).SetDescription(desc)
        ds_.SetMetadataItem("GF4CAL_TRUTH", "true pan-MS misregistration delta = MS image point - pan/DEM/MS-RPC "
                            "prediction (METHODS §9), MS pixels, at MS pixel centres, GDAL convention")
        set_crop_origin(ds_, window)
        for y0 in range(0, H, tile):
            h = min(tile, H - y0)
            yy = wy + y0 + np.arange(h) + 0.5
            for x0 in range(0, W, tile):
                w = min(tile, W - x0)
                out_s = np.full((h, w), np.nan, dtype=np.float32)
                out_l = np.full((h, w), np.nan, dtype=np.float32)
                for a, b, sp_s, sp_l in splines:
                    lo, hi = max(a, x0), min(b, x0 + w)
                    if hi <= lo:
                        continue
                    xx = wx + np.arange(lo, hi) + 0.5
                    out_s[:, lo - x0:hi - x0] = sp_s(yy, xx)
                    out_l[:, lo - x0:hi - x0] = sp_l(yy, xx)
                ds_.GetRasterBand(1).WriteArray(out_s, x0, y0)
                ds_.GetRasterBand(2).WriteArray(out_l, x0, y0)
        ds_ = None
    return path


def misregistration_stats(scene, n: int = 64, window=None) -> dict:
    """RMS about zero per axis, max and P(<= 0.25 px) of the true field on an ``n x n`` MS grid (METHODS §9's
    "before" numbers), and the MS sub-CCD edges inside the image; ``window = (x0, y0, w, h)``: of that crop
    (MS image pixels), edges in the crop's pixels."""
    x0, y0, W, H = window if window is not None else (0, 0) + tuple(scene.image("ms").size)
    s, l = np.meshgrid(x0 + (np.arange(n) + 0.5) * W / n, y0 + (np.arange(n) + 0.5) * H / n)
    ds, dl = true_misregistration(scene, s, l)
    ok = np.isfinite(ds) & np.isfinite(dl)
    ds, dl = ds[ok], dl[ok]
    return {"rms_sample_px": float(np.sqrt(np.mean(ds ** 2))), "rms_line_px": float(np.sqrt(np.mean(dl ** 2))),
            "max_px": float(np.max(np.hypot(ds, dl))), "p_le_0.25": float(np.mean(np.hypot(ds, dl) <= 0.25)),
            "ms_sub_ccd_edges_px": [e - x0 for e in scene.image("ms").true.camera.edges_in_image()
                                    if 0 < e - x0 < W], "grid": n}


# ------------------------------------------------------------------------------------------------ rendering
def ground_reflectance(scene, lon, lat, *, edge_m: float, reference=None):
    """Reflectance in [0, 1] of the 4 MS bands at ground points, shape ``(4,) + lon.shape``.

    Texture ``v``: the built-in :func:`~gdal_gf4cal.simulate.render.texture_value` (``seed`` = the scene seed,
    finest wavelength 3 MS pixels, edges box-averaged over ``edge_m``) or ``reference`` (a ``render._Reference``,
    its values / 255); band ``k`` = ``gain_k v + offset_k`` + a slow per-band variation; clouds (flat bright) and
    water (flat dark, NIR darkest) replace it by their cover weights (:func:`cover_weights`). The pan is the mean
    of the four bands, so pan and MS show the same ground."""
    lon, lat = np.asarray(lon, dtype=float), np.asarray(lat, dtype=float)
    seed = int(scene.seed)
    x, y = _merc(lon, lat)
    if reference is None:
        v = texture_of_mercator(x, y, seed, 3.0 * MS_GSD_M, edge_m=edge_m)
    else:
        v = np.clip(reference.sample(lon, lat) / 255.0, 0.0, 1.0)
    # Without clouds and water every cover weight is exactly 0 (b * 1 + 0 + 0 = b): skip the cover fields.
    cover = None if _no_cover(scene) else cover_weights(scene, lon, lat, (x, y))
    out = np.empty((len(MS_BANDS),) + lon.shape)
    slows = value_noise_salts(x, y, 80.0 * MS_GSD_M, [seed * 1000 + 700 + k for k in range(len(MS_BANDS))])
    for k in range(len(MS_BANDS)):
        b = np.clip(_BAND_GAIN[k] * v + _BAND_OFFSET[k] + 0.1 * (slows[k] - 0.5), 0.0, 1.0)
        if cover is None:
            out[k] = b
        else:
            wc, ww = cover
            out[k] = b * (1.0 - wc - ww) + _CLOUD * wc + _WATER[k] * ww
    return out


def band_color(name: str) -> int:
    """GDAL colour interpretation of an MS band name (blue, green, red -> Blue, Green, Red; NIR -> Undefined,
    never Alpha)."""
    return {"blue": gdal.GCI_BlueBand, "green": gdal.GCI_GreenBand, "red": gdal.GCI_RedBand}.get(
        name, gdal.GCI_Undefined)


def _to_byte(r):
    return np.clip(np.round(20.0 + 220.0 * r), 1, 255).astype(np.uint8)


@with_gdal_exceptions
def render_gf7_image(scene, name: str, path, *, reference=None, mask_path=None, tile: int = 512,
                     workers: int = 2, window=None, progress=None) -> str:
    """Render the ``pan`` (1 band) or ``ms`` (4 bands: blue, green, red, NIR) image of a GF7 scene through its
    TRUE model into a tiled Byte GeoTIFF (METHODS §9, §10), from the built-in texture or ``reference`` (any GDAL
    raster, any CRS). Each sub-CCD is localised with its own smooth camera (the jumps stay sharp, no smoothing
    across an edge), so matching pan to MS through the RPCs sees exactly :func:`true_misregistration`.
    ``mask_path`` receives the cover class of every pixel (0 clear, 1 cloud, 2 water). ``window = (x0, y0, w,
    h)`` (image pixels): render only that crop (nothing outside it is computed), written with its origin as a
    pixel-unit geotransform (:func:`.scene.set_crop_origin`). Tiled, ``workers`` threads, memory of a few tiles;
    atomic."""
    im = scene.image(name)
    model = im.true
    wx, wy, W, H = window if window is not None else (0, 0) + tuple(model.size)
    demgrid = _DemGrid(scene.dem, model_bounds(model))
    ref = _Reference(reference, im.gsd_m) if reference is not None else None
    pieces = [(int(round(a)), int(round(b)), model.with_camera(model.camera.piece_camera(k)))
              for k, (a, b) in enumerate(model.camera.piece_ranges()) if b > a]
    nb = len(MS_BANDS) if name == "ms" else 1

    def do_tile(x0, y0, w, h):
        lon, lat = np.empty((h, w)), np.empty((h, w))
        for a, b, m in pieces:
            lo, hi = max(a - wx, x0), min(b - wx, x0 + w)
            if hi > lo:
                lo_, la_, _ = ground_of_pixels(m, demgrid, wx + lo, wy + y0, hi - lo, h)
                lon[:, lo - x0:hi - x0], lat[:, lo - x0:hi - x0] = lo_, la_
        arr = np.empty((nb, h, w), np.uint8)
        mask = np.empty((h, w), np.uint8) if mask_path else None
        # Per pixel: in row bands that stay in the CPU cache; a reference is read (and averaged) per window,
        # so from one window per tile.
        band_rows = h if ref is not None else BAND_ROWS
        for r0 in range(0, h, band_rows):
            rows = slice(r0, r0 + band_rows)
            r = ground_reflectance(scene, lon[rows], lat[rows], edge_m=im.gsd_m, reference=ref)
            arr[:, rows] = _to_byte(r) if nb > 1 else _to_byte(r.mean(axis=0))[None]
            if mask is not None:
                mask[rows] = cover_class(scene, lon[rows], lat[rows])
        return x0, y0, arr, mask

    opts = gtiff_options(tile=tile, extra=["PHOTOMETRIC=MINISBLACK", "ALPHA=NO", "INTERLEAVE=BAND"] if nb > 1 else [])
    tiles = [(x, y, min(tile, W - x), min(tile, H - y)) for y in range(0, H, tile) for x in range(0, W, tile)]
    path = os.fspath(path)
    with atomic_output(path) as tmp, _maybe_atomic(mask_path) as tmpm:
        ds = gdal.GetDriverByName("GTiff").Create(tmp, W, H, nb, gdal.GDT_Byte, opts)
        for k in range(nb):
            ds.GetRasterBand(k + 1).SetNoDataValue(0)
            ds.GetRasterBand(k + 1).SetDescription(MS_BANDS[k] if nb > 1 else "pan")
            if nb > 1:
                ds.GetRasterBand(k + 1).SetColorInterpretation(band_color(MS_BANDS[k]))
        mds = None
        if tmpm is not None:
            mds = gdal.GetDriverByName("GTiff").Create(tmpm, W, H, 1, gdal.GDT_Byte, opts[:5])
            mds.SetMetadataItem("GF4CAL_COVER", "0 clear, 1 cloud, 2 water")
            set_crop_origin(mds, window)
        set_crop_origin(ds, window)
        with closing(_bounded_map(do_tile, tiles, workers)) as results:
            for done, (x0, y0, arr, mask) in enumerate(results, start=1):
                for k in range(nb):
                    ds.GetRasterBand(k + 1).WriteArray(arr[k], x0, y0)
                ds.FlushCache()       # the tile to disk, out of GDAL's block cache (memory at a few tiles)
                if mds is not None:
                    mds.GetRasterBand(1).WriteArray(mask, x0, y0)
                    mds.FlushCache()
                report(progress, done / len(tiles), f"{name}: rendering tile {done}/{len(tiles)}")
        ds.SetMetadataItem("GF4CAL_RENDERED", f"gf7 {name} true model; " + (
            f"reference {reference}" if reference else f"built-in texture seed {scene.seed}"))
        ds = None
        mds = None
    return path


@contextmanager
def _maybe_atomic(path):
    if path is None:
        yield None
        return
    with atomic_output(os.fspath(path)) as tmp:
        yield tmp


# --------------------------------------------------------------------------------------------------- crops
@dataclass(frozen=True)
class GF7Crop:
    """A crop of the full GF7 product that keeps its place: pan pixels ``[x0, x0 + width) x [y0, y0 + height)``
    of the full pan array, and the same ground in the MS, ``window("ms") = (x0, y0, width, height) / 4`` (one
    focal plane: MS detector = 4 pan detectors, MS line = 4 pan lines). All four multiples of :data:`RATIO`."""

    x0: int
    y0: int
    width: int
    height: int

    def window(self, name: str) -> tuple:
        """``(x0, y0, w, h)`` of the crop in image ``name``'s (``pan`` or ``ms``) product pixels."""
        r = 1 if name == "pan" else RATIO
        return (self.x0 // r, self.y0 // r, self.width // r, self.height // r)

    def windows(self) -> dict:
        return {"pan": self.window("pan"), "ms": self.window("ms")}


def gf7_crop(crop) -> GF7Crop:
    """A :class:`GF7Crop` from ``(x0, y0, width, height)`` in pan pixels of the full product (``--crop``), checked:
    multiples of 4, at least 64 x 64, inside the 30720 x 30720 pan array."""
    if isinstance(crop, GF7Crop):
        return crop
    vals = [int(v) for v in crop]
    if len(vals) != 4:
        raise SimulationError(f"--crop needs X0 Y0 W H (4 numbers, pan pixels of the full product), got {crop}")
    x0, y0, w, h = vals
    if any(v % RATIO for v in vals):
        raise SimulationError(f"--crop {x0} {y0} {w} {h}: give multiples of {RATIO} (one MS pixel = {RATIO} pan "
                              "pixels), so that the MS crop covers the same ground")
    if w < 16 * RATIO or h < 16 * RATIO:
        raise SimulationError(f"--crop {x0} {y0} {w} {h} is too small; use at least {16 * RATIO} x {16 * RATIO} pan "
                              "pixels (16 x 16 MS pixels)")
    if x0 < 0 or y0 < 0 or x0 + w > PAN_FULL[0] or y0 + h > PAN_FULL[1]:
        raise SimulationError(f"--crop {x0} {y0} {w} {h} leaves the {PAN_FULL[0]} x {PAN_FULL[1]} pan product; "
                              "choose a crop inside it")
    return GF7Crop(x0, y0, w, h)


def _full_scene(scene):
    if tuple(scene.image("ms").size) != MS_FULL:
        raise SimulationError("crop truth needs the full-product scene (make_gf7_scene without size)")
    return scene


def crop_misregistration(scene, crop, sample, line):
    """The TRUE pan-MS field (:func:`true_misregistration`, MS pixels) at points ``(sample, line)`` of a crop's
    MS grid (crop MS pixels, GDAL convention), ``scene`` the full product (``make_gf7_scene`` without size)."""
    x0, y0, _, _ = gf7_crop(crop).window("ms")
    _full_scene(scene)
    return true_misregistration(scene, np.asarray(sample, dtype=float) + x0, np.asarray(line, dtype=float) + y0)


def crop_sub_ccd_edges(scene, crop) -> list:
    """The TRUE MS sub-CCD edges strictly inside a crop, in the crop's MS pixels (columns)."""
    x0, _, w, _ = gf7_crop(crop).window("ms")
    return [e - x0 for e in _full_scene(scene).image("ms").true.camera.edges_in_image() if 0 < e - x0 < w]


def _write_gf7_images(scene, results, *, render, reference, windows, workers, tile, progress, written) -> dict:
    """:attr:`SensorSpec.write_images` of gf7: ``pan/scene.tif`` (1 band) and ``ms/scene.tif`` (4 bands) rendered
    by :func:`render_gf7_image` (or placeholders), ``ms/cover_mask.tif``, ``ms/misregistration_truth.tif``
    (:func:`write_misregistration_truth`); each on the crop's ``windows`` when given. Returns the ``"gf7"``
    record of truth.json."""
    files = {}
    for name, (f0, f1) in (("pan", (0.0, 0.6)), ("ms", (0.6, 0.8))):
        paths = results[name].paths
        win = windows[name] if windows else None
        mask = os.path.join(results[name].dir, "cover_mask.tif") if name == "ms" and render else None
        if render:
            render_gf7_image(scene, name, paths["image"], reference=reference, mask_path=mask, tile=tile,
                             workers=workers, window=win, progress=scaled(progress, f0, f1))
        else:
            size = win[2:] if win else scene.image(name).size
            write_placeholder_tif(paths["image"], size, bands=len(MS_BANDS) if name == "ms" else 1,
                                  origin=win[:2] if win else None)
        written.append(paths["image"])
        files[f"{name}_image"] = f"{name}/scene.tif"
        if mask:
            written.append(mask)
            paths["cover_mask"] = mask
            files["ms_cover_mask"] = "ms/cover_mask.tif"
    report(progress, 0.8, "true misregistration field")
    truth_tif = os.path.join(results["ms"].dir, "misregistration_truth.tif")
    write_misregistration_truth(scene, truth_tif, step=8.0, tile=tile, window=windows["ms"] if windows else None)
    written.append(truth_tif)
    results["ms"].paths["misregistration_truth"] = truth_tif
    files["misregistration_truth"] = "ms/misregistration_truth.tif"
    opt = scene.image("ms").errors["options"]
    return {"options": opt, "misregistration_before": misregistration_stats(
        scene, window=windows["ms"] if windows else None), "files": files, "rendered": bool(render),
        "bands": list(MS_BANDS),
        "definition": "delta = MS image point - (pan true point -> pan RPC/current on the DEM -> MS RPC/current), "
                      "MS pixels (METHODS §9)"}


def write_gf7_scene(out_dir, *, seed: int = 0, camera_seed: int = 4, look_time_s: float = 0.117,
                    jitter: bool = True, yaw_steering: bool = True, clouds: float = 0.0, water: float = 0.0,
                    center=None, size=None, crop=None, crop_center_ms_px: Optional[float] = None, dem=None,
                    render: bool = True, reference=None, n_gcps: int = 50, workers: int = 2, tile: int = 512,
                    progress=None):
    """Write a GF7 pan + MS scene (METHODS §9, §10): :func:`~gdal_gf4cal.simulate.write_scene` ``("gf7", ...)``
    (the same path as ``gf4cal simulate --sensor gf7``): ``pan/`` and ``ms/`` with the RPCs fitted from the
    current models, GCPs, cameras, ``dem.tif``, ``truth.json``; with ``render``, ``pan/scene.tif`` (1 band) and
    ``ms/scene.tif`` (4 bands: blue, green, red, NIR) rendered by :func:`render_gf7_image`,
    ``ms/cover_mask.tif`` (0 clear, 1 cloud, 2 water); always ``ms/misregistration_truth.tif``
    (:func:`write_misregistration_truth`). ``truth.json`` gets a ``"gf7"`` entry: the options,
    :func:`misregistration_stats` and the file names.

    ``crop = (x0, y0, w, h)`` in pan pixels of the full product (:func:`gf7_crop`): the full product is simulated
    and only the crop written, keeping its place (see :func:`~gdal_gf4cal.simulate.write_scene`); the truth of
    the crop from :func:`crop_misregistration` / :func:`crop_sub_ccd_edges`. Other options as
    :func:`make_gf7_scene`. Returns the :class:`~gdal_gf4cal.simulate.SceneResult`."""
    options = dict(look_time_s=look_time_s, jitter=jitter, camera_seed=camera_seed, yaw_steering=yaw_steering,
                   clouds=clouds, water=water, crop_center_ms_px=crop_center_ms_px)
    return write_scene("gf7", os.fspath(out_dir), seed=seed, center=center, size=size, crop=crop, n_gcps=n_gcps,
                       dem=dem, render=render, reference=reference, workers=workers, tile=tile, options=options,
                       progress=progress)


SENSORS["gf7"] = SensorSpec(
    "gf7", "Gaofen-7 backward camera, pan 0.65 m + MS 2.6 m (4 bands) 0.117 s apart, three quartic sub-CCDs, "
    "differential jitter", (113.3, 23.1), (0.0, 1200.0), build_gf7, ("pan", "ms"),
    options=tuple(f.name for f in fields(GF7Options)), write_images=_write_gf7_images,
    crop_windows=lambda crop: gf7_crop(crop).windows())
