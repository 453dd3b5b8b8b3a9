"""``gf4cal collect-gcps`` and the end-to-end chain collect -> refine -> gdalwarp -rpc -> ortho vs reference."""
from __future__ import annotations

import math
import subprocess
import sys
import warnings

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal.cli import main
from gdal_gf4cal.gcp import read_gcps
from gdal_gf4cal.matching import collect_gcps
from gdal_gf4cal.matching.collect import DEFAULT_SPACING_PX, MIN_WINDOWS_ACROSS, default_spacing
from gdal_gf4cal.matching.correlate import phase_correlate

import ventouxpair
from matchscene import build_scene, error_affine

SIZE = (320, 320)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli")
    # Shift + scale + a small rotation: an affine error, ~55 px.
    sc = build_scene(folder, texture="pleiades", size=SIZE, seed=3,
                     error=error_affine(shift=(42.2, -35.4), rotation_rad=0.0015, scale=0.9985, center=(160, 160)))
    sc.rpc.write_rpb(str(folder / "raw.RPB"))  # the biased RPC travels with the image, as in a product
    return sc


def test_cli_writes_gcps_that_refine_reads(scene, tmp_path, capsys):
    out = tmp_path / "gcps.gpkg"
    rc = main([("collect-gcps"), scene.image, "--reference", scene.reference, "--dem", scene.dem_path,
               "--out", str(out), "--spacing", "40", "--window", "64", "--workers", "1"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "wrote" in text and "windows" in text
    g = read_gcps(out)  # the project's reader accepts it (schema, GDAL convention)
    import geopandas as gpd
    assert len(g) >= 25 and not gpd.read_file(out)["outlier"].any()  # inliers only by default
    ts, tl = scene.truth(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    assert np.sqrt(np.mean((g["sample"] - ts) ** 2 + (g["line"] - tl) ** 2)) <= 0.1
    # Existing output: refused, one line, exit 2.
    assert main(["collect-gcps", scene.image, "--reference", scene.reference, "--dem", scene.dem_path,
                 "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err


def test_cli_bad_input_is_one_line(scene, tmp_path):
    r = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "collect-gcps", scene.image, "--reference",
                        str(tmp_path / "missing.tif"), "--dem", scene.dem_path, "--out", str(tmp_path / "g.gpkg")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "reference not found" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.slow
def test_end_to_end_collect_refine_orthorectify(scene, tmp_path):
    """collect -> refine (affine, gdal_gf4cal.compensation) -> gdalwarp -rpc with the refined RPC: the
    orthoimage matches the reference within 0.2 px (phase correlation), while the biased RPC is ~50 px off."""
    from gdal_gf4cal.workflows import refine_rpc
    from gdal_gf4cal.gcp import write_gcps
    from gdal_gf4cal.matching import collect_gcps
    g = collect_gcps(scene.image, None, scene.reference, scene.dem, spacing_px=32, window_px=64, workers=1)
    g = g[~g["outlier"].to_numpy(bool)]
    gpath = write_gcps(g, tmp_path / "gcps.gpkg")
    vrt = str(tmp_path / "refined.vrt")
    rep = refine_rpc(scene.image, gpath, "affine", out=vrt, dem=scene.dem_path)
    assert rep["control"]["after"]["sample"]["rms"] < 0.1

    ref = gdal.Open(scene.reference)
    gt = ref.GetGeoTransform()
    te = [str(gt[0]), str(gt[3] + gt[5] * ref.RasterYSize), str(gt[0] + gt[1] * ref.RasterXSize), str(gt[3])]
    refarr = ref.ReadAsArray().astype(float)

    def ortho(src, name):
        out = str(tmp_path / name)
        subprocess.run(["gdalwarp", "-q", "-rpc", "-to", f"RPC_DEM={scene.dem_path}", "-t_srs", "EPSG:32631",
                        "-te", *te, "-ts", str(ref.RasterXSize), str(ref.RasterYSize), "-r", "cubic",
                        "-dstnodata", "0", src, out], check=True)
        return gdal.Open(out).ReadAsArray().astype(float)

    def shifts(o):
        # 96-px windows on a grid over the orthoimage's valid area.
        wins_r, wins_o = [], []
        for y in range(60, o.shape[0] - 156, 48):
            for x in range(60, o.shape[1] - 156, 48):
                a, b = refarr[y:y + 96, x:x + 96], o[y:y + 96, x:x + 96]
                if np.all(b > 0):
                    wins_r.append(a)
                    wins_o.append(b)
        r = phase_correlate(np.array(wins_r), np.array(wins_o))
        return r, len(wins_r)

    before, n0 = shifts(ortho(scene.image, "ortho_before.tif"))      # image + biased .RPB
    after, n1 = shifts(ortho(vrt, "ortho_after.tif"))                  # VRT carrying the refined RPC
    assert n1 >= 9
    assert np.median(np.hypot(before.dx, before.dy)) > 10 or np.median(before.peak) < 0.3
    err = np.hypot(after.dx, after.dy)
    assert np.all(after.ncc > 0.8)
    assert np.max(err) <= 0.2, err


@pytest.mark.parametrize("size, window, spacing", [((10240, 10240), 64, 256), ((1920, 2500), 64, 256),
                                                    ((1024, 1024), 64, 128), ((4000, 1000), 32, 133),
                                                    ((500, 500), 64, 64), ((200, 200), 64, 64)])
def test_default_spacing_puts_eight_windows_across_small_images(size, window, spacing):
    """Without --spacing: 256 px on a scene, finer on a crop (eight windows across its shorter side, the most
    the span between the margins holds at that step), never closer than a window."""
    assert default_spacing(*size, window) == spacing
    span = min(size) - 2 * window                     # centres lie a window from the edges (half a window margin)
    across = span // spacing + 1
    assert across >= MIN_WINDOWS_ACROSS or spacing in (window, DEFAULT_SPACING_PX)


def test_cli_default_grid_finds_gcps_on_a_real_crop(tmp_path, capsys):
    """The real Pleiades Ventoux left crop (500 x 500 px, its own .geom) against an ortho of the right crop of the
    stereo pair, on SRTM above EGM96, as a user runs it: no --spacing. The old default step (256 px) laid 4 windows
    on it and wrote one or two GCPs; the default grid is 64 px, 36 windows, several GCPs."""
    left, right = ventouxpair.pair(tmp_path)
    ref = tmp_path / "right_ortho.tif"
    assert main(["ortho", str(right), *ventouxpair.dem_args(), "--out", str(ref)]) == 0
    capsys.readouterr()
    counts = {}
    for name, extra in (("default", []), ("256", ["--spacing", "256"])):
        out = tmp_path / f"gcps_{name}.gpkg"
        assert main(["collect-gcps", str(left), "--reference", str(ref), *ventouxpair.dem_args(), "--out", str(out),
                     *extra]) == 0
        text = capsys.readouterr().out
        counts[name] = (int(text.split("windows ")[1].split()[0]), len(read_gcps(out)))
        assert f"every {64 if name == 'default' else 256} px" in text
    assert counts["256"][0] == 4 and counts["256"][1] <= 2
    assert counts["default"][0] == 36 and counts["default"][1] >= 5


def _coarser(reference, folder, factor):
    """The reference averaged ``factor`` x coarser (what a user has when the only ortho is, say, Sentinel-2)."""
    gt = gdal.Open(reference).GetGeoTransform()
    out = str(folder / f"reference_x{factor}.tif")
    gdal.Warp(out, reference, xRes=gt[1] * factor, yRes=-gt[5] * factor, resampleAlg="average")
    return out, gt[1] * factor


def test_coarse_reference_named_with_what_to_do(scene, tmp_path, capsys):
    """A reference 8x coarser than the image: a 64-px window spans 8 of its pixels, most matches are weak; the run
    says so and which window would span 16 (here a warning line beside one GCP). At 16x nothing matches: exit 2,
    one line naming that cause, not "raise --search", nothing written. At the image's resolution no warning."""
    coarseness = {}
    for factor in (8, 16):
        ref, px = _coarser(scene.reference, tmp_path, factor)
        coarseness[factor] = px / 30.0                                       # the scene's 30 m pixels
        out = tmp_path / f"gcps_x{factor}.gpkg"
        rc = main(["collect-gcps", scene.image, "--reference", ref, "--dem", scene.dem_path, "--out", str(out),
                   "--workers", "1"])
        err = capsys.readouterr().err.strip()
        hint = (f"the reference's pixels are {coarseness[factor]:.1f}x the image's: a 64-px window spans "
                f"{64 / coarseness[factor]:.0f} of them, too few for firm matches; use --window "
                f"{2 * math.ceil(8 * coarseness[factor])} or more")
        assert hint in err and "--search" not in err and err.count("\n") == 0, err
        # a failed run writes nothing; at 8x a window or two may still hold (a warning then), at 16x none does
        assert rc in ((0, 2) if factor == 8 else (2,)) and out.exists() == (rc == 0), err
    assert 7.5 < coarseness[8] < 8.5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(collect_gcps(scene.image, scene.rpc, scene.reference, scene.dem, workers=1)) > 0
