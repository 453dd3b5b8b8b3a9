"""Issue 23: the simulator's fast rendering paths give the numbers of the plain ones.

- value noise from a per-tile table of lattice hashes = hashing every point (exactly);
- a GF7 pan window across a sub-CCD edge and a 4-band MS window with clouds and water (and its cover mask) render
  to the bytes the renderer gave before the speed-up (SHA-256 pinned from commit c7c2dc8, the tree before it);
- the same bytes with 1 and 2 threads;
- the 32 px node grid of the lines of sight: its interpolation error against every pixel's own line of sight is
  < 0.01 px; the whole image -> ground mapping against the exact DEM intersection (localize_dem) stays within
  0.015 px (the straight-line-in-(lon, lat) ray between the two ends of the height range: ~0.011 pan px).
"""
from __future__ import annotations

import hashlib

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal.simulate.gf7 import make_gf7_scene, render_gf7_image
from gdal_gf4cal.simulate.render import (_DemGrid, _value_noise_grad, ground_of_pixels, model_bounds, value_noise,
                                         value_noise_salts)

gdal.UseExceptions()

#: SHA-256 of the rendered bytes, from the renderer before the speed-up (commit c7c2dc8).
PINNED = {"pan": "50d6e55bdf45077ddae189c8570436e9348888a103cbb57ac8611adf9662b761",
          "ms": "3f023738db7e1d35088e9785662a644b98f92e348da77cd285ac094b642e814b",
          "mask": "df6501699a937c73fdefbd9de8f8cd4d6e58c24f701dd8e2698355fb61af2827"}
PAN_WINDOW = (10200, 3000, 256, 192)         # across the first pan sub-CCD edge (10240)
MS_WINDOW = (3500, 2520, 400, 128)           # clouds, clear ground and water


@pytest.fixture(scope="module")
def scenes():
    return make_gf7_scene(seed=0), make_gf7_scene(seed=1, clouds=0.2, water=0.2)


def _sha(path):
    return hashlib.sha256(np.ascontiguousarray(gdal.Open(str(path)).ReadAsArray()).tobytes()).hexdigest()


def _per_point(fn, x, y, chunk=50):
    """``fn`` on chunks of fewer than 64 points: every point hashed on its own (no table)."""
    xs, ys = x.ravel(), y.ravel()
    parts = [fn(xs[i:i + chunk], ys[i:i + chunk]) for i in range(0, xs.size, chunk)]
    return [np.concatenate([p[k] for p in parts]).reshape(x.shape) for k in range(len(parts[0]))]


def test_lattice_table_gives_the_hash_of_every_point():
    rng = np.random.default_rng(5)
    ang = 0.3                                 # a rotated, sheared pixel grid, as a tile's ground points are
    i, j = np.meshgrid(np.arange(96.0), np.arange(80.0))
    x = 1.23e7 + 0.65 * (i * np.cos(ang) - j * np.sin(ang)) + rng.normal(0, 0.01, i.shape)
    y = 2.6e6 + 0.70 * (i * np.sin(ang) + j * np.cos(ang))
    for wl in (7.8, 208.0, 5000.0):
        assert np.array_equal(value_noise(x, y, wl, 17), _per_point(lambda a, b: [value_noise(a, b, wl, 17)], x, y)[0])
        many = value_noise_salts(x, y, wl, (3, 4, 5))
        assert all(np.array_equal(m, value_noise(x, y, wl, s)) for m, s in zip(many, (3, 4, 5)))
        v, g = _value_noise_grad(x, y, wl, 9)
        pv, pg = _per_point(lambda a, b: _value_noise_grad(a, b, wl, 9), x, y)
        assert np.array_equal(v, pv) and np.array_equal(g, pg)
    # scattered points (a table larger than the points): hashed per point
    xs, ys = rng.uniform(0, 1e6, 500), rng.uniform(0, 1e6, 500)
    assert np.array_equal(value_noise(xs, ys, 7.8, 1), _per_point(lambda a, b: [value_noise(a, b, 7.8, 1)], xs, ys)[0])


def test_gf7_render_keeps_the_bytes_of_before_the_speedup(scenes, tmp_path):
    plain, cover = scenes
    render_gf7_image(plain, "pan", tmp_path / "pan.tif", window=PAN_WINDOW, workers=2)
    render_gf7_image(cover, "ms", tmp_path / "ms.tif", window=MS_WINDOW, workers=2, mask_path=tmp_path / "mask.tif")
    mask = gdal.Open(str(tmp_path / "mask.tif")).ReadAsArray()
    assert all(np.mean(mask == c) > 0.05 for c in (0, 1, 2))        # the window has clear, cloud and water
    assert {k: _sha(tmp_path / f"{k}.tif") for k in PINNED} == PINNED


def test_gf7_render_same_bytes_with_1_and_2_threads(scenes, tmp_path):
    plain, _ = scenes
    for w in (1, 2):
        render_gf7_image(plain, "pan", tmp_path / f"t{w}.tif", window=(10200, 3000, 384, 256), tile=128, workers=w)
    assert _sha(tmp_path / "t1.tif") == _sha(tmp_path / "t2.tif")


def test_line_of_sight_node_grid_within_a_hundredth_of_a_pixel(scenes):
    plain, _ = scenes
    m0 = plain.image("pan").true
    m = m0.with_camera(m0.camera.piece_camera(1))
    dg = _DemGrid(plain.dem, model_bounds(m))
    x0, y0, w, h = 12000, 2000, 96, 80
    coarse = ground_of_pixels(m, dg, x0, y0, w, h)                 # the renderer's 32 px node grid
    fine = ground_of_pixels(m, dg, x0, y0, w, h, step=1)           # every pixel's own line of sight
    s, l = np.meshgrid(x0 + np.arange(w) + 0.5, y0 + np.arange(h) + 0.5)
    cs, cl = m.project(*coarse)
    fs, fl = m.project(*fine)
    assert np.max(np.hypot(cs - fs, cl - fl)) < 0.01
    # the whole mapping against the exact DEM intersection of a sample of pixels
    lon, lat, hh = m.localize_dem(s[::7, ::7].ravel(), l[::7, ::7].ravel(), plain.dem)
    es, el = m.project(lon, lat, hh)
    assert np.max(np.hypot(cs[::7, ::7].ravel() - es, cl[::7, ::7].ravel() - el)) < 0.015


def test_gf7_render_keeps_gdal_block_cache_at_a_few_tiles(scenes, tmp_path):
    """As render_image (issue 14): each 4-band tile is flushed out of GDAL's block cache once written (the full
    MS is 236 MB of blocks, the pan 944 MB)."""
    _, cover = scenes
    used, tile = [], 64
    base = gdal.GetCacheUsed()
    render_gf7_image(cover, "ms", tmp_path / "ms.tif", window=(3500, 2520, 512, 256), tile=tile, workers=2,
                     mask_path=tmp_path / "mask.tif", progress=lambda f, m="": used.append(gdal.GetCacheUsed()))
    assert len(used) == (512 // tile) * (256 // tile)
    # growth after the first tile (the DEM copy's reads come before): without the flush ~635 kB here
    assert max(used) - used[0] < 12 * 5 * tile * tile, (max(used), used[0], base)
