"""collect_gcps on rendered scenes with a known systematic RPC error (issue 7 "Must show").

Scenes (tests/test_matching_scene.py): real SRTM relief (Mont Ventoux), a reference orthophoto in UTM 31N, the raw
image rendered through the true RPC, and a biased RPC = true RPC + image-space affine error of ~50-60 px.
Truth of a GCP: ``true_rpc.project(lon, lat, h)``.
"""
from __future__ import annotations

import concurrent.futures as cf
import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal.errors import CancelledError, Gf4calError
from gdal_gf4cal.gcp import read_gcps, write_gcps
from gdal_gf4cal.matching import collect_gcps, match_tile, plan_tiles

from matchscene import build_scene, error_affine

SIZE = (384, 384)
# Biased RPC predicts E(true): the matcher must find offsets of ~(+50.3, -37.6) px (62.8 px) plus rotation/scale.
ERROR = error_affine(shift=(-50.3, 37.6), rotation_rad=0.002, scale=1.001, center=(192, 192))


def _errors(g, scene):
    ts, tl = scene.truth(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    return g["sample"].to_numpy() - ts, g["line"].to_numpy() - tl


def _kept_fraction(g):
    """Accepted inliers over the windows that can be matched: all but those whose ground is outside the image
    (the RPC error moves ~60 px of the grid's edge out of the picture) or with no data."""
    w = g.attrs["windows"]
    matchable = w["total"] - w["outside_image"] - w["nodata"]
    return (len(g) - w["outliers"]) / matchable


@pytest.fixture(scope="module")
def builtin_scene(tmp_path_factory):
    return build_scene(tmp_path_factory.mktemp("builtin"), texture="builtin", size=SIZE, error=ERROR)


@pytest.fixture(scope="module")
def pleiades_scene(tmp_path_factory):
    return build_scene(tmp_path_factory.mktemp("pleiades"), texture="pleiades", size=SIZE, error=ERROR, seed=1)


@pytest.mark.parametrize("scene_name", ["builtin_scene", "pleiades_scene"])
def test_accuracy_and_yield_with_large_initial_offset(scene_name, request):
    sc = request.getfixturevalue(scene_name)
    g = collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, spacing_px=40, window_px=64, workers=1)
    es, el = _errors(g, sc)
    ok = ~g["outlier"].to_numpy()
    # The initial offsets really are large: > 50 px everywhere.
    assert np.all(np.hypot(g["dsample"], g["dline"]) > 50)
    rms = np.sqrt(np.mean(es[ok] ** 2 + el[ok] ** 2))
    assert rms <= 0.1, rms
    assert np.max(np.hypot(es[ok], el[ok])) < 0.25
    assert _kept_fraction(g) >= 0.95, g.attrs["windows"]
    assert len(g) >= 30
    # Schema and quality columns, GDAL convention (sample/line are where the ground truly is).
    for col in ("id", "lon", "lat", "h", "sample", "line", "role", "sigma", "peak", "peak_ratio", "precision_px",
                "outlier"):
        assert col in g.columns
    assert set(g["role"]) == {"control"}
    assert np.all(g["peak"] > 0.5) and np.all(g["peak_ratio"] > 2)
    # Precision estimates are small like the actual errors (not an order of magnitude off).
    assert 0.002 < np.median(g["precision_px"]) < 0.1


def test_clouds_and_water_give_no_gcps(tmp_path):
    sc = build_scene(tmp_path, texture="builtin", size=SIZE, error=ERROR, water=True, clouds=True, seed=2)
    assert sc.cloud_mask.mean() > 0.05 and sc.water_mask.mean() > 0.03
    g = collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, spacing_px=32, window_px=64, workers=1)
    w = g.attrs["windows"]
    assert w["featureless"] + w["cloud_or_change"] + w["weak_correlation"] >= 6
    es, el = _errors(g, sc)
    ts = np.clip(np.round(g["sample"].to_numpy() - es - 0.5).astype(int), 0, SIZE[0] - 1)
    tl = np.clip(np.round(g["line"].to_numpy() - el - 0.5).astype(int), 0, SIZE[1] - 1)
    # No GCP (accepted, outlier or not) lies on a painted cloud or on water; a point within 2 px of a shore is a
    # shoreline point (the rendered mask itself is only defined to a pixel), hence the erosion.
    from scipy import ndimage
    inside = ndimage.binary_erosion(sc.cloud_mask | sc.water_mask, iterations=2)
    assert not np.any(inside[tl, ts])
    ok = ~g["outlier"].to_numpy()
    assert np.sqrt(np.mean(es[ok] ** 2 + el[ok] ** 2)) <= 0.1
    # Windows clear of both masks are still kept.
    near = ndimage.binary_dilation(sc.cloud_mask | sc.water_mask, iterations=40)
    specs, _ = plan_tiles(sc.image, sc.rpc, sc.reference, sc.dem, 32, 64)
    res = [match_tile(s) for s in specs]
    st = np.concatenate([r["status"] for r in res])
    # Where each window's ground point truly is (rejected windows have no trustworthy offset).
    cs, cl = sc.truth(*(np.concatenate([r[k] for r in res]) for k in ("lon", "lat", "h")))
    clear = (st != 5) & np.isfinite(cs)
    ci = np.clip(np.nan_to_num(cs).astype(int), 0, SIZE[0] - 1)
    cj = np.clip(np.nan_to_num(cl).astype(int), 0, SIZE[1] - 1)
    clear &= ~near[cj, ci]
    assert clear.sum() >= 10
    assert np.mean(st[clear] == 0) >= 0.95


def test_offset_beyond_search_range_needs_the_coarse_level(builtin_scene):
    sc = builtin_scene
    g = collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, spacing_px=64, window_px=64, search_px=8, workers=1)
    # Without a coarse level nothing near a 60 px offset is found: windows are rejected, not guessed.
    es, el = _errors(g, sc)
    assert len(g) == 0 or np.all(np.hypot(es, el)[~g["outlier"].to_numpy()] < 0.3)
    assert g.attrs["windows"]["weak_correlation"] >= 0.8 * (g.attrs["windows"]["total"]
                                                             - g.attrs["windows"]["outside_image"])


def test_finer_reference_in_another_crs_with_overviews(builtin_scene, tmp_path):
    """'Any GDAL raster, any CRS, any resolution': the reference warped to EPSG:4326 at ~1/3 of the raw GSD,
    with overviews, gives the same accuracy (decimated reads + low-pass)."""
    sc = builtin_scene
    ref = str(tmp_path / "ref_4326.tif")
    subprocess.run(["gdalwarp", "-q", "-t_srs", "EPSG:4326", "-tr", "0.00012", "0.00009", "-r", "cubic",
                    "-ot", "Float32", sc.reference, ref], check=True)
    subprocess.run(["gdaladdo", "-q", "-r", "average", ref, "2", "4"], check=True)
    g = collect_gcps(sc.image, sc.rpc, ref, sc.dem, spacing_px=48, window_px=64, workers=1)
    es, el = _errors(g, sc)
    ok = ~g["outlier"].to_numpy()
    assert ok.sum() >= 20
    assert np.sqrt(np.mean(es[ok] ** 2 + el[ok] ** 2)) <= 0.1
    assert _kept_fraction(g) >= 0.95


def test_parallel_executors_and_picklable_tiles(builtin_scene):
    sc = builtin_scene
    kw = dict(spacing_px=64, window_px=64, tile_windows=4)
    a = collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, workers=1, **kw)
    b = collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, workers=2, **kw)
    with cf.ThreadPoolExecutor(2) as ex:
        c = collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, executor=ex, **kw)
    for other in (b, c):
        np.testing.assert_array_equal(a["sample"].to_numpy(), other["sample"].to_numpy())
        np.testing.assert_array_equal(a["line"].to_numpy(), other["line"].to_numpy())
    specs, _ = plan_tiles(sc.image, sc.rpc, sc.reference, sc.dem, 64, 64, tile_windows=4)
    assert len(specs) > 1
    r1 = match_tile(specs[0])
    r2 = match_tile(pickle.loads(pickle.dumps(specs[0])))
    np.testing.assert_array_equal(r1["dsample"], r2["dsample"])


def test_progress_cancel_and_output_file(builtin_scene, tmp_path):
    sc = builtin_scene
    seen = []
    g = collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, spacing_px=96, window_px=64, workers=1,
                     progress=lambda f, m: seen.append(f))
    assert seen[0] == 0.0 and seen[-1] == 1.0 and seen == sorted(seen)
    out = write_gcps(g, tmp_path / "gcps.gpkg")
    back = read_gcps(out)
    np.testing.assert_allclose(back["sample"], g["sample"])
    import geopandas as gpd
    layer = gpd.read_file(out)
    assert "outlier" in layer.columns and "precision_px" in layer.columns and "peak_ratio" in layer.columns

    def cancel(f, m):
        if f > 0:
            raise CancelledError("stop")
    with pytest.raises(CancelledError):
        collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, spacing_px=96, window_px=64, workers=1,
                     tile_windows=1, progress=cancel)


def test_nodata_in_raw_image_is_skipped(builtin_scene, tmp_path):
    sc = builtin_scene
    img = str(tmp_path / "holes.tif")
    gdal.Translate(img, sc.image)
    ds = gdal.Open(img, gdal.GA_Update)
    ds.GetRasterBand(1).WriteArray(np.zeros((200, 384), dtype=np.uint16), 0, 0)  # top half: no data
    ds = None
    g = collect_gcps(img, sc.rpc, sc.reference, sc.dem, spacing_px=48, window_px=64, workers=1)
    assert g.attrs["windows"]["nodata"] >= 10
    assert len(g) > 0 and np.all(g["line"] > 200 + 32 - 1)


def test_bad_inputs_raise_clear_errors(builtin_scene, tmp_path):
    sc = builtin_scene
    with pytest.raises(Gf4calError, match="reference not found"):
        collect_gcps(sc.image, sc.rpc, tmp_path / "nope.tif", sc.dem)
    with pytest.raises(Gf4calError, match="window"):
        collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, window_px=15)
    nogeo = str(tmp_path / "nogeo.tif")
    gdal.Translate(nogeo, sc.image)
    with pytest.raises(Gf4calError, match="geotransform|CRS"):
        collect_gcps(sc.image, sc.rpc, nogeo, sc.dem)
    with pytest.raises(Gf4calError, match="too small"):
        collect_gcps(sc.image, sc.rpc, sc.reference, sc.dem, window_px=400)


def test_half_pixel_oscillation_keeps_offset_and_correlation_consistent(tmp_path):
    """A window whose offset is ~k + 0.5 px can make the fine level jump back and forth (|residual| > 0.5 on each
    side). The offset reported must be the one the last correlation was measured at: before the fix the last
    jump was applied after the last correlation, so this seeded scene had one accepted window 1.0 px off."""
    sc = build_scene(tmp_path, texture="builtin", size=(256, 256), error=error_affine(shift=(-20.5, 13.5)),
                     noise=0.1, seed=1)
    specs, _ = plan_tiles(sc.image, sc.rpc, sc.reference, sc.dem, 12, 64)
    res = [match_tile(s) for s in specs]
    cat = {k: np.concatenate([r[k] for r in res]) for k in ("status", "lon", "lat", "h", "center_sample",
                                                            "center_line", "dsample", "dline")}
    ok = cat["status"] == 0
    assert ok.sum() >= 100
    ts, tl = sc.truth(cat["lon"][ok], cat["lat"][ok], cat["h"][ok])
    err = np.hypot(cat["center_sample"][ok] + cat["dsample"][ok] - ts, cat["center_line"][ok] + cat["dline"][ok] - tl)
    assert err.max() < 0.25, np.sort(err)[-3:]


def test_image_rewritten_at_the_same_path_is_reread(builtin_scene, tmp_path):
    """Workers cache open datasets per thread; a long-lived process (QGIS) that rewrites the image at the same
    path and matches again must see the new pixels, not the old file through a stale handle."""
    sc = builtin_scene
    img = str(tmp_path / "raw.tif")
    gdal.Translate(img, sc.image)
    specs, _ = plan_tiles(img, sc.rpc, sc.reference, sc.dem, 96, 64, tile_windows=4)
    first = match_tile(specs[0])
    assert np.any(first["status"] == 0)
    blank = str(tmp_path / "blank.tif")
    gdal.Translate(blank, sc.image, scaleParams=[[0, 65535, 0, 0]])  # all zero = no data
    os.replace(blank, img)
    again = match_tile(specs[0])
    assert np.all(again["status"] == 1), again["status"]


def test_pilot_probes_start_every_window_where_the_full_pilots_would(tmp_path, monkeypatch):
    """Without a coarse level (128-px windows, 8 px of search) the pilots of a tile are first probed on 2 x 2
    block means; when the probes agree every window starts at their prediction. The accepted GCPs are the same
    bits as with full-size pilot passes (the probe only picks where the full-size pass starts), they are as
    accurate against the truth, and the windows needing a second full-size pass (the pilots' from offset 0) are
    gone: the offsets here are ~(+2.6, -1.7) px, so every pilot started at 0 moved."""
    from gdal_gf4cal.matching import collect
    sc = build_scene(tmp_path, texture="builtin", size=(384, 384), error=error_affine(shift=(-2.6, 1.7)), seed=2)
    specs, _ = plan_tiles(sc.image, sc.rpc, sc.reference, sc.dem, 16, 128, search_px=8)
    assert specs[0].factor == 1 and specs[0].centers.shape[0] == 64
    calls = []
    real = collect.correlate_spectra

    def counted(F, G, sigma):
        calls.append(F.S.shape[0])
        return real(F, G, sigma)

    monkeypatch.setattr(collect, "correlate_spectra", counted)
    runs = {}
    for name, probe in (("probe", collect.PROBE_MIN_PX), ("full", 10 ** 6)):
        monkeypatch.setattr(collect, "PROBE_MIN_PX", probe)
        calls.clear()
        runs[name] = match_tile(specs[0]), sum(calls)
    (r_p, n_p), (r_f, n_f) = runs["probe"], runs["full"]
    ok = r_f["status"] == 0
    assert ok.sum() >= 60
    np.testing.assert_array_equal(r_p["status"], r_f["status"])
    for k in ("dsample", "dline", "peak", "peak_ratio", "ncc", "precision_px", "texture"):
        np.testing.assert_array_equal(r_p[k][ok], r_f[k][ok])
    ts, tl = sc.truth(r_p["lon"][ok], r_p["lat"][ok], r_p["h"][ok])
    err = np.hypot(r_p["center_sample"][ok] + r_p["dsample"][ok] - ts, r_p["center_line"][ok] + r_p["dline"][ok] - tl)
    assert err.max() < 0.1, np.sort(err)[-3:]
    # 64 windows: full pilots take 64 + 16 correlations (the 16 pilots twice), probes 64 and a few.
    assert n_f >= 80 and n_p <= 68, (n_p, n_f)


_HEAP_PROBE = """
import json, resource, sys
import numpy as np
from gdal_gf4cal import executors
from gdal_gf4cal.matching import run_tiles

def faults(_=None):
    # A tile's pattern: two stacks of 2 MB alive at once, then freed (windows and their spectra).
    r = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        a = np.ones(1 << 18)
        b = np.ones(1 << 18)
        del a, b
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r

before = faults()
in_tiles = run_tiles([0, 1, 2], workers=1, fn=faults)
print(json.dumps({"before": before, "in_tiles": in_tiles, "set": executors._heap["set"]}))
"""


def _huge_pages_always() -> bool:
    """Transparent huge pages for every mapping (then the heap grows by 2 MB pages: few faults either way)."""
    try:
        return "[always]" in Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc thresholds")
@pytest.mark.parametrize("env", [False, True])
def test_tiles_keep_their_stacks_on_the_heap(env):
    """Tiles run after executors.keep_heap: glibc's defaults page-fault every 2 MB stack in afresh (a fault per
    4 KB page, ~20,000 for this pattern); then, after the first tile, none. Thresholds the environment sets are
    left alone (then they are what keeps the stacks on the heap)."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    if env:
        environ.update(MALLOC_TRIM_THRESHOLD_="67108864", MALLOC_MMAP_THRESHOLD_="33554432")
    r = subprocess.run([sys.executable, "-c", _HEAP_PROBE], capture_output=True, text=True, env=environ, check=True)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    if not env and not _huge_pages_always():
        assert out["before"] > 10000, out      # the cost keep_heap removes (else this test proves nothing)
    assert out["set"] is not env
    assert max(out["in_tiles"][1:]) < 50, out


@pytest.mark.parametrize("n, w", [(1, 128), (5, 192), (16, 256)])
def test_probe_means_are_the_bits_of_numpys_block_mean(n, w):
    """The pilots' 2 x 2 block means (_means_2x2: four whole-stack additions) are the bits of NumPy's mean over the
    two length-2 axes, which sums each block's row pairs, then their sums; another order (row by row) differs in
    about a quarter of the blocks, so the probes (and every window's start) would change."""
    from gdal_gf4cal.matching.collect import _means_2x2
    rng = np.random.default_rng(n)
    v = (rng.normal(size=(n, w, w)) * 10.0 ** rng.uniform(-3, 4)).astype(np.float32)
    h = w // 2
    ref = v.reshape(n, h, 2, h, 2).mean(axis=(2, 4))
    got = _means_2x2(v)
    assert got.dtype == ref.dtype == np.float32 and np.array_equal(got, ref)
    rowwise = ((v[:, 0::2, 0::2] + v[:, 0::2, 1::2]) + v[:, 1::2, 0::2]) + v[:, 1::2, 1::2]
    assert not np.array_equal(rowwise * np.float32(0.25), ref)      # the order matters on these values
