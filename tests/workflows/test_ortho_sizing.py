"""``gf4cal ortho`` refuses, before writing, what cannot make an ortho, and says why in one line (issue 19 items 7,
9): a geocentric or far-away output CRS, a resolution coarser than the footprint or beyond the size limit, a DEM
without a height over the scene, a full disk; a killed run's hidden temporary is removed by the next run.

The scene: the real Ventoux Pleiades crop geometry (500 x 500 px at product pixel (5000, 5000), pixel-unit
geotransform without CRS) with the product's real OSSIM .geom and the real SRTM tile above EGM96 (tests/data)."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from osgeo import gdal, osr

from gdal_gf4cal.outputs import OutputSet, check_raster, raster_has_data
from gdal_gf4cal.errors import Gf4calError

ROOT = Path(__file__).parents[2]
DATA = ROOT / "tests" / "data"
GEOM = DATA / "rpc" / "ventoux_left_image.geom"
SRTM = DATA / "dem" / "N44E005.hgt"
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))


def gf4cal(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", *map(str, args)], capture_output=True, text=True,
                          env=ENV, timeout=timeout)


@pytest.fixture(scope="module")
def crop(tmp_path_factory):
    path = tmp_path_factory.mktemp("crop") / "left_image.tif"
    ds = gdal.GetDriverByName("GTiff").Create(str(path), 500, 500, 1, gdal.GDT_UInt16)
    ds.SetGeoTransform((5000.0, 1.0, 0.0, 5000.0, 0.0, 1.0))
    noise = np.random.default_rng(19).integers(1, 4096, (500, 500))      # incompressible: fills a small disk
    ds.GetRasterBand(1).WriteArray(noise.astype(np.uint16))
    ds = None
    return path


def ortho_args(crop, out, *extra, dem=SRTM, geoid="egm96"):
    return ["ortho", crop, "--rpc", GEOM, "--dem", dem, "--geoid", geoid, "--out", out, *extra]


def assert_one_line_refusal(res, words, folder):
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2, res.stderr
    assert len(lines) == 1 and lines[0].startswith("gf4cal: error: ") and words in lines[0], res.stderr
    assert os.listdir(folder) == [], os.listdir(folder)          # nothing written, no temporary left


@pytest.mark.parametrize("extra, words", [
    (["--crs", "EPSG:4978"], "is geocentric"),
    (["--crs", "EPSG:5773"], "not a horizontal"),
    (["--crs", "EPSG:32760"], "made for another part of the Earth"),
    (["--res", "1e6"], "coarser than the scene's footprint"),
    (["--crs", "EPSG:4326", "--res", "0.5"], "coarser than the scene's footprint"),
], ids=["geocentric", "vertical", "utm60s", "res1e6", "deg"])
def test_output_that_cannot_hold_the_ortho_is_refused(tmp_path, crop, extra, words):
    assert_one_line_refusal(gf4cal(*ortho_args(crop, tmp_path / "out" / "o.tif", *extra)), words, tmp_path)


def test_huge_resolution_refused_before_writing_naming_size_limit_and_force(tmp_path, crop):
    t0 = time.perf_counter()
    res = gf4cal(*ortho_args(crop, tmp_path / "o.tif", "--res", "0.0005"))
    assert time.perf_counter() - t0 < 60
    assert_one_line_refusal(res, "more than the limit of 4e+09 px", tmp_path)
    assert "x" in res.stderr and "--force" in res.stderr and "at --res 0.0005" in res.stderr


def test_dem_without_height_over_the_scene_is_named(tmp_path, crop):
    dem = tmp_path / "dem" / "far.tif"
    dem.parent.mkdir()
    ds = gdal.GetDriverByName("GTiff").Create(str(dem), 20, 20, 1, gdal.GDT_Float32)
    ds.SetGeoTransform((10.0, 0.05, 0.0, 51.0, 0.0, -0.05))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    ds.SetSpatialRef(srs)
    ds.GetRasterBand(1).Fill(100.0)
    ds = None
    out = tmp_path / "out"
    out.mkdir()
    res = gf4cal(*ortho_args(crop, out / "o.tif", dem=dem, geoid="none"))
    assert_one_line_refusal(res, "the DEM far.tif has no height over the scene", out)


def test_ortho_is_written_and_has_data(tmp_path, crop):
    res = gf4cal(*ortho_args(crop, tmp_path / "o.tif"))
    assert res.returncode == 0, res.stderr
    assert [line for line in res.stderr.splitlines() if not line.startswith("gf4cal: note: ")] == []
    ds = gdal.Open(str(tmp_path / "o.tif"))
    assert raster_has_data(ds)


def test_empty_raster_is_an_error(tmp_path):
    """The backstop every raster output can declare: a raster without a valid pixel fails the run."""
    out = tmp_path / "empty.tif"
    outs = OutputSet([], overwrite=False)
    tmp = outs.declare("r", out, check=check_raster(require_data=True, empty_reason="the test's reason"))
    with pytest.raises(Gf4calError, match="without a single valid pixel: the test's reason"):
        with outs:
            gdal.GetDriverByName("GTiff").Create(tmp, 64, 64, 1, gdal.GDT_Byte)   # all 0, GDAL's warp fill
    assert os.listdir(tmp_path) == []


@pytest.fixture()
def small_tmpfs(tmp_path):
    """A real full disk: a 200 KB tmpfs (root only; skipped where mounting is not permitted)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a small tmpfs here (not root)")
    yield mnt
    subprocess.run(["umount", str(mnt)], capture_output=True)


def test_full_disk_is_one_line_naming_it(small_tmpfs, crop):
    res = gf4cal(*ortho_args(crop, small_tmpfs / "o.tif"))
    assert_one_line_refusal(res, "the disk is full", small_tmpfs)


def test_full_disk_geopackage_writes_no_gdal_line(small_tmpfs):
    """The residual GeoPackage (OGR/SQLite) on a full disk: our line only, no ``ERROR 1: sqlite3_exec``."""
    code = ("import numpy as np, pandas as pd, sys\n"
            "from gdal_gf4cal.report import write_residuals_gpkg\n"
            "n = 2000\n"
            "t = pd.DataFrame({'id': [f'p{i}' for i in range(n)], 'lon': np.linspace(5, 5.1, n),"
            " 'lat': np.linspace(44, 44.1, n), 'h': 500.0, 'sample': np.arange(n) * 1.0, 'line': np.arange(n) * 1.0,"
            " 'role': 'control', 'res_sample_after': 0.1, 'res_line_after': 0.2})\n"
            "from gdal_gf4cal.cli import main\n"
            f"write_residuals_gpkg(t, {str(small_tmpfs / 'r.gpkg')!r})\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert res.returncode != 0
    assert "ERROR 1" not in res.stderr and "disk is full" in res.stderr.splitlines()[-1], res.stderr


def test_killed_run_temporary_removed_by_the_next_run(tmp_path, crop):
    out = tmp_path / "o.tif"
    code = ("import os, signal\nfrom gdal_gf4cal.outputs import OutputSet\n"
            f"outs = OutputSet([]); tmp = outs.declare('ortho', {str(out)!r})\n"
            "outs.__enter__(); open(tmp, 'wb').write(b'half an ortho')\n"
            "os.kill(os.getpid(), signal.SIGKILL)\n")
    subprocess.run([sys.executable, "-c", code], env=ENV, timeout=60)
    left = [n for n in os.listdir(tmp_path) if n.startswith(".gf4cal-")]
    assert len(left) == 1 and left[0].endswith("-o.tif")
    alive = tmp_path / f".gf4cal-{os.getpid()}x0a0b0c-o.tif"     # a running process's temporary: kept
    alive.write_bytes(b"in progress")
    res = gf4cal(*ortho_args(crop, out))
    assert res.returncode == 0, res.stderr
    assert sorted(os.listdir(tmp_path)) == sorted(["o.tif", alive.name])


def test_rpc_of_other_pixels_is_named(tmp_path):
    """An RPC whose image lies 50,000 scales away from the image's pixels (none of its border localises)."""
    from gdal_gf4cal import RPCModel
    far = RPCModel.from_file(GEOM).replace(samp_off=5e7, samp_scale=1000.0)
    rpb = far.write_rpb(tmp_path / "far.RPB")
    img = tmp_path / "plain.tif"
    ds = gdal.GetDriverByName("GTiff").Create(str(img), 64, 64, 1, gdal.GDT_Byte)
    ds.GetRasterBand(1).Fill(7)
    ds = None
    out = tmp_path / "out"
    out.mkdir()
    res = gf4cal("ortho", img, "--rpc", rpb, "--dem", SRTM, "--geoid", "egm96", "--out", out / "o.tif")
    assert_one_line_refusal(res, "the RPC cannot localise the image's border (64 x 64 px)", out)
