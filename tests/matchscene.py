"""Rendered test scenes for automatic GCP collection (issue 7): the shared builder of the matching, executor and
batch tests (tests/matching/test_matching_scene.py checks the renderer itself with GDAL).

A scene = a reference orthophoto (GeoTIFF, UTM 31N), a real SRTM DEM crop (Mont Ventoux), a raw image rendered
through a *true* RPC, and a *biased* RPC (the true one composed with a known image-space affine error) that the
matcher is given. The raw image is rendered by forward projection ("splatting"): a ground grid three times finer
than the reference is projected with the true RPC (``project``, closed form) and averaged per raw pixel, so the
raw pixels integrate the ground like a detector and the renderer shares no code path with the matcher (which
localises raw pixels with ``localize_dem`` and samples the reference with cubic splines).

Truth: the ground point ``(lon, lat, h)`` of a GCP is truly imaged at ``true_rpc.project(lon, lat, h)``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Tuple

import numpy as np

from rasters import write_tif
from gdal_gf4cal.dem import DEM
from gdal_gf4cal.rpc import RPCModel

DATA = Path(__file__).parent / "data" / "matching"
SRTM = DATA / "srtm_ventoux_crop.tif"
PLEIADES = DATA / "pleiades_ventoux_left.tif"
UTM31 = 32631


def synthetic_rpc(size: Tuple[int, int], gsd_m: float, lon0: float = 5.27, lat0: float = 44.17,
                  parallax: float = 0.03) -> RPCModel:
    """A smooth RPC of a ``size`` image at ``gsd_m`` (north up), with height parallax and mild non-linearity.

    Both image axes share one denominator, so an image-space affine error folds exactly (:func:`affine_rpc`).
    """
    W, H = size
    half_w_m, half_h_m = W / 2 * gsd_m, H / 2 * gsd_m
    long_scale = half_w_m / (111320.0 * np.cos(np.radians(lat0)))
    lat_scale = half_h_m / 110950.0
    num_s = np.zeros(20)
    num_l = np.zeros(20)
    den = np.zeros(20)
    num_s[[1, 2, 3, 4, 7]] = [1.0, 0.015, parallax, 0.004, -0.003]     # L, P, H, LP, L2
    num_l[[1, 2, 3, 8, 4]] = [0.01, -1.0, -0.4 * parallax, 0.003, 0.002]  # L, P, H, P2, LP
    den[[0, 1, 2]] = [1.0, 0.002, -0.0015]
    return RPCModel(line_off=H / 2 - 0.5, samp_off=W / 2 - 0.5, lat_off=lat0, long_off=lon0, height_off=1000.0,
                    line_scale=H / 2, samp_scale=W / 2, lat_scale=lat_scale, long_scale=long_scale,
                    height_scale=1000.0, line_num=num_l, line_den=den, samp_num=num_s, samp_den=den)


def affine_rpc(rpc: RPCModel, A: np.ndarray) -> RPCModel:
    """RPC whose projection is ``A @ [1, s, l]`` of ``rpc``'s (GDAL convention; exact for a common denominator)."""
    assert np.allclose(rpc.samp_den, rpc.line_den)
    so, lo = rpc.samp_off + 0.5, rpc.line_off + 0.5
    ss, ls = rpc.samp_scale, rpc.line_scale
    D, Ns, Nl = np.asarray(rpc.samp_den), np.asarray(rpc.samp_num), np.asarray(rpc.line_num)
    new = []
    for row, off, sc in ((A[0], so, ss), (A[1], lo, ls)):
        const = row[0] + row[1] * so + row[2] * lo - off
        new.append((const * D + row[1] * ss * Ns + row[2] * ls * Nl) / sc)
    return rpc.replace(samp_num=new[0], line_num=new[1])


def error_affine(shift=(0.0, 0.0), rotation_rad=0.0, scale=1.0, center=(0.0, 0.0)) -> np.ndarray:
    """2x3 image-space affine ``E`` acting on ``[1, s, l]``: the biased RPC predicts ``E(true position)``
    (rotation/scale about ``center``); a matcher measures ``true - E(true)``."""
    c, s = np.cos(rotation_rad) * scale, np.sin(rotation_rad) * scale
    M = np.array([[c, -s], [s, c]])
    t = np.asarray(center) - M @ np.asarray(center) + np.asarray(shift)
    return np.column_stack([t, M])




def builtin_texture(shape, seed: int = 7) -> np.ndarray:
    """The simulator's fractal (spectral-synthesis) surface used as a ground texture: land-cover-like patches."""
    from gdal_gf4cal.simulate.terrain import fractal_surface
    return 0.6 * fractal_surface(shape, seed, beta=2.4) + 0.4 * fractal_surface(shape, seed + 1, beta=1.8)


def pleiades_texture() -> np.ndarray:
    from osgeo import gdal
    return gdal.Open(str(PLEIADES)).ReadAsArray().astype(np.float64)


@dataclass
class Scene:
    image: str
    reference: str
    dem: DEM
    dem_path: str
    true_rpc: RPCModel
    rpc: RPCModel                 # biased: what the matcher is given
    size: Tuple[int, int]
    cloud_mask: np.ndarray        # raw-geometry masks of painted features (bool, lines x samples)
    water_mask: np.ndarray

    def truth(self, lon, lat, h):
        return self.true_rpc.project(lon, lat, h)


def _ground_frame(rpc: RPCModel, size, ref_px_m: float, margin_m: float):
    """UTM 31N frame (geotransform, shape) covering the image footprint plus ``margin_m``."""
    import pyproj
    W, H = size
    s = np.array([0, W, 0, W, W / 2]) * 1.0
    l_ = np.array([0, 0, H, H, H / 2]) * 1.0
    lon, lat = rpc.localize(s, l_, 1000.0)
    tr = pyproj.Transformer.from_crs(4326, UTM31, always_xy=True)
    x, y = tr.transform(lon, lat)
    x0, x1 = np.min(x) - margin_m, np.max(x) + margin_m
    y0, y1 = np.min(y) - margin_m, np.max(y) + margin_m
    nx = int(np.ceil((x1 - x0) / ref_px_m))
    ny = int(np.ceil((y1 - y0) / ref_px_m))
    return (float(np.floor(x0)), ref_px_m, 0.0, float(np.ceil(y1)), 0.0, -ref_px_m), (ny, nx)


def render(true_rpc: RPCModel, dem: DEM, texture: np.ndarray, gt, size, sub: int = 3) -> np.ndarray:
    """Raw image (float64, lines x samples) seen through ``true_rpc``: ground grid ``sub`` x finer than the
    texture, projected and averaged per raw pixel (NaN where no ground sample fell)."""
    import pyproj
    from scipy import ndimage
    W, H = size
    ny, nx = texture.shape
    tr = pyproj.Transformer.from_crs(UTM31, 4326, always_xy=True)
    out_sum = np.zeros(W * H)
    out_cnt = np.zeros(W * H)
    off = (np.arange(sub) + 0.5) / sub
    for r0 in range(0, ny, 128):  # strips keep memory small
        rows = np.arange(r0, min(ny, r0 + 128))
        fy = (rows[:, None] + off[None, :]).ravel()
        fx = (np.arange(nx)[:, None] + off[None, :]).ravel()
        FX, FY = np.meshgrid(fx, fy)
        val = ndimage.map_coordinates(texture, [FY.ravel() - 0.5, FX.ravel() - 0.5], order=1, mode="nearest")
        X = gt[0] + gt[1] * FX.ravel()
        Y = gt[3] + gt[5] * FY.ravel()
        lon, lat = tr.transform(X, Y)
        h = dem.height(lon, lat)
        s, l_ = true_rpc.project(lon, lat, h)
        i = np.floor(s).astype(np.int64)
        j = np.floor(l_).astype(np.int64)
        ok = (i >= 0) & (i < W) & (j >= 0) & (j < H) & np.isfinite(val)
        k = j[ok] * W + i[ok]
        out_sum += np.bincount(k, weights=val[ok], minlength=W * H)
        out_cnt += np.bincount(k, minlength=W * H)
    with np.errstate(invalid="ignore", divide="ignore"):
        img = (out_sum / out_cnt).reshape(H, W)
    return img


def build_scene(folder, *, texture: str = "builtin", size=(384, 384), gsd_m: float = 30.0, ref_px_m: float = 27.0,
                error=None, noise: float = 0.01, water: bool = False, clouds: bool = False,
                seed: int = 0) -> Scene:
    """Write a rendered scene into ``folder`` (see module docstring) and return its description."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    true_rpc = synthetic_rpc(size, gsd_m)
    dem = DEM.from_file(SRTM)
    margin = 80 * gsd_m
    if texture == "pleiades":
        tex = pleiades_texture()
        gt, shape = _ground_frame(true_rpc, size, ref_px_m, margin)
        # The real crop is 500 x 500: choose the pixel size so that it covers the frame.
        ref_px_m = max(gt[1] * shape[1], -gt[5] * shape[0]) / 500.0
        gt, _ = _ground_frame(true_rpc, size, ref_px_m, margin)
        tex = tex[:500, :500]
    else:
        gt, shape = _ground_frame(true_rpc, size, ref_px_m, margin)
        tex = builtin_texture(shape, seed=7 + seed)
    tex = (tex - tex.mean()) / tex.std()
    W, H = size
    water_ground = np.zeros(tex.shape, dtype=bool)
    if water:
        # A lake: flat in the reference and on the ground (so in the raw image too).
        yy, xx = np.mgrid[0:tex.shape[0], 0:tex.shape[1]]
        cy, cx = 0.35 * tex.shape[0], 0.6 * tex.shape[1]
        water_ground = ((yy - cy) / (0.14 * tex.shape[0])) ** 2 + ((xx - cx) / (0.2 * tex.shape[1])) ** 2 < 1
        tex = np.where(water_ground, -2.5, tex)
    ref_u16 = np.clip(1000 + 150 * tex, 1, 65535).astype(np.uint16)
    reference = write_tif(folder / "reference.tif", ref_u16, gt=gt, epsg=UTM31)
    raw = render(true_rpc, dem, ref_u16.astype(np.float64), gt, size)
    water_mask = render(true_rpc, dem, water_ground.astype(np.float64), gt, size) > 0.5 if water else \
        np.zeros((H, W), dtype=bool)
    cloud_mask = np.zeros((H, W), dtype=bool)
    if clouds:
        from scipy import ndimage
        yy, xx = np.mgrid[0:H, 0:W]
        blob = np.hypot((yy - 0.7 * H) / (0.16 * H), (xx - 0.3 * W) / (0.2 * W)) < 1
        alpha = np.clip(ndimage.gaussian_filter(blob.astype(float), 4), 0, 1)
        # Clouds are bright with their own faint structure, only in the raw image.
        cloud_tex = 1800 + 40 * ndimage.gaussian_filter(rng.standard_normal((H, W)), 3)
        raw = (1 - alpha) * raw + alpha * cloud_tex
        cloud_mask = alpha > 0.5
    # Different radiometry from the reference (gain, offset) plus detector noise; quantised like a product.
    raw = 0.8 * raw + 200.0
    raw = raw + noise * np.nanstd(raw) * rng.standard_normal(raw.shape)
    raw = np.where(np.isfinite(raw), raw, 0)
    image = write_tif(folder / "raw.tif", np.clip(np.round(raw * 4), 1, 65535).astype(np.uint16), nodata=0)
    if error is None:
        error = error_affine()
    biased = affine_rpc(true_rpc, error)
    return Scene(image, reference, dem, str(SRTM), true_rpc, biased, size, cloud_mask, water_mask)


# ------------------------------------------------------------------------------------- checks of the renderer
