"""Raw-to-raw matching (issues 12 and 13): CCD overlaps and band to band on a rendered Jilin-1 group, pan-MS cells on
a rendered Gaofen-7 scene, against the simulators' TRUE models (METHODS §8, §9).

Truth of a tie ``(a: p_a, b: p_b)``: the ground point ``a.true`` shows at ``p_a`` (on the scene DEM), projected with
``b.true``, must be ``p_b``. Truth of a pan-MS offset: :func:`gdal_gf4cal.simulate.gf7.true_misregistration`.
"""
from __future__ import annotations

import pickle

import numpy as np
import pandas as pd
import pytest
from osgeo import gdal
from scipy import ndimage

from gdal_gf4cal.dem import DEM
from gdal_gf4cal.errors import Gf4calError
from gdal_gf4cal.executors import SerialExecutor
from gdal_gf4cal.rpc import RPCModel
from gdal_gf4cal.matching import (RawReference, cells_from_matches, match_raw, match_tile, match_ties, pan_ms_cells,
                                  plan_tiles, reference_on_grids)
from gdal_gf4cal.matching.collect import match_tiles
from gdal_gf4cal.matching.raw import CELL_COLUMNS, RAW_COLUMNS, _same_windows, match_raw_bands
from gdal_gf4cal.simulate import write_scene
from gdal_gf4cal.simulate.gf7 import cover_weights, true_misregistration, write_gf7_scene


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


@pytest.fixture(scope="module")
def jl1(tmp_path_factory):
    """A rendered 512 x 512 (pan) Jilin-1 group: 4 CCDs x (pan + 4 MS bands), 128 px pan overlaps (~20 s: the
    tests using it are slow)."""
    out = tmp_path_factory.mktemp("jl1")
    res = write_scene("jl1", out, seed=5, size=(512, 512), render=True, n_gcps=10, reference_ortho=False)
    return out, res.scene


def _path(out, name):
    return str(out / name / "scene.tif")


def _tie_errors(ties, scene, a, b):
    A = ties[ties.image_id == a].reset_index(drop=True)
    B = ties[ties.image_id == b].reset_index(drop=True)
    assert (A.point_id == B.point_id).all()
    lon, lat, h = scene.image(a).true.localize_dem(A["sample"].to_numpy(), A["line"].to_numpy(), scene.dem)
    bs, bl = scene.image(b).true.project(lon, lat, h)
    return B["sample"].to_numpy() - bs, B["line"].to_numpy() - bl, (bs, bl)


@pytest.mark.slow
def test_jl1_renders_every_image(jl1):
    out, scene = jl1
    assert len(scene.images) == 20
    for im in scene.images:
        ds = gdal.Open(_path(out, im.name))
        assert (ds.RasterXSize, ds.RasterYSize) == tuple(im.true.size)
        assert ds.GetRasterBand(1).ComputeRasterMinMax()[1] > ds.GetRasterBand(1).ComputeRasterMinMax()[0] + 50


@pytest.mark.slow
@pytest.mark.parametrize("a, b", [("ccd1", "ccd2"), ("ccd2", "ccd3"), ("ccd3", "ccd4")])
def test_ties_between_adjacent_ccds_agree_with_true_models(jl1, a, b):
    out, scene = jl1
    dem = str(out / "dem.tif")
    ties = match_ties(_path(out, a), scene.image(a).current, _path(out, b), scene.image(b).current, dem, ids=(a, b),
                      spacing_px=32, window_px=32)
    assert list(ties.columns[:10]) == ["point_id", "image_id", "kind", "sample", "line", "sigma", "role", "lon", "lat",
                                       "h"]
    assert (ties.kind == "tie").all() and set(ties.image_id) == {a, b}
    es, el, (bs, bl) = _tie_errors(ties, scene, a, b)
    assert es.size >= 15
    assert _rms(es) <= 0.1 and _rms(el) <= 0.1, (_rms(es), _rms(el))
    assert np.abs(es).max() <= 0.3 and np.abs(el).max() <= 0.3
    # Only the overlap: every tie is truly seen by both images, and lies in a's overlap strip (its right edge).
    W = scene.image(b).true.size[0]
    assert ((bs > 0) & (bs < W)).all()
    A = ties[ties.image_id == a]
    assert A["sample"].min() > 512 - 128 - 40
    w = ties.attrs["windows"]
    assert w["accepted"] >= 15 and w["total"] < 16 * 16 / 2  # the grid was restricted to the overlap


@pytest.mark.slow
def test_band_to_reference_band_ties(jl1):
    out, scene = jl1
    a, b = "ccd2_green", "ccd2_blue"
    ties = match_ties(_path(out, a), scene.image(a).current, _path(out, b), scene.image(b).current,
                      str(out / "dem.tif"), ids=(a, b), spacing_px=16, window_px=32)
    es, el, _ = _tie_errors(ties, scene, a, b)
    assert es.size >= 25
    assert _rms(es) <= 0.1 and _rms(el) <= 0.1, (_rms(es), _rms(el))


@pytest.mark.slow
def test_match_raw_columns_and_identity(jl1):
    """An image matched against itself through the same model: every offset is zero (the resampling through
    localise-then-project is the identity), and the table has the documented columns."""
    out, scene = jl1
    p, m = _path(out, "ccd1"), scene.image("ccd1").current
    t = match_raw(p, m, p, m, str(out / "dem.tif"), spacing_px=96, window_px=32, workers=1)
    assert tuple(t.columns) == RAW_COLUMNS
    ok = t.status == 0
    assert ok.sum() >= 16
    assert np.abs(t.d_sample[ok]).max() < 0.02 and np.abs(t.d_line[ok]).max() < 0.02
    np.testing.assert_allclose(t.ref_sample[ok], t.pred_sample[ok], atol=1e-6)
    np.testing.assert_allclose(t["sample"], t.pred_sample + t.d_sample)
    # The resampler sees the raw reference exactly: reference_on_grids through the same model reproduces pixels.
    ref = RawReference(p, m)
    grid = reference_on_grids(m, DEM.from_user_input(str(out / "dem.tif")), ref, [100.0], [120.0], 16)[0]
    raw = gdal.Open(p).ReadAsArray(100, 120, 16, 16).astype(float)
    assert np.abs(grid - raw).max() < 0.05


@pytest.mark.slow
def test_no_overlap_is_a_clear_error(jl1):
    out, scene = jl1
    with pytest.raises(Gf4calError, match="do not overlap"):
        match_ties(_path(out, "ccd1"), scene.image("ccd1").current, _path(out, "ccd4"),
                   scene.image("ccd4").current, str(out / "dem.tif"), ids=("ccd1", "ccd4"))


@pytest.fixture(scope="module")
def gf7(tmp_path_factory):
    """A rendered GF7 crop (pan 1024^2, MS 256^2) across the first sub-CCD edge, 20 % cloud and 10 % water."""
    out = tmp_path_factory.mktemp("gf7")
    res = write_gf7_scene(out, seed=3, size=(1024, 1024), crop_center_ms_px=2560, clouds=0.2, water=0.1,
                          n_gcps=10, tile=256)
    return out, res.scene


@pytest.fixture(scope="module")
def gf7_small(tmp_path_factory):
    """A rendered clear GF7 crop (pan 512^2, MS 128^2) across the first sub-CCD edge."""
    out = tmp_path_factory.mktemp("gf7s")
    res = write_gf7_scene(out, seed=3, size=(512, 512), crop_center_ms_px=2560, n_gcps=10, tile=256)
    return out, res.scene


def test_pan_ms_sign_and_accuracy_on_a_clear_crop(gf7_small):
    """Windows and cells give METHODS §9's nabla = p' - p'' (MS px): the simulator's true misregistration."""
    out, scene = gf7_small
    pan, ms = str(out / "pan" / "scene.tif"), str(out / "ms" / "scene.tif")
    cells = pan_ms_cells(pan, ms, str(out / "dem.tif"), cell_px=32, window_px=32, spacing_px=8,
                         executor=SerialExecutor())
    t = cells.attrs["matches"]
    ok = (t.status == 0).to_numpy()
    assert ok.mean() > 0.95
    ts, tl = true_misregistration(scene, t["sample"][ok].to_numpy(), t["line"][ok].to_numpy())
    assert _rms(ts) > 0.3 and _rms(tl) > 0.2  # a field far from zero: a wrong sign could not pass
    assert _rms(t.d_sample[ok] - ts) <= 0.1 and _rms(t.d_line[ok] - tl) <= 0.1
    # Homologous positions: the pan point is where the pan model sees the ground point of the window centre.
    ps, pl = RPCModel.from_file(pan).project(t.lon[ok], t.lat[ok], t.h[ok])
    np.testing.assert_allclose(t.ref_sample[ok], ps, atol=1e-6)
    np.testing.assert_allclose(t.ref_line[ok], pl, atol=1e-6)
    u = cells.usable.to_numpy()
    assert u.sum() >= 14
    cs, cl = true_misregistration(scene, cells["sample"][u].to_numpy(), cells["line"][u].to_numpy())
    assert _rms(cells.d_sample[u] - cs) <= 0.05 and _rms(cells.d_line[u] - cl) <= 0.05
    # Windows straddling the sub-CCD edge (a jump of the field) can be left out of the cell means.
    edges = scene.image("ms").true.camera.edges_in_image()
    assert len(edges) == 1
    by_edge = cells_from_matches(t, 128, 128, cell_px=32, breaks=edges)
    gone = np.abs(t.pred_sample.to_numpy() - edges[0]) < 16
    assert gone.any() and by_edge.n_windows.sum() == (t.status != 5).sum() - (gone & (t.status != 5).to_numpy()).sum()
    u = by_edge.usable.to_numpy()
    cs, cl = true_misregistration(scene, by_edge["sample"][u].to_numpy(), by_edge["line"][u].to_numpy())
    assert _rms(by_edge.d_sample[u] - cs) <= 0.05 and _rms(by_edge.d_line[u] - cl) <= 0.05


@pytest.mark.slow
def test_pan_ms_cells_measure_the_true_misregistration(gf7):
    out, scene = gf7
    cells = pan_ms_cells(str(out / "pan" / "scene.tif"), str(out / "ms" / "scene.tif"), str(out / "dem.tif"),
                         cell_px=32, window_px=32, spacing_px=8)
    assert tuple(cells.columns) == CELL_COLUMNS
    assert len(cells) == 64 and cells.attrs["scale"] == pytest.approx(4.0, rel=0.01)
    # Per cell: the share of texture-less cover (the inside of opaque cloud or of opaque water, 3 px from its
    # edge: a cloud-water boundary is a sharp ground edge both images show, i.e. texture) and of any cover at all.
    ms = scene.image("ms").true
    W, H = ms.size
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    lon, lat, _ = ms.localize_dem(xx, yy, scene.dem)
    wc, ww = cover_weights(scene, lon, lat)
    flat = ndimage.minimum_filter(wc >= 0.99, 7) | ndimage.minimum_filter(ww >= 0.99, 7)

    def per_cell(mask):
        return mask.reshape(H // 32, 32, W // 32, 32).mean(axis=(1, 3)).ravel()

    flat, any_cover = per_cell(flat), per_cell(wc + ww > 0)
    usable = cells.usable.to_numpy()
    assert (flat > 0.5).sum() >= 5 and (any_cover == 0).sum() >= 8
    assert not usable[flat > 0.5].any()
    assert (cells.clear_fraction[flat > 0.5] < 0.5).all()
    clear = any_cover == 0
    assert usable[clear].mean() >= 0.8
    sel = clear & usable
    ts, tl = true_misregistration(scene, cells["sample"][sel].to_numpy(), cells["line"][sel].to_numpy())
    es, el = cells.d_sample[sel] - ts, cells.d_line[sel] - tl
    assert _rms(es) <= 0.05 and _rms(el) <= 0.05, (_rms(es), _rms(el))
    # The sign is METHODS §9's nabla (the misregistration itself is ~0.7 / 0.4 px RMS here).
    assert _rms(ts) > 0.3
    # Every usable cell, partly covered ones included, stays sub-tenth of a pixel on average.
    ts, tl = true_misregistration(scene, cells["sample"][usable].to_numpy(), cells["line"][usable].to_numpy())
    assert _rms(cells.d_sample[usable] - ts) <= 0.06 and _rms(cells.d_line[usable] - tl) <= 0.06
    assert (cells.sigma_sample[usable] > 0).all() and (cells.n[usable] >= 4).all()


def test_cells_from_matches_trims_blunders():
    """Robust cell mean: median + MAD-trimmed mean; a blunder does not move it; sparse cells are not usable."""
    rng = np.random.default_rng(0)
    n = 40
    ps = np.r_[rng.uniform(0, 64, n), rng.uniform(64, 128, 2)]
    pl = rng.uniform(0, 64, n + 2)
    ds = np.r_[0.3 + 0.02 * rng.standard_normal(n), 0.0, 0.0]
    dl = np.r_[-0.2 + 0.02 * rng.standard_normal(n), 0.0, 0.0]
    ds[:3] = 5.0  # blunders
    t = pd.DataFrame({"pred_sample": ps, "pred_line": pl, "d_sample": ds, "d_line": dl, "sigma": 0.02,
                      "status": np.zeros(n + 2, dtype=np.int8), "outlier": False, "flat": 0.0})
    cells = cells_from_matches(t, 128, 64, cell_px=64, min_matches=4)
    assert len(cells) == 2
    c0, c1 = cells.iloc[0], cells.iloc[1]
    assert n - 6 <= c0.n <= n - 3 and c0.usable  # the 3 blunders and at most a few 3-sigma tails
    assert c0.d_sample == pytest.approx(0.3, abs=0.01) and c0.d_line == pytest.approx(-0.2, abs=0.01)
    assert 0.001 < c0.sigma_sample < 0.01
    assert (c0["sample"], c0["line"]) == (32.0, 32.0)
    assert c1.n == 2 and not c1.usable


def test_union_grid_resampling_equals_per_window_and_specs_pickle(gf7_small):
    """Dense windows resampled once on their union grid give the per-window values; a raw-reference tile spec
    travels through pickle (process pools, Dask) and gives the same matches."""
    out, _ = gf7_small
    pan, ms, dem = str(out / "pan" / "scene.tif"), str(out / "ms" / "scene.tif"), DEM.from_user_input(
        str(out / "dem.tif"))
    pm, mm = RPCModel.from_file(pan), RPCModel.from_file(ms)
    ref = RawReference(pan, pm)
    x0 = np.repeat(np.arange(10.0, 80.0, 8.0), 2)
    y0 = np.tile([20.0, 36.0], x0.size // 2)
    shared = reference_on_grids(mm, dem, ref, x0, y0, 32, shared=True)
    each = reference_on_grids(mm, dem, ref, x0, y0, 32)
    assert np.isfinite(shared).all()
    assert np.abs(shared - each).max() < 0.5  # DN of 0-255 texture: geometry nodes differ by < 1e-3 px
    specs, _ = plan_tiles(ms, mm, pan, dem, 16, 32, search_px=8, reference_model=pm, tile_windows=16)
    direct = match_tile(specs[0])
    again = match_tile(pickle.loads(pickle.dumps(specs[0])))
    for k in ("dsample", "dline", "ref_sample", "status"):
        np.testing.assert_array_equal(direct[k], again[k])


def test_bands_at_the_same_windows_share_their_geometry_with_the_same_bits(gf7_small):
    """match_tiles (the unit of match_raw_bands: one tile per band at the same windows, the ground points, footprints
    and the resampled pan once) gives every band exactly what match_tile gives it alone, also through pickle (process
    pools, Dask); tiles at other windows are not grouped."""
    out, _ = gf7_small
    pan, ms = str(out / "pan" / "scene.tif"), str(out / "ms" / "scene.tif")
    dem = DEM.from_user_input(str(out / "dem.tif"))
    pm, mm = RPCModel.from_file(pan), RPCModel.from_file(ms)
    plans = [plan_tiles(ms, mm, pan, dem, 8, 32, search_px=8, reference_model=pm, tile_windows=64, band=b)[0]
             for b in (1, 2, 3, 4)]
    groups = _same_windows([s for p in plans for s in p])
    assert len(groups) == len(plans[0]) and all(len(g) == 4 for g in groups)
    assert [g.index for g in groups][:2] == [(0, len(plans[0]), 2 * len(plans[0]), 3 * len(plans[0])),
                                            (1, len(plans[0]) + 1, 2 * len(plans[0]) + 1, 3 * len(plans[0]) + 1)]
    g = pickle.loads(pickle.dumps(groups[0]))
    assert g.index == groups[0].index
    together = match_tiles(g)
    alone = [match_tile(s) for s in groups[0]]
    assert len(together) == 4 and (alone[0]["status"] == 0).sum() > 20
    assert not np.array_equal(alone[0]["dsample"], alone[1]["dsample"], equal_nan=True)  # the bands differ
    for a, b in zip(alone, together):
        assert list(a) == list(b)
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    other = plan_tiles(ms, mm, pan, dem, 12, 32, search_px=8, reference_model=pm, tile_windows=64, band=2)[0]
    assert len(_same_windows(plans[0] + other)) == len(plans[0]) + len(other)


def test_units_run_largest_first_and_every_band_gets_its_own_results(gf7_small):
    """match_raw_bands runs its units (band groups or tiles) largest first (issue 23: a grid's smaller edge tiles
    last, the threads end together) and puts every unit's results in its tiles' places: each band's table is the
    one match_raw gives that band alone, with 1 or 2 threads."""
    out, _ = gf7_small
    pan, ms = str(out / "pan" / "scene.tif"), str(out / "ms" / "scene.tif")
    dem = DEM.from_user_input(str(out / "dem.tif"))
    pm, mm = RPCModel.from_file(pan), RPCModel.from_file(ms)
    kw = dict(window_px=32, search_px=8, tile_windows=25, margin_px=4, outlier_model=None)
    sizes = [len(s.centers) for s in plan_tiles(ms, mm, pan, dem, 8, 32, search_px=8, reference_model=pm,
                                                tile_windows=25, margin_px=4)[0]]
    assert len(set(sizes)) > 1 and sizes != sorted(sizes, reverse=True)      # the order does change
    for workers in (1, 2):
        together = match_raw_bands(ms, mm, pan, pm, dem, bands=[1, 2, 3], spacing_px=[8, 8, 12], workers=workers,
                                   **kw)
        for b, step in ((1, 8), (2, 8), (3, 12)):
            alone = match_raw(ms, mm, pan, pm, dem, spacing_px=step, band=b, workers=1, **kw)
            assert (alone["status"] == 0).sum() > 20
            pd.testing.assert_frame_equal(together[b], alone)


def test_region_and_no_overlap_errors(gf7_small):
    out, _ = gf7_small
    pan, ms, dem = str(out / "pan" / "scene.tif"), str(out / "ms" / "scene.tif"), str(out / "dem.tif")
    t = match_raw(ms, None, pan, None, dem, spacing_px=16, window_px=32, region=(0, 0, 64, 70), workers=1)
    assert len(t) > 0 and (t.pred_sample <= 64).all() and (t.pred_line <= 70).all()
    assert t.attrs["region"] == (0.0, 0.0, 64.0, 70.0)
    with pytest.raises(Gf4calError, match="outside its overlap"):
        match_raw(ms, None, pan, None, dem, region=(500, 500, 600, 600))
    # A pan RPC that puts the pan 100 km away: no common ground.
    far = RPCModel.from_file(pan)
    far = far.replace(long_off=far.long_off + 1.0)
    with pytest.raises(Gf4calError, match="do not overlap"):
        pan_ms_cells(pan, ms, dem, pan_model=far)
