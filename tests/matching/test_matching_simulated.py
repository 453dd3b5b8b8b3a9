"""Automatic GCP collection on scenes rendered by the simulator, through the public CLI (issue 7 "Must show").

Every scene is made as a user would: ``gf4cal simulate --sensor gf4 --render`` (a 1024 x 1024 crop of the GF4 array
over Tibet-like synthetic relief, or 512 x 512 with a real orthophoto as the ground), then ``gf4cal collect-gcps``
with the scene's own ``reference.tif`` (or the real orthophoto) and ``dem.tif``. ``scene.RPB`` is fitted from the
*current* rigorous model, so it carries the simulator's known systematic error (rotation + scale + cubic camera
error, ~2.4 px on this crop); a second case folds a further 70 px shift into it.

Truth: the ground point ``(lon, lat, h)`` of a GCP is truly imaged at ``true.project(lon, lat, h)``, with ``true``
the scene's TRUE rigorous model, rebuilt in memory by ``make_scene`` with the same seed and size (the simulator is
deterministic). Nothing in the truth goes through the RPC, the matcher or GDAL.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal import RPCModel, write_rpc_vrt
from gdal_gf4cal.cli import main
from gdal_gf4cal.gcp import read_gcps
from gdal_gf4cal.matching import collect_gcps, match_tile, plan_tiles
from gdal_gf4cal.matching.correlate import phase_correlate
from gdal_gf4cal.simulate import make_scene
from gdal_gf4cal.simulate.render import model_bounds

gdal.UseExceptions()

PLEIADES = Path(__file__).parents[1] / "data" / "matching" / "pleiades_ventoux_left.tif"
SIZE = 1024            # built-in texture scenes
SIZE_REAL = 512        # the real 500 x 500 orthophoto then has about the GF4 crop's ground resolution (~60 m)
SPACING, WINDOW = 64, 64
SHIFT = (53.4, -47.1)  # extra RPC error of the "large initial offset" case (px; 71 px)


@dataclass
class Rendered:
    dir: Path
    true: object           # the TRUE rigorous model (truth)
    current: object        # the current model (what scene.RPB was fitted from)
    reference: str
    size: int

    @property
    def image(self):
        return str(self.dir / "scene.tif")

    @property
    def dem(self):
        return str(self.dir / "dem.tif")


def _simulate(out: Path, seed: int, size: int, *extra) -> None:
    assert main(["simulate", "--sensor", "gf4", "--seed", str(seed), "--size", str(size), str(size), "--render",
                 "--n-gcps", "10", "--out", str(out), *extra]) == 0


def _models(seed: int, size: int):
    im = make_scene("gf4", seed=seed, size=(size, size)).images[0]
    return im.true, im.current


def _collect_cli(image, reference, dem, out: Path, *extra, spacing: int = SPACING):
    """``gf4cal collect-gcps`` -> the GCP table read back with the project's reader (as refine does)."""
    assert main(["collect-gcps", str(image), "--reference", str(reference), "--dem", str(dem), "--out", str(out),
                 "--spacing", str(spacing), "--window", str(WINDOW), "--workers", "2", *extra]) == 0
    return read_gcps(out)


def _errors(g, true):
    ts, tl = true.project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    return g["sample"].to_numpy() - ts, g["line"].to_numpy() - tl


def _kept_fraction(gdf) -> float:
    """Inliers over the windows that can be matched: all but those whose ground is not in the image (a biased
    RPC moves the grid's edge out of the picture) or on no-data."""
    w = gdf.attrs["windows"]
    return (w["accepted"] - w["outliers"]) / (w["total"] - w["outside_image"] - w["nodata"])


def _check_matching(sc: Rendered, image, tmp: Path, name: str, spacing: int = SPACING):
    """CLI and API on one image: accuracy vs truth, yield, and CLI == API; returns (CLI table, API table, path of
    the CLI's GeoPackage)."""
    path = tmp / f"{name}.gpkg"
    g = _collect_cli(image, sc.reference, sc.dem, path, spacing=spacing)
    api = collect_gcps(image, None, sc.reference, sc.dem, spacing_px=spacing, window_px=WINDOW, workers=2)
    inl = api[~api["outlier"].to_numpy(bool)]
    # The CLI wrote exactly the API's inliers.
    assert len(g) == len(inl)
    np.testing.assert_allclose(g["sample"].to_numpy(), inl["sample"].to_numpy(), atol=1e-9)
    np.testing.assert_allclose(g["line"].to_numpy(), inl["line"].to_numpy(), atol=1e-9)
    # The matcher had something to find: the RPC is off by pixels (the simulator's systematic error, or more).
    assert np.median(np.hypot(g["dsample"], g["dline"])) > 1.0
    es, el = _errors(g, sc.true)
    err = np.hypot(es, el)
    rms = float(np.sqrt(np.mean(err ** 2)))
    print(f"{name}: {len(g)} GCPs, windows {api.attrs['windows']}, kept {_kept_fraction(api):.3f}, "
          f"rms vs truth {rms:.4f} px, max {err.max():.3f} px")
    assert rms <= 0.1, rms
    assert err.max() < 0.3, err.max()
    assert _kept_fraction(api) >= 0.95, api.attrs["windows"]
    return g, api, path


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def builtin(tmp_path_factory):
    """``gf4cal simulate --render`` with the built-in texture: scene.tif + reference.tif (same ground)."""
    d = tmp_path_factory.mktemp("gf4_builtin")
    _simulate(d, 0, SIZE)
    assert (d / "reference.tif").exists()
    true, current = _models(0, SIZE)
    return Rendered(d, true, current, str(d / "reference.tif"), SIZE)


@pytest.fixture(scope="module")
def builtin_gcps(builtin, tmp_path_factory):
    return _check_matching(builtin, builtin.image, tmp_path_factory.mktemp("gcps_builtin"), "builtin")


@pytest.fixture(scope="module")
def shifted(builtin, tmp_path_factory):
    """The same image with its RPC shifted by SHIFT: a VRT over the untouched scene.tif carrying the new RPC."""
    d = tmp_path_factory.mktemp("gf4_shifted")
    rpc = RPCModel.from_file(builtin.dir / "scene.RPB").with_image_affine(*SHIFT)
    vrt = str(d / "scene_shifted.vrt")
    write_rpc_vrt(builtin.image, rpc, vrt)
    return vrt


# ------------------------------------------------------------------------------------------------ tests
def test_builtin_texture_accuracy_and_yield(builtin, builtin_gcps):
    g, api, _ = builtin_gcps
    # The RPC really is wrong by the simulator's systematic error: the matcher measured it, truth confirms it.
    ps, pl = builtin.current.project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    ts, tl = builtin.true.project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    initial = np.hypot(ps - ts, pl - tl)
    assert np.median(initial) > 1.5, np.median(initial)
    np.testing.assert_allclose(g["dsample"], ts - ps, atol=0.3)
    np.testing.assert_allclose(g["dline"], tl - pl, atol=0.3)
    assert len(g) >= 200
    assert set(g["role"]) == {"control"}


def test_builtin_texture_featureless_means_flat(builtin):
    """A window is called featureless only where the raw image really is flat at its centre (independent test:
    3 x 3 range <= 2 DN over most of the central half; in this texture, where a road widens into a patch), and
    never for textured land next to a road or a field edge (8 of 225 windows were, before flat_fraction compared
    local gradient energy with the noise level too)."""
    from scipy import ndimage
    img = gdal.Open(builtin.image).ReadAsArray().astype(float)
    specs, _ = plan_tiles(builtin.image, None, builtin.reference, builtin.dem, SPACING, WINDOW)
    res = [match_tile(s) for s in specs]
    st = np.concatenate([r["status"] for r in res])
    cs, cl = (np.concatenate([r[k] for r in res]) for k in ("center_sample", "center_line"))
    flat_px = (ndimage.maximum_filter(img, 3) - ndimage.minimum_filter(img, 3)) <= 2
    q = WINDOW // 4
    flat = np.array([flat_px[int(y) - q:int(y) + q, int(x) - q:int(x) + q].mean() for x, y in zip(cs, cl)])
    print(f"featureless windows: {np.count_nonzero(st == 2)}, flat fraction {flat[st == 2]}; textured windows "
          f"{np.count_nonzero(flat < 0.5)}")
    assert np.count_nonzero(flat < 0.5) >= 200
    assert not np.any(st[flat < 0.5] == 2)
    assert not np.any(st[flat > 0.5] == 0)


def test_builtin_texture_edges_are_pixel_integrated():
    """texture_value box-averages its field and road edges over a pixel (scale_m / 3): against a brute-force
    12 x 12 average of the hard-edged texture over the pixel, near edges it is ~15x closer than point sampling
    (point-sampled hard edges moved by up to half a pixel between the raw image and the reference)."""
    from gdal_gf4cal.simulate import texture_value
    gsd = 60.0
    rng = np.random.default_rng(0)
    lon, lat = 88 + rng.uniform(0, 0.5, 20000), 31 + rng.uniform(0, 0.5, 20000)
    # One pixel in spherical-Mercator metres (the texture's units), in degrees.
    dlon, dlat = np.degrees(gsd / 6378137.0), np.degrees(gsd * np.cos(np.radians(lat)) / 6378137.0)
    o = (np.arange(12) + 0.5) / 12 - 0.5
    box = np.mean([texture_value(lon + a * dlon, lat + b * dlat, 0, 3 * gsd, edge_m=0) for a in o for b in o],
                  axis=0)
    point = texture_value(lon, lat, 0, 3 * gsd, edge_m=0)
    soft = texture_value(lon, lat, 0, 3 * gsd)
    near = np.abs(box - point) > 0.02
    assert near.sum() > 200
    e_point, e_soft = np.abs(point - box)[near].mean(), np.abs(soft - box)[near].mean()
    assert e_soft < e_point / 8, (e_soft, e_point)


def test_fifty_pixel_initial_offset(builtin, shifted, tmp_path):
    g, api, _ = _check_matching(builtin, shifted, tmp_path, "shifted")
    # Every accepted GCP was found from an initial offset of more than 50 px.
    assert np.all(np.hypot(g["dsample"], g["dline"]) > 50)
    assert len(g) >= 150


def test_real_orthophoto_texture(tmp_path):
    """The ground is a real Pleiades image (tests/data/matching, PROVENANCE.txt), georeferenced in UTM 45N over
    the crop's footprint: ``simulate --render --reference`` renders from it and ``collect-gcps`` matches
    against it."""
    import pyproj
    true, current = _models(1, SIZE_REAL)
    b = model_bounds(true, margin=0.1)
    x, y = pyproj.Transformer.from_crs(4326, 32645, always_xy=True).transform(
        np.array([b[0], b[2], b[0], b[2]]), np.array([b[1], b[1], b[3], b[3]]))
    ref = str(tmp_path / "pleiades_utm45.tif")
    gdal.Translate(ref, str(PLEIADES), outputSRS="EPSG:32645",
                   outputBounds=[float(x.min()), float(y.max()), float(x.max()), float(y.min())])
    d = tmp_path / "scene"
    _simulate(d, 1, SIZE_REAL, "--reference", ref)
    assert not (d / "reference.tif").exists()        # the user's reference is the reference
    sc = Rendered(d, true, current, ref, SIZE_REAL)
    g, api, _ = _check_matching(sc, sc.image, tmp_path, "pleiades", spacing=32)
    assert len(g) >= 150


def test_painted_clouds_give_no_gcps(tmp_path):
    from scipy import ndimage
    d = tmp_path / "scene"
    _simulate(d, 2, SIZE, "--clouds", "0.2")
    true, _ = _models(2, SIZE)
    mask = gdal.Open(str(d / "cloud_mask.tif")).ReadAsArray() > 0
    assert 0.1 < mask.mean() < 0.3
    # All accepted windows, outliers included.
    g = _collect_cli(d / "scene.tif", d / "reference.tif", d / "dem.tif", tmp_path / "g.gpkg", "--keep-outliers")
    ts, tl = true.project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    i = np.clip(np.floor(ts).astype(int), 0, SIZE - 1)
    j = np.clip(np.floor(tl).astype(int), 0, SIZE - 1)
    # No GCP inside a cloud; within 2 px of its edge a point is a cloud-edge point (the mask is defined to a pixel).
    inside = ndimage.binary_erosion(mask, iterations=2)
    assert not np.any(inside[j, i]), int(inside[j, i].sum())
    es, el = _errors(g[~g["outlier"].to_numpy(bool)], true)
    assert np.sqrt(np.mean(es ** 2 + el ** 2)) <= 0.1
    # Windows whose ground point lies well clear of the clouds (40 px) are still kept.
    specs, _ = plan_tiles(str(d / "scene.tif"), None, str(d / "reference.tif"), str(d / "dem.tif"), SPACING, WINDOW)
    res = [match_tile(s) for s in specs]
    st = np.concatenate([r["status"] for r in res])
    cs, cl = true.project(*(np.concatenate([r[k] for r in res]) for k in ("lon", "lat", "h")))
    ok = np.isfinite(cs) & np.isfinite(cl)
    ci = np.clip(np.nan_to_num(cs).astype(int), 0, SIZE - 1)
    cj = np.clip(np.nan_to_num(cl).astype(int), 0, SIZE - 1)
    near = ndimage.binary_dilation(mask, iterations=40)
    clear = ok & ~near[cj, ci] & (st != 5)
    cloudy = ok & mask[cj, ci]
    print(f"clouds: {mask.mean():.3f} of the image; {clear.sum()} clear windows, kept {np.mean(st[clear] == 0):.3f}; "
          f"{cloudy.sum()} windows centred on cloud, statuses {np.bincount(st[cloudy], minlength=6).tolist()}")
    assert clear.sum() >= 100 and cloudy.sum() >= 20
    assert np.mean(st[clear] == 0) >= 0.95
    assert not np.any(st[cloudy] == 0)


# ------------------------------------------------------------------------------------------------ end to end
def _ortho_vs_reference(src, sc: Rendered, out: str, win: int = 96, step: int = 64):
    """``gdalwarp -rpc -to RPC_DEM=dem.tif`` of ``src`` onto the reference's grid, then phase correlation of
    ``win``-px windows (fully inside the orthoimage) against the reference: (dx, dy, ncc) per window, in
    reference pixels."""
    ref = gdal.Open(sc.reference)
    gt = ref.GetGeoTransform()
    gdal.Warp(out, src, rpc=True, transformerOptions=[f"RPC_DEM={sc.dem}"], dstSRS=ref.GetProjection(),
              outputBounds=[gt[0], gt[3] + gt[5] * ref.RasterYSize, gt[0] + gt[1] * ref.RasterXSize, gt[3]],
              width=ref.RasterXSize, height=ref.RasterYSize, resampleAlg="cubic", dstNodata=0)
    o = gdal.Open(out).ReadAsArray().astype(float)
    r = ref.ReadAsArray().astype(float)
    a, b = [], []
    for y in range(0, o.shape[0] - win, step):
        for x in range(0, o.shape[1] - win, step):
            if np.all(o[y:y + win, x:x + win] > 0):
                a.append(r[y:y + win, x:x + win])
                b.append(o[y:y + win, x:x + win])
    res = phase_correlate(np.array(a), np.array(b))
    return res.dx, res.dy, res.ncc


@pytest.mark.slow
def test_end_to_end_collect_calibrate_orthorectify(builtin, builtin_gcps, tmp_path):
    """collect-gcps -> calibrate-lookangle (the GF4 chain, METHODS §5) -> gdalwarp -rpc with the recalibrated
    RPC: the orthoimage matches the reference within 0.2 px; with the scene's RPC it is ~2.4 px off."""
    gcps = builtin_gcps[2]                            # written by gf4cal collect-gcps
    cal = tmp_path / "cal"
    assert main(["calibrate-lookangle", "--rpc", builtin.image, "--gcps", str(gcps), "--camera",
                 str(builtin.dir / "camera_current.json"), "--image", builtin.image, "--out", str(cal)]) == 0
    dx0, dy0, _ = _ortho_vs_reference(builtin.image, builtin, str(tmp_path / "before.tif"))
    dx, dy, ncc = _ortho_vs_reference(str(cal / "scene.vrt"), builtin, str(tmp_path / "after.tif"))
    err0, err = np.hypot(dx0, dy0), np.hypot(dx, dy)
    print(f"ortho vs reference, {err.size} windows: before median {np.median(err0):.3f} px; after median "
          f"{np.median(err):.4f}, max {err.max():.3f} px, mean shift ({dx.mean():+.4f}, {dy.mean():+.4f}) px")
    assert err.size >= 150
    assert np.median(err0) > 1.0
    assert np.all(ncc > 0.9)
    assert err.max() <= 0.2, err.max()
    assert np.hypot(dx.mean(), dy.mean()) <= 0.02


@pytest.mark.slow
def test_end_to_end_fifty_pixel_offset_refine_orthorectify(builtin, shifted, tmp_path):
    """collect-gcps on the 71-px-shifted RPC -> refine (affine) -> gdalwarp -rpc: within 0.2 px of the reference."""
    gcps = tmp_path / "gcps.gpkg"
    _collect_cli(shifted, builtin.reference, builtin.dem, gcps)
    vrt = tmp_path / "refined.vrt"
    assert main(["refine", shifted, "--gcps", str(gcps), "--model", "affine", "--out", str(vrt)]) == 0
    dx, dy, ncc = _ortho_vs_reference(str(vrt), builtin, str(tmp_path / "after.tif"))
    err = np.hypot(dx, dy)
    print(f"refine affine, ortho vs reference, {err.size} windows: median {np.median(err):.4f}, max "
          f"{err.max():.3f} px, mean shift ({dx.mean():+.4f}, {dy.mean():+.4f}) px")
    assert err.size >= 150
    assert np.all(ncc > 0.9)
    assert err.max() <= 0.2, err.max()
    assert np.hypot(dx.mean(), dy.mean()) <= 0.02
