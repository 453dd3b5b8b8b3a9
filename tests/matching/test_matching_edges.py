"""collect-gcps against an ortho whose pixel grid is the raw image's (two orthos of one tiling, as AROSICS's
Sentinel-2 pair, bench/bench_arosics.py): the reference is read, not resampled; windows cut by the reference's edge
or its no-data collar are matched on the largest centred square inside them (as AROSICS shrinks its windows),
windows whose centre it does not cover are ``outside_image``; a changed quarter of a window is judged by the
window's correlation, a covered one (cloud) is rejected.

The raw image is a crop of the reference texture moved by a known sub-pixel amount (exact Fourier shift of a larger
block), with an RPC fitted to its geotransform at one height: the truth of every offset is that amount.
"""
from __future__ import annotations

import numpy as np
import pyproj
import pytest
from osgeo import gdal
from scipy import ndimage

from gdal_gf4cal.matching import ReferenceImage, assemble_gcps, plan_tiles, reference_on_grids, run_tiles
from gdal_gf4cal.matching import collect, resample
from gdal_gf4cal.rpc_fit import fit_rpc

from matchscene import UTM31, builtin_texture
from rasters import write_tif

HEIGHT = 300.0
GT = (650000.0, 10.0, 0.0, 4900000.0, 0.0, -10.0)
SHIFT = (0.3, -0.2)   # the raw image's content moved by (x, y) px: the offset every GCP must measure


def _grid_rpc(gt, W, H):
    """RPC of an ortho of ``W x H`` px with geotransform ``gt`` (UTM 31N), fitted at one height."""
    s, l = (v.ravel() for v in np.meshgrid(np.linspace(0, W, 21), np.linspace(0, H, 21)))
    lon, lat = pyproj.Transformer.from_crs(UTM31, 4326, always_xy=True).transform(gt[0] + s * gt[1],
                                                                                gt[3] + l * gt[5])
    return fit_rpc(np.asarray(lon), np.asarray(lat), np.full(s.size, HEIGHT), s, l)[0]


def _pair(folder, x0, y0, W, H, size=(640, 640), edit=None, reference=None):
    """A reference texture ``size`` (UTM 31N, 10 m) and the raw ``W x H`` crop at reference pixel ``(x0, y0)``
    moved by ``SHIFT``; ``edit(raw)`` changes the raw pixels, ``reference(tex)`` the reference's."""
    tex = builtin_texture(size[::-1], seed=11)
    tex = 1000 + 150 * (tex - tex.mean()) / tex.std()
    moved = np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(tex), SHIFT[::-1])).real
    raw = moved[y0:y0 + H, x0:x0 + W].copy()
    if edit is not None:
        edit(raw)
    gt = (GT[0] + x0 * GT[1], GT[1], 0.0, GT[3] + y0 * GT[5], 0.0, GT[5])
    image = write_tif(folder / "raw.tif", np.clip(raw, 1, 65535).astype(np.float32), gt=gt, epsg=UTM31)
    ref = tex if reference is None else reference(tex.copy())
    ref_path = write_tif(folder / "ref.tif", ref.astype(np.float32), gt=GT, epsg=UTM31, nodata=0)
    return image, ref_path, _grid_rpc(gt, W, H)


def _collect(image, rpc, ref, spacing, window):
    specs, ctx = plan_tiles(image, rpc, ref, HEIGHT, spacing, window, search_px=8, margin_px=0)
    res = run_tiles(specs, workers=1)
    cat = {k: np.concatenate([r[k] for r in res]) for k in ("status", "center_sample", "center_line", "dsample",
                                                            "dline")}
    return cat, assemble_gcps(res, ctx)


def test_reference_on_the_raw_grid_is_read_not_resampled(tmp_path, monkeypatch):
    image, ref, rpc = _pair(tmp_path, 100, 80, 320, 256)
    x0 = np.array([0.0, 64.0, 200.0])
    y0 = np.array([0.0, 100.0, 150.0])
    pix = gdal.Open(ref).ReadAsArray().astype(np.float64)
    read = reference_on_grids(rpc, HEIGHT, ReferenceImage(ref), x0, y0, 64)
    for k in range(3):
        np.testing.assert_array_equal(read[k], pix[int(y0[k]) + 80:int(y0[k]) + 144, int(x0[k]) + 100:
                                                  int(x0[k]) + 164])
    # The shared grid of dense windows too.
    dense = reference_on_grids(rpc, HEIGHT, ReferenceImage(ref), [0, 32], [0, 0], 64, shared=True)
    np.testing.assert_array_equal(dense[1], pix[80:144, 132:196])
    # The cubic spline at whole pixels returns the pixels: the read is what resampling gives, to rounding.
    monkeypatch.setattr(resample, "IDENTITY_TOL", -1.0)
    np.testing.assert_allclose(reference_on_grids(rpc, HEIGHT, ReferenceImage(ref), x0, y0, 64), read, atol=1e-3)
    np.testing.assert_allclose(reference_on_grids(rpc, HEIGHT, ReferenceImage(ref), [0, 32], [0, 0], 64,
                                                  shared=True), dense, atol=1e-3)


def test_float32_grids_and_the_whole_pixel_probe(tmp_path, monkeypatch):
    """``dtype=np.float32`` gives the float64 values rounded (read and resampled, window by window and shared), and
    the whole-pixel probe (a subset of the nodes) does not take a mapping off a translation by 1e-3 px over a window
    for one: that is resampled exactly as when every node is tested."""
    image, ref, rpc = _pair(tmp_path, 100, 80, 320, 256)
    x0, y0 = np.array([0.0, 64.0, 200.0]), np.array([0.0, 100.0, 150.0])
    r = ReferenceImage(ref)
    for tol in (resample.IDENTITY_TOL, -1.0):   # whole-pixel read, then resampling forced
        monkeypatch.setattr(resample, "IDENTITY_TOL", tol)
        for xs, ys, shared in ((x0, y0, False), ([0, 32], [0, 0], True)):
            f64 = reference_on_grids(rpc, HEIGHT, r, xs, ys, 64, shared=shared)
            f32 = reference_on_grids(rpc, HEIGHT, r, xs, ys, 64, shared=shared, dtype=np.float32)
            assert f64.dtype == np.float64 and f32.dtype == np.float32
            np.testing.assert_array_equal(f32, f64.astype(np.float32))
    monkeypatch.setattr(resample, "IDENTITY_TOL", 1e-4)
    # The reference's pixels 1 + 1.6e-5 times larger about the first node (raw (0.5, 0.5), reference column
    # 100.5): 0 px off there, 1e-3 px 63 px further, more than IDENTITY_TOL only beyond 6 px.
    a = GT[1] * (1 + 1.6e-5)
    gt = (GT[0] + 100.5 * (GT[1] - a), a, 0.0, GT[3], 0.0, GT[5])
    off = write_tif(tmp_path / "off.tif", gdal.Open(ref).ReadAsArray(), gt=gt, epsg=UTM31, nodata=0)
    pix = gdal.Open(off).ReadAsArray().astype(np.float64)
    for xs, ys, shared in ((x0, y0, False), ([0, 32], [0, 0], True)):
        got = reference_on_grids(rpc, HEIGHT, ReferenceImage(off), xs, ys, 64, shared=shared)
        assert not np.array_equal(got[0], pix[80 + int(ys[0]):144 + int(ys[0]), 100 + int(xs[0]):164 + int(xs[0])])
        monkeypatch.setattr(resample, "PROBE_EVERY", 1)   # every node tested, as before the probe
        np.testing.assert_array_equal(got, reference_on_grids(rpc, HEIGHT, ReferenceImage(off), xs, ys, 64,
                                                              shared=shared))
        monkeypatch.setattr(resample, "PROBE_EVERY", 4)


def test_windows_cut_by_the_reference_edge_or_nodata_shrink(tmp_path):
    """Raw crop at reference pixel (300, 200), 320 x 320: the reference ends at raw x = 240 (no data beyond its
    column 540) and has a no-data triangle over the crop's top-left corner (raw x + y < 90)."""
    def cut(tex):
        yy, xx = np.mgrid[0:tex.shape[0], 0:tex.shape[1]]
        tex[(xx - 300) + (yy - 200) < 90] = 0             # a no-data collar across the raw's top-left corner
        return tex[:, :540]                               # the reference raster ends at raw x = 240
    image, ref, rpc = _pair(tmp_path, 300, 200, 320, 320, reference=cut)
    cat, g = _collect(image, rpc, ref, 32, 64)
    cs, cl, st = cat["center_sample"], cat["center_line"], cat["status"]
    # Distance (raw px, chessboard) from each window centre to the reference's edge or no-data.
    free = np.minimum(240 - cs, (cs + cl - 90) / 2.0)
    assert np.all(st[cs > 240] == 5) and not np.any(st[free < 0] == 0)
    cut_windows = (free >= 16) & (free < 32) & (cs >= 32) & (cl >= 32) & (cs <= 288) & (cl <= 288)
    assert cut_windows.sum() >= 8
    assert np.mean(st[cut_windows] == 0) >= 0.9, st[cut_windows]
    ok = st == 0
    err = np.hypot(cat["dsample"][ok] - SHIFT[0], cat["dline"][ok] - SHIFT[1])
    assert np.max(err[cut_windows[ok]]) < 0.05, err[cut_windows[ok]]
    assert np.sqrt(np.mean(err ** 2)) < 0.02
    assert len(g) == ok.sum() and not g["outlier"].any()


def test_changed_quarter_is_judged_by_the_window_a_covered_one_is_rejected(tmp_path):
    """Four 256-px windows; in the raw image one window's top-left quarter shows other ground (a change: the
    texture of another place), another's is under a cloud (haze at the ground's brightness, faint structure)."""
    rng = np.random.default_rng(3)

    def edit(raw):
        raw[:128, :128] = raw[300:428, 300:428][::-1].copy()          # window (128, 128): changed quarter
        cloud = raw[256:384, 256:384].mean() + 10 * ndimage.gaussian_filter(rng.standard_normal((128, 128)), 3)
        raw[256:384, 256:384] = cloud                                    # window (384, 384): covered quarter
    image, ref, rpc = _pair(tmp_path, 60, 60, 512, 512, edit=edit)
    cat, _ = _collect(image, rpc, ref, 256, 256)
    st = dict(zip(zip(cat["center_sample"], cat["center_line"]), cat["status"]))
    d = dict(zip(zip(cat["center_sample"], cat["center_line"]), zip(cat["dsample"], cat["dline"])))
    assert st[(128.0, 128.0)] == 0 and np.hypot(d[(128.0, 128.0)][0] - SHIFT[0], d[(128.0, 128.0)][1] - SHIFT[1]) < 0.05
    assert st[(384.0, 384.0)] == 4
    assert st[(384.0, 128.0)] == 0 and st[(128.0, 384.0)] == 0


@pytest.mark.parametrize("window", [64, 256])
def test_every_window_measures_the_shift(tmp_path, window):
    image, ref, rpc = _pair(tmp_path, 64, 64, 512, 512)
    cat, g = _collect(image, rpc, ref, 128, window)
    ok = cat["status"] == 0
    assert ok.sum() >= 4
    np.testing.assert_allclose(cat["dsample"][ok], SHIFT[0], atol=0.02)
    np.testing.assert_allclose(cat["dline"][ok], SHIFT[1], atol=0.02)


def test_large_windows_keep_ground_whose_brightness_changed(tmp_path):
    """Fields whose reflectance changed between the dates (a strong smooth brightness pattern added to the raw
    image only) drop the NCC of 256-px windows below ``min_ncc``; their phase-correlation peak stays unambiguous,
    so they are kept (collect.LARGE_WINDOW_PX), with the right offset."""
    def edit(raw):
        fields = ndimage.gaussian_filter(np.random.default_rng(5).standard_normal(raw.shape), 12)
        raw += 700 * fields / fields.std()
    image, ref, rpc = _pair(tmp_path, 60, 60, 512, 512, edit=edit)
    specs, ctx = plan_tiles(image, rpc, ref, HEIGHT, 256, 256, search_px=8, margin_px=0)
    res = run_tiles(specs, workers=1)
    cat = {k: np.concatenate([r[k] for r in res]) for k in ("status", "ncc", "peak_ratio", "dsample", "dline")}
    assert np.all(cat["status"] == 0), cat
    assert np.sum(cat["ncc"] < 0.3) >= 3, cat["ncc"]
    err = np.hypot(cat["dsample"] - SHIFT[0], cat["dline"] - SHIFT[1])
    assert np.max(err) < 0.05, err


def test_a_quarter_that_gained_texture_does_not_make_the_others_covered(tmp_path):
    """One 256-px window: new strong structure in its top-left quarter (twice the ground's contrast added)
    and other ground in its bottom-right one (a changed field, as textured as before). Neither is a cover: the
    window is judged by its correlation and measures the shift."""
    def edit(raw):
        raw[:128, :128] += 2 * (raw[384:512, 0:128] - raw[384:512, 0:128].mean())
        raw[128:256, 128:256] = raw[300:428, 300:428][:, ::-1].copy()
    image, ref, rpc = _pair(tmp_path, 60, 60, 512, 512, edit=edit)
    cat, _ = _collect(image, rpc, ref, 256, 256)
    st = dict(zip(zip(cat["center_sample"], cat["center_line"]), cat["status"]))
    d = dict(zip(zip(cat["center_sample"], cat["center_line"]), zip(cat["dsample"], cat["dline"])))
    assert st[(128.0, 128.0)] == 0
    # Half of the window is other ground: its error is larger than the unchanged windows' (< 0.005 px).
    assert np.hypot(d[(128.0, 128.0)][0] - SHIFT[0], d[(128.0, 128.0)][1] - SHIFT[1]) < 0.06


def test_probe_for_a_translation_only_where_the_corners_allow_one(tmp_path, monkeypatch):
    """A tile whose windows' corners are no whole-pixel translation of the reference (here its pixels 0.1 % larger)
    is resampled without probing a subset of the nodes for one first (a localisation saved per tile), the same bits
    as with the probe; corners on the raw grid keep the probe, and a grid read with ``probe=False`` is still
    recognised as a translation on every node."""
    image, ref, rpc = _pair(tmp_path, 100, 80, 320, 256)
    probes = []
    real = resample._probe_shift
    monkeypatch.setattr(resample, "_probe_shift", lambda *a: probes.append(1) or real(*a))
    _collect(image, rpc, ref, 64, 64)
    assert probes
    pix = gdal.Open(ref).ReadAsArray()
    a = GT[1] * 1.001
    scaled = write_tif(tmp_path / "scaled.tif", pix, gt=(GT[0] + 100.5 * (GT[1] - a), a, 0.0, GT[3], 0.0, GT[5]),
                       epsg=UTM31, nodata=0)
    probes.clear()
    got, g = _collect(image, rpc, scaled, 64, 64)
    assert not probes and len(g) > 10
    monkeypatch.setattr(collect, "whole_pixel_shift", lambda dx, dy: (0, 0))   # corners said translated: probe
    again, _ = _collect(image, rpc, scaled, 64, 64)
    assert probes
    for k in ("dsample", "dline", "status"):
        np.testing.assert_array_equal(got[k], again[k])
    r = ReferenceImage(ref)
    for xs, ys, shared in (([0.0, 64.0, 200.0], [0.0, 100.0, 150.0], False), ([0, 32], [0, 0], True)):
        np.testing.assert_array_equal(reference_on_grids(rpc, HEIGHT, r, xs, ys, 64, shared=shared, probe=False),
                                      reference_on_grids(rpc, HEIGHT, r, xs, ys, 64, shared=shared))
