"""The fine level's batches (issue 23): the chunks of windows its passes and measures run in, and the reference side
computed once for the bands of a group, change no bit of the results.

Scenes: matching scenes of tests/matchscene.py (the real SRTM relief under a 384 x 384 raw image rendered through a
true RPC, a biased RPC ~63 px off, water and a painted cloud; a 640 x 640 one ~27 px off), and a rendered GF7 crop
(pan 512^2, MS 128^2).
"""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.dem import DEM
from gdal_gf4cal.matching import collect, correlate, match_tile, plan_tiles
from gdal_gf4cal.matching.collect import match_tiles
from gdal_gf4cal.rpc import RPCModel
from gdal_gf4cal.simulate.gf7 import write_gf7_scene

from matchscene import build_scene, error_affine

ERROR = error_affine(shift=(-50.3, 37.6), rotation_rad=0.002, scale=1.001, center=(192, 192))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return build_scene(tmp_path_factory.mktemp("fine"), texture="pleiades", size=(384, 384), error=ERROR, water=True,
                       clouds=True)


@pytest.fixture(scope="module")
def large(tmp_path_factory):
    return build_scene(tmp_path_factory.mktemp("fine640"), texture="pleiades", size=(640, 640), water=True,
                       error=error_affine(shift=(-20.3, 17.6), rotation_rad=0.002, scale=1.001, center=(320, 320)))


@pytest.fixture(scope="module")
def gf7(tmp_path_factory):
    out = tmp_path_factory.mktemp("gf7fine")
    write_gf7_scene(out, seed=3, size=(512, 512), crop_center_ms_px=2560, n_gcps=10, tile=256)
    return out


def test_chunks_are_balanced_and_cover_every_item_once():
    for n, step in ((0, 4), (1, 4), (5, 4), (6, 4), (288, 256), (384, 256), (1000, 7), (3, 1000)):
        parts = correlate.chunks(n, step)
        got = np.concatenate([np.arange(n)[s] for s in parts]) if parts else np.zeros(0, int)
        np.testing.assert_array_equal(got, np.arange(n))
        sizes = [s.stop - s.start for s in parts]
        assert len(parts) == (max(1, int(n / step + 0.5)) if n else 0)
        assert not sizes or max(sizes) - min(sizes) <= 1
    assert [s.stop - s.start for s in correlate.chunks(288, 256)] == [288]        # one set of calls, not 256 + 32
    assert [s.stop - s.start for s in correlate.chunks(384, 256)] == [192, 192]


@pytest.mark.parametrize("window,spacing", [(64, 40), (256, 48)])
def test_chunk_sizes_change_no_bit(scene, large, monkeypatch, window, spacing):
    """The fine passes, the texture measures and the quarter gradients by one or three windows at a time, or the
    whole tile at once: the same results, bit for bit, as with the default chunks (64-px windows over the coarse
    level; 256-px ones with pilots and probes, some cut by the image's edge)."""
    sc = scene if window == 64 else large
    specs, _ = plan_tiles(sc.image, sc.rpc, sc.reference, sc.dem, spacing, window, search_px=64, margin_px=0)
    ref = [match_tile(s) for s in specs]
    status = np.concatenate([r["status"] for r in ref])
    assert (status == 0).sum() >= 10 and (status != 0).sum() >= 5           # accepted and flagged windows
    for size in (4 * window * window, 3 * 4 * window * window, 1 << 30):
        for mod, name in ((collect, "PASS_BYTES"), (correlate, "_MEASURE_BYTES"), (collect, "QUARTER_BYTES")):
            monkeypatch.setattr(mod, name, size)
        for a, b in zip(ref, [match_tile(s) for s in specs]):
            for k in a:
                np.testing.assert_array_equal(b[k], a[k], err_msg=f"{k} {size}")


def test_bands_of_a_group_compute_the_reference_side_once(gf7, monkeypatch):
    """The bands of a group (match_tiles: one tile per band at the same windows) transform and measure the pan's
    windows once (collect._GroupReference), not once per band: the same bits as each band alone, with 3 of every 4
    reference transforms and quarter gradients saved."""
    pan, ms = str(gf7 / "pan" / "scene.tif"), str(gf7 / "ms" / "scene.tif")
    dem = DEM.from_user_input(str(gf7 / "dem.tif"))
    pm, mm = RPCModel.from_file(pan), RPCModel.from_file(ms)
    group = [plan_tiles(ms, mm, pan, dem, 8, 32, search_px=8, reference_model=pm, tile_windows=64, band=b)[0][0]
             for b in (1, 2, 3, 4)]
    counts = {"spectra": 0, "chunks": 0, "quarters": 0}

    def counted(name, fn):
        def run(*a, **k):
            counts[name] += 1
            return fn(*a, **k)
        return run
    monkeypatch.setattr(collect, "spectra", counted("spectra", collect.spectra))
    monkeypatch.setattr(collect._FinePasses, "_chunk_passes", counted("chunks", collect._FinePasses._chunk_passes))
    monkeypatch.setattr(collect, "_quarter_gradient", counted("quarters", collect._quarter_gradient))
    alone = [match_tile(s) for s in group]
    each = dict(counts)
    counts.update(spectra=0, chunks=0, quarters=0)
    together = match_tiles(group)
    assert (alone[0]["status"] == 0).sum() > 20
    assert not np.array_equal(alone[0]["dsample"], alone[1]["dsample"], equal_nan=True)    # the bands differ
    for a, b in zip(alone, together):
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    # every chunk transforms its raw windows, and (alone) its reference windows: together, those once per group
    assert counts["chunks"] == each["chunks"] and each["chunks"] % 4 == 0
    assert counts["spectra"] == each["spectra"] - 3 * each["chunks"] // 4
    # the reference's quarter gradients once, not per band; the raw side's not at all (32-px windows: quarters too
    # small to tell a change from a cover, every textured one is judged)
    assert each["quarters"] == 4 and counts["quarters"] == 1


def test_flat_share_spares_the_partial_sort_of_textured_windows_with_the_same_bits(scene, monkeypatch):
    """The flat test's threshold is min(0.05 x the local energy's 90th percentile, 3 sigma^2): where the percentile
    is surely above 60 sigma^2 (textured windows, most) it is not computed (np.partition holds the GIL: 170 us of a
    256-px window's 725), and the measures are the same bits as with every percentile computed; the percentiles
    computed are those of np.percentile."""
    from osgeo import gdal
    img = gdal.Open(scene.image).ReadAsArray().astype(np.float32)
    wins = np.stack([img[y:y + 64, x:x + 64] for y in range(0, 320, 40) for x in range(0, 320, 40)])
    rng = np.random.default_rng(2)
    half = wins[:2].copy()
    half[:, :, 8:] = 7.0 + rng.normal(0, 0.01, (2, 64, 56))                  # water over most of the window
    wins = np.concatenate([wins, half, np.zeros((1, 64, 64), np.float32)])
    spared = []
    real = correlate._percentile90

    def seen(inner, bound=None):
        level = real(inner, bound)
        spared.append(np.isinf(level))
        exact = real(inner)
        np.testing.assert_array_equal(level[~np.isinf(level)], exact[~np.isinf(level)])
        assert np.all(exact[np.isinf(level)] >= bound[np.isinf(level)])
        np.testing.assert_allclose(exact, np.percentile(inner, 90, axis=-1), rtol=1e-6)
        return level
    monkeypatch.setattr(correlate, "_percentile90", seen)
    fast = correlate.window_measures(wins, (16, 48))
    spared = np.concatenate(spared)
    assert 0 < spared.sum() < spared.size          # textured windows spared, the flat and zero ones not
    monkeypatch.setattr(correlate, "_percentile90", lambda inner, bound=None: real(inner))
    every = correlate.window_measures(wins, (16, 48))
    for f, e in zip(fast, every):
        np.testing.assert_array_equal(f, e)
    assert fast[1][-1] == 1.0 and np.all(fast[1][-3:-1] > 0.9) and np.median(fast[1][:-3]) < 0.1
