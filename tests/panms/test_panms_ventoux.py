"""register-pan-ms on the real Pleiades-1B pair over Mont Ventoux as delivered (issue 20): a 500 x 500 pan crop and a
145 x 145 x 4 MS crop, each with its product's own RPC in a .geom beside it and its product origin only in a
pixel-unit geotransform. No option but the DEM: exit 0, and an independent check -- plain normalised cross-correlation
of ms_on_pan.tif against the pan reduced to MS pixels in 64 px windows, not the engine's matcher -- finds red within
0.08 MS px and green within 0.10 MS px of the pan (0.24 / 0.35 px through the RPCs alone)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal import panms
from gdal_gf4cal.dem import DEM
from gdal_gf4cal.crop import image_rpc

DATA = os.path.join(os.path.dirname(__file__), "..", "data")


@pytest.fixture(scope="module")
def pair(ventoux_pair):
    """The crops under their shareloc names, each .geom beside its image."""
    return ventoux_pair


@pytest.fixture(scope="module")
def registered(pair):
    dem = os.path.join(DATA, "dem", "N44E005.hgt")
    proc = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "register-pan-ms", "left_image.tif",
                           "lowres_color_image.tif", "--dem", dem, "--geoid", "egm96", "--out", "out"],
                          capture_output=True, text=True, cwd=pair)
    assert proc.returncode == 0, proc.stderr
    return pair / "out", json.loads((pair / "out" / "report.json").read_text()), proc


def _block_mean(a, r):
    h, w = a.shape[0] // r * r, a.shape[1] // r * r
    return a[:h, :w].reshape(h // r, r, w // r, r).mean(axis=(1, 3))


def _xcorr_shifts(ref, img, win=64, step=16, search=3, min_ncc=0.5):
    """Shift (sample, line) of ``img`` against ``ref`` per ``win`` px window every ``step`` px: plain normalised
    cross-correlation at every integer shift within ``search`` px, parabola through the peak and its neighbours."""
    h, w = ref.shape
    out = []
    for y0 in range(search, h - win - search + 1, step):
        for x0 in range(search, w - win - search + 1, step):
            r = ref[y0:y0 + win, x0:x0 + win]
            r = (r - r.mean()) / r.std()
            c = np.empty((2 * search + 1, 2 * search + 1))
            for i, dy in enumerate(range(-search, search + 1)):
                for j, dx in enumerate(range(-search, search + 1)):
                    m = img[y0 + dy:y0 + dy + win, x0 + dx:x0 + dx + win]
                    c[i, j] = np.mean(r * (m - m.mean()) / m.std())
            i, j = np.unravel_index(np.argmax(c), c.shape)
            if not (0 < i < 2 * search and 0 < j < 2 * search) or c[i, j] < min_ncc:
                continue
            sx = j - search + 0.5 * (c[i, j - 1] - c[i, j + 1]) / (c[i, j - 1] - 2 * c[i, j] + c[i, j + 1])
            sy = i - search + 0.5 * (c[i - 1, j] - c[i + 1, j]) / (c[i - 1, j] - 2 * c[i, j] + c[i + 1, j])
            out.append((sx, sy))
    return np.array(out)


def _planar_rms_per_band(pan_path, image_path, ratio=4):
    p = _block_mean(gdal.Open(str(pan_path)).ReadAsArray().astype(float), ratio)
    ds = gdal.Open(str(image_path))
    out = {}
    for b in range(1, ds.RasterCount + 1):
        m = ds.GetRasterBand(b).ReadAsArray().astype(float)[:p.shape[0], :p.shape[1]]
        d = _xcorr_shifts(p, m)
        out[b] = (float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))), len(d))
    return out


def test_the_pair_as_delivered_registers_every_band(registered, pair):
    out, rep, proc = registered
    after = _planar_rms_per_band(pair / "left_image.tif", out / "ms_on_pan.tif")
    before_path = pair / "ms_on_pan_rpc_only.tif"
    pan_rpc, _ = image_rpc(pair / "left_image.tif")
    ms_rpc, _ = image_rpc(pair / "lowres_color_image.tif")
    dem = DEM.from_user_input(os.path.join(DATA, "dem", "N44E005.hgt"), geoid="egm96")
    panms.resample_ms_on_pan(None, pair / "left_image.tif", pair / "lowres_color_image.tif", before_path,
                             pan_rpc=pan_rpc, ms_rpc=ms_rpc, dem=dem, ratio=4)
    before = _planar_rms_per_band(pair / "left_image.tif", before_path)
    print("planar RMS (MS px) before / after, per band:", {b: (before[b][0], after[b][0]) for b in after})
    assert all(after[b][1] >= 9 for b in (1, 2, 3))             # 16 windows of 64 px on the 125 px grid
    assert before[1][0] > 0.15 and after[1][0] <= 0.08          # red (measured 0.238 -> 0.060)
    assert after[2][0] <= 0.10 and after[2][0] < 0.5 * before[2][0]   # green (0.354 -> 0.042)
    assert after[3][0] < 0.5 * before[3][0]                     # blue (0.283 -> 0.065)
    # what the engine says: a ratio of 4 from the RPCs, both crops placed in their products, every band reported
    assert rep["sizes"]["ratio"] == 4 and rep["sizes"]["ms_on_pan"] == [125, 125]
    assert any("crop at (5000, 5000)" in n for n in rep["notes"]) and any("(1240, 1240)" in n for n in rep["notes"])
    assert [b["band"] for b in rep["bands"]] == [1, 2, 3, 4]
    assert rep["bands"][3].get("spectral") is True and "spectral" in proc.stderr
    assert rep["geometry"]["ray_angle_deg"] < 0.5
    assert rep["breaks_ms_px"] == [] and rep["breaks_from"] == "data"     # no sub-CCD edge in a 145 px crop


def test_outputs_a_gis_places(registered, pair):
    out, rep, _ = registered
    ds = gdal.Open(str(out / "ms_on_pan.tif"))
    assert ds.RasterCount == 4
    # band colours from the product: the .geom's band list "B2 B1 B0 B3" (Pleiades B0 blue ... B3 NIR)
    assert [(ds.GetRasterBand(b).GetDescription(), ds.GetRasterBand(b).GetColorInterpretation())
            for b in range(1, 5)] == [("red", gdal.GCI_RedBand), ("green", gdal.GCI_GreenBand),
                                      ("blue", gdal.GCI_BlueBand), ("nir", gdal.GCI_Undefined)]
    assert ds.GetGeoTransform(can_return_null=True) is None and ds.GetMetadata("RPC")
    # correction.tif carries the MS crop's RPC: GDAL places its centre where the MS RPC (shifted to the crop) does
    c = gdal.Open(str(out / "correction.tif"))
    assert c.GetMetadata("RPC") and c.GetGeoTransform(can_return_null=True) is None
    ms_rpc, _ = image_rpc(pair / "lowres_color_image.tif")
    tr = gdal.Transformer(c, None, ["METHOD=RPC", "RPC_HEIGHT=500"])
    ok, (lon, lat, _) = tr.TransformPoint(0, 72.5, 72.5, 0)
    lon2, lat2 = ms_rpc.localize(np.array([72.5]), np.array([72.5]), np.array([500.0]))
    assert ok and abs(lon - lon2[0]) < 1e-6 and abs(lat - lat2[0]) < 1e-6
    assert 5.1 < lon < 5.3 and 44.1 < lat < 44.3                 # Mont Ventoux
    # ms_on_pan's RPC is the pan crop's at a quarter of its size: the same ground at the same place
    pan_rpc, _ = image_rpc(pair / "left_image.tif")
    tr = gdal.Transformer(ds, None, ["METHOD=RPC", "RPC_HEIGHT=500"])
    ok, (lon, lat, _) = tr.TransformPoint(0, 62.5, 62.5, 0)
    lon2, lat2 = pan_rpc.localize(np.array([250.0]), np.array([250.0]), np.array([500.0]))
    assert ok and abs(lon - lon2[0]) < 1e-6 and abs(lat - lat2[0]) < 1e-6


def test_no_cell_size_or_jitter_count_ends_in_a_solver_failure(pair):
    """``--cell`` 4..128 and ``--jitter`` 0..20 (and 999) on the real pair's matches: every combination solves
    (terms the cells cannot support are dropped with a note; the jitter design never turns NaN), except a fixed
    jitter count beyond the sines the usable cell rows resolve, ``(rows - 4) // 3``: refused, naming the rows and the
    count that would do (auto and counts within it always solve)."""
    from gdal_gf4cal.matching import match_raw
    from gdal_gf4cal.workflows.panms import _cells, _spacing
    pan_rpc, _ = image_rpc(pair / "left_image.tif")
    ms_rpc, _ = image_rpc(pair / "lowres_color_image.tif")
    dem = DEM.from_user_input(os.path.join(DATA, "dem", "N44E005.hgt"), geoid="egm96")
    t = match_raw(str(pair / "lowres_color_image.tif"), ms_rpc, str(pair / "left_image.tif"), pan_rpc, dem,
                  spacing_px=4, window_px=32, search_px=8, band=1, margin_px=4)
    refused = []
    for cell in (4, 6, 8, 16, 32, 64, 128):
        cells = _cells(t, (145, 145), cell, _spacing((145, 145), cell), [])
        rows = np.unique(np.round(cells["line"].to_numpy(float)[cells["usable"].to_numpy(bool)], 3)).size
        for jitter in ("auto", 0, 1, 3, 20, 999):
            try:
                m = panms.estimate(cells, ms_size=(145, 145), breaks=[], jitter=jitter)
            except panms.PanMSError as exc:
                # the rows of the cells left after the blunders; no sine below 8 rows (no band to search)
                got = re.search(r"lie on (\d+) rows .* enough for (\d+) sine", str(exc))
                r, k = (int(got.group(1)), int(got.group(2))) if got else (0, -1)
                assert jitter not in ("auto", 0) and r <= rows and k == (0 if r < 8 else (r - 4) // 3) < jitter, \
                    (cell, jitter, str(exc))
                refused.append((cell, jitter))
                continue
            last = m.steps[-1]
            assert np.isfinite(last["rms_sample_px"]) and np.isfinite(last["rms_line_px"]), (cell, jitter)
            assert last["rms_sample_px"] < 0.1 and last["rms_line_px"] < 0.1, (cell, jitter)
    assert {c for c, j in refused if j == 999} == {4, 6, 8, 16, 32, 64, 128}, refused
