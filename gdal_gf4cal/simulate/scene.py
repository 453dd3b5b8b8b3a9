"""Scene writer of the simulator (METHODS §10): RPC from the current model, GCPs from the true model, files.

Per image: ``scene.tif`` (placeholder or rendered), ``scene.RPB`` (fitted from the *current* model, METHODS §3),
``gcps.csv``/``gcps.gpkg`` (measured = true + noise + outliers), ``check_grid.csv``, ``camera_current.json``,
``camera_true.json``, ``reference.tif`` (rendered from the built-in texture: a reference orthophoto of the same
ground, for ``gf4cal collect-gcps``); per scene: ``dem.tif`` and ``truth.json``.
"""
from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass, field
from typing import Dict, Optional

import numpy as np
import pandas as pd
from osgeo import gdal

from .._gdal import with_gdal_exceptions
from ..atomic import atomic_output
from ..dem import DEM
from ..errors import CancelledError, Gf4calError
from ..gcp import make_gcps, write_gcps
from ..geodesy import metres_per_degree
from ..outputs import gtiff_options
from ..progress import report, scaled
from ..rpc_fit import fit_rpc_from_model
from .cameras import write_json_atomic
from .render import model_bounds, render_image, write_reference_ortho
from .sensors import SENSORS, SimImage, SimScene, SimulationError, make_scene
from .terrain import write_dem_tif

#: Sensors whose images cover the same ground (GCPs drawn once, from the first image).
_SHARED_COVERAGE = {"zy3", "gf7"}


@dataclass
class ImageResult:
    """What :func:`write_scene` wrote for one image."""

    name: str
    dir: str
    rpc: object
    fit_report: object
    gcps: object
    check_grid: object
    paths: Dict[str, str] = field(default_factory=dict)


@dataclass
class SceneResult:
    scene: SimScene
    out_dir: str
    images: Dict[str, ImageResult]
    truth_path: str
    dem_path: str
    elapsed_s: float = 0.0
    #: ``write_scene(crop=...)``: ``{image name: (x0, y0, w, h)}``, each image's window of its product (else None)
    crop: Optional[Dict] = None


def _draw_ground_points(image: SimImage, dem, n: int, rng):
    """``n`` ground points on the DEM seen at uniformly random true image positions of ``image``."""
    W, H = image.true.size
    s = rng.uniform(0.0, W, n)
    l = rng.uniform(0.0, H, n)
    lon, lat, h = image.true.localize_dem(s, l, dem)
    ok = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h)
    return np.asarray(lon)[ok], np.asarray(lat)[ok], np.asarray(h)[ok]


def simulate_gcps(scene: SimScene, *, n_gcps: int = 200, gcp_noise_px: float = 0.6, outlier_fraction: float = 0.0,
                  check_fraction: float = 0.3, seed: Optional[int] = None, outlier_range_px=(5.0, 30.0)):
    """GCP tables (one GeoDataFrame per image name) with known truth (METHODS §10).

    Ground points lie on the scene DEM; ``truth_sample, truth_line`` = the true model's exact image position;
    ``sample, line`` = truth + Gaussian noise of ``gcp_noise_px`` per axis, plus, for ``round(outlier_fraction * n)``
    of the points, an offset of 5-30 px in a random direction (``truth_outlier`` = True: ground truth, named apart
    from the ``outlier`` flag that estimators set). ``role`` is "check" for
    ``check_fraction`` of the ground points (the same in every image), else "control". Ids are shared between
    images: the same id is the same ground point.
    """
    if n_gcps < 1:
        raise SimulationError("n_gcps must be at least 1")
    if not (0.0 <= outlier_fraction < 1.0) or not (0.0 <= check_fraction < 1.0) or gcp_noise_px < 0:
        raise SimulationError("need 0 <= outlier_fraction < 1, 0 <= check_fraction < 1 and gcp_noise_px >= 0")
    rng = np.random.default_rng((scene.seed if seed is None else seed) + 104729)
    sources = scene.images[:1] if scene.sensor in _SHARED_COVERAGE else scene.images
    pts = [_draw_ground_points(im, scene.dem, n_gcps, rng) for im in sources]
    lon, lat, h = (np.concatenate(c) for c in zip(*pts))
    ids = np.array([f"G{i + 1:05d}" for i in range(lon.size)])
    roles = np.where(rng.random(lon.size) < check_fraction, "check", "control").astype(object)
    out = {}
    for im in scene.images:
        ts, tl = im.true.project(lon, lat, h)
        W, H = im.size
        inside = np.isfinite(ts) & np.isfinite(tl) & (ts >= 0) & (ts <= W) & (tl >= 0) & (tl <= H)
        # A true camera's cubic distortion, extrapolated far outside its CCD, can fold a distant ground point into
        # the image (jl1 MS bands): keep only points the current model also sees in the image, give or take the
        # largest simulated error (hj1: 75 px at the edge of 12000 px; jl1 MS: a few px of 128).
        cs, cl = im.current.project(lon[inside], lat[inside], h[inside])
        mw, mh = 0.05 * W + 30.0, 0.05 * H + 30.0
        near = (np.isfinite(cs) & np.isfinite(cl) & (cs >= -mw) & (cs <= W + mw) & (cl >= -mh) & (cl <= H + mh)
                & (np.abs(cs - ts[inside]) < 100) & (np.abs(cl - tl[inside]) < 100))
        # ... and whose true image point localises back to them (a folded projection does not)
        blon, blat = im.true.localize(ts[inside], tl[inside], h[inside])
        mx, my = metres_per_degree(lat[inside])
        back = np.hypot((np.asarray(blon) - lon[inside]) * mx, (np.asarray(blat) - lat[inside]) * my)
        near &= np.isfinite(back) & (back < 0.01 * im.gsd_m)
        inside[np.flatnonzero(inside)[~near]] = False
        k = int(inside.sum())
        noise_s = rng.normal(0.0, gcp_noise_px, k) if gcp_noise_px > 0 else np.zeros(k)
        noise_l = rng.normal(0.0, gcp_noise_px, k) if gcp_noise_px > 0 else np.zeros(k)
        # Exactly round(fraction * k) blunders (a Bernoulli draw per point may give none on small sets).
        outlier = np.zeros(k, dtype=bool)
        outlier[rng.permutation(k)[:int(round(outlier_fraction * k))]] = True
        mag = rng.uniform(*outlier_range_px, k)
        ang = rng.uniform(0, 2 * np.pi, k)
        ms = ts[inside] + noise_s + np.where(outlier, mag * np.cos(ang), 0.0)
        ml = tl[inside] + noise_l + np.where(outlier, mag * np.sin(ang), 0.0)
        gdf = make_gcps(lon[inside], lat[inside], h[inside], ms, ml, ids=ids[inside], role=roles[inside],
                        sigma=max(gcp_noise_px, 1e-3), truth_sample=ts[inside], truth_line=tl[inside],
                        truth_outlier=outlier)
        out[im.name] = gdf
    return out


def check_grid(image: SimImage, dem, n: int = 41):
    """Dense check grid: ``n x n`` image points of the current model on the DEM, projected by both models.

    Returns a DataFrame ``lon, lat, h, sample_current, line_current, sample_true, line_true``.
    """
    W, H = image.size
    s, l = np.meshgrid((np.arange(n) + 0.5) * W / n, (np.arange(n) + 0.5) * H / n)
    lon, lat, h = image.current.localize_dem(s.ravel(), l.ravel(), dem)
    sc, lc = image.current.project(lon, lat, h)
    st, lt = image.true.project(lon, lat, h)
    df = pd.DataFrame({"lon": lon, "lat": lat, "h": h, "sample_current": sc, "line_current": lc,
                       "sample_true": st, "line_true": lt})
    return df[np.isfinite(df.to_numpy()).all(axis=1)].reset_index(drop=True)


def set_crop_origin(ds, window) -> None:
    """Give a GDAL dataset the crop convention of CNES products (``gdal_gf4cal.crop``): its origin in the product
    ``window[:2] = (col0, row0)`` as a pixel-unit geotransform ``(col0, 1, 0, row0, 0, 1)`` without CRS (crop pixel
    (x, y) is product pixel (col0 + x, row0 + y)). ``window`` None: nothing (a full product)."""
    if window is not None:
        ds.SetGeoTransform((float(window[0]), 1.0, 0.0, float(window[1]), 0.0, 1.0))


@with_gdal_exceptions
def write_placeholder_tif(path: str, size, dtype: str = "Byte", *, bands: int = 1, origin=None) -> str:
    """A sparse tiled GeoTIFF of the image size: unwritten blocks cost nothing (10240^2 in a few kB);
    ``origin = (col0, row0)``: a crop of a product (:func:`set_crop_origin`)."""
    with atomic_output(path) as tmp:
        ds = gdal.GetDriverByName("GTiff").Create(tmp, int(size[0]), int(size[1]), int(bands),
                                                  gdal.GetDataTypeByName(dtype),
                                                  gtiff_options(tile=512, extra=["SPARSE_OK=TRUE"] + (
                                                      ["PHOTOMETRIC=MINISBLACK", "ALPHA=NO"] if bands > 1 else [])))
        for k in range(int(bands)):
            ds.GetRasterBand(k + 1).SetNoDataValue(0)
        ds.SetMetadataItem("GF4CAL_PLACEHOLDER", "YES: pixels not rendered (gf4cal simulate --render renders them)")
        set_crop_origin(ds, origin)
        ds = None
    return path


def _write_csv(df, path):
    with atomic_output(path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.12g")
    return path


def write_scene(sensor_name: str, out_dir, seed: int = 0, center=None, size=None, n_gcps: int = 200,
                gcp_noise_px: float = 0.6, outlier_fraction: float = 0.0, dem=None, render: bool = False,
                reference=None, progress=None, *, check_fraction: float = 0.3, paint_clouds: float = 0.0,
                workers: int = 2, tile: int = 512, check_grid_n: int = 41,
                reference_ortho: bool = True, options: Optional[Dict] = None,
                observation_options: Optional[Dict] = None, crop=None) -> SceneResult:
    """Simulate a scene and write every file (METHODS §10). See DESIGN.md "Simulator API" for the layout.

    Parameters
    ----------
    sensor_name : "gf4", "zy3", "hj1", "jl1" or "gf7".
    out_dir : output folder (created); multi-image sensors get one sub-folder per image.
    seed, center, size, dem : see :func:`make_scene`.
    n_gcps, gcp_noise_px, outlier_fraction, check_fraction : see :func:`simulate_gcps`.
    render : render ``scene.tif`` through the TRUE model (from ``reference``, any GDAL raster in any CRS, or the
        built-in seeded texture); otherwise a sparse placeholder of the right size.
    paint_clouds : fraction (0..1) of the image covered by bright clouds when rendering (``cloud_mask.tif`` too);
        for sensors with a ``clouds`` option (gf7: clouds on the ground, seen alike by pan and MS) that option.
    crop : ``(x0, y0, w, h)`` in pixels of the first image's full product (gf7: pan pixels; sensors with
        :attr:`SensorSpec.crop_windows`): the full product is simulated, only the crop's window of each image is
        written (rendered alone), keeping its place: the image carries its origin in the product as a pixel-unit
        geotransform without CRS (:func:`set_crop_origin`, the convention of CNES crops), and the RPC written,
        ``product.RPB`` (not a sidecar GDAL attaches to the crop), is the product's, as are the GCPs and the check
        grid (product pixels). Exclusive with ``size``.
    reference_ortho : when rendering from the built-in texture, also write ``reference.tif`` next to each
        ``scene.tif``: the same texture as an EPSG:4326 orthophoto (:func:`.render.write_reference_ortho`, pixel =
        the image's nominal GSD, covering its footprint plus a margin), i.e. what ``gf4cal collect-gcps
        --reference`` needs to match the scene. Without clouds.
    options : sensor options of :func:`make_scene` (jl1: ``orbit_seed``).
    observation_options : jl1 only: keywords of :func:`.jl1.block_observations` (``n_overlap_ties``,
        ``n_band_ties``, ``tie_noise_px``, ``reference_band``) for ``observations.csv``, the long observation table
        of GCPs (the rows of the per-image gcps.csv) and tie points, written beside the image folders.
    progress : callback ``(fraction, message)``; raising :class:`CancelledError` from it cancels (files written by
        this call are removed).
    """
    t0 = time.perf_counter()
    out_dir = os.fspath(out_dir)
    spec = SENSORS.get(sensor_name)
    windows = _crop_windows(spec, sensor_name, crop, size)
    options, paint_clouds = _check_render_options(spec, options, paint_clouds, render, reference)
    _refuse_inputs_among_outputs(sensor_name, out_dir, [reference, getattr(dem, "path", dem)])
    os.makedirs(out_dir, exist_ok=True)
    written = []
    try:
        dem_path = os.path.join(out_dir, "dem.tif")
        scene = _scene_with_dem(sensor_name, dem, dem_path, seed=seed, center=center, size=size,
                                progress=scaled(progress, 0.0, 0.1), options=options)
        written.append(dem_path)
        report(progress, 0.1, "control points")
        gcps = simulate_gcps(scene, n_gcps=n_gcps, gcp_noise_px=gcp_noise_px, outlier_fraction=outlier_fraction,
                             check_fraction=check_fraction)
        write_images = SENSORS[scene.sensor].write_images
        truth = dict(scene.truth)
        truth["gcps"] = {"n_gcps": n_gcps, "gcp_noise_px": gcp_noise_px, "outlier_fraction": outlier_fraction,
                         "check_fraction": check_fraction, "outlier_range_px": [5.0, 30.0],
                         "measured": "truth (true model) + N(0, gcp_noise_px) per axis + outlier offset"}
        render_options = None if write_images is not None else {
            "render": render, "reference": reference, "seed": seed, "paint_clouds": paint_clouds,
            "workers": workers, "tile": tile, "reference_ortho": reference_ortho}
        results = _write_image_folders(scene, out_dir, gcps, windows, render_options, check_grid_n, written,
                                       progress, sensor_name, truth)
        if write_images is not None:
            truth[scene.sensor] = write_images(scene, results, render=render, reference=reference, windows=windows,
                                               workers=workers, tile=tile, progress=scaled(progress, 0.3, 0.98),
                                               written=written)
        _add_crop_and_observations(truth, scene, windows, out_dir, gcps, observation_options, written)
        truth["elapsed_s"] = time.perf_counter() - t0
        truth_path = os.path.join(out_dir, "truth.json")
        write_json_atomic(truth_path, truth, overwrite=True)
        report(progress, 1.0, "scene written")
        return SceneResult(scene, out_dir, results, truth_path, dem_path, time.perf_counter() - t0, windows)
    except (CancelledError, Gf4calError, OSError, ValueError, KeyboardInterrupt):
        for path in written:
            if os.path.exists(path):
                os.unlink(path)
        raise


def _scene_with_dem(sensor_name: str, dem, dem_path: str, **kw) -> SimScene:
    """The simulated scene, its DEM written to ``dem_path`` (the one given, copied; else the simulated terrain)."""
    if dem is not None:
        scene = make_scene(sensor_name, dem=DEM.from_user_input(dem), **kw)
        _copy_dem(scene, dem_path)
        return scene
    return make_scene(sensor_name, dem_path=dem_path, **kw)


def _check_render_options(spec, options, paint_clouds: float, render: bool, reference):
    """``(options, paint_clouds)``: clouds go to the sensor's own ``clouds`` option when it has one; clouds and
    a reference without rendering, or a cloud fraction outside [0, 1), are refused."""
    if spec is not None and paint_clouds > 0 and "clouds" in spec.options:
        options = dict(options or {}, clouds=paint_clouds)
        paint_clouds = 0.0
        if not render:
            raise SimulationError("--clouds only makes sense with --render")
    if reference is not None and not render:
        raise SimulationError("--reference only makes sense with --render")
    if not (0.0 <= paint_clouds < 1.0):
        raise SimulationError("paint_clouds must be a fraction in [0, 1)")
    if paint_clouds > 0 and not render:
        raise SimulationError("--clouds only makes sense with --render")
    return options, paint_clouds


def _write_image_folders(scene: SimScene, out_dir: str, gcps, windows, render_options: Optional[Dict],
                         check_grid_n: int, written: list, progress, sensor_name: str, truth: Dict) -> Dict:
    """Every image's folder (:func:`_write_image`; progress 0.1 .. 0.3 when the sensor writes its images
    itself, else .. 1.0); each image's RPC fit, GCP count and files recorded in ``truth``."""
    results = {}
    n_im = len(scene.images)
    truth["files"] = {}
    for k, im in enumerate(scene.images):
        span = 0.2 if render_options is None else 0.9         # the sensor's images: 0.3 .. 0.98
        p = scaled(progress, 0.1 + span * k / n_im, 0.1 + span * (k + 1) / n_im)
        d = os.path.join(out_dir, im.name) if im.name else out_dir
        os.makedirs(d, exist_ok=True)
        result = _write_image(scene, im, d, gcps[im.name], windows, render_options, check_grid_n, written, p,
                              sensor_name)
        results[im.name] = result
        key = im.name or "scene"
        truth["images"][key]["rpc_fit"] = result.fit_report.to_dict()
        truth["images"][key]["n_gcps"] = int(len(result.gcps))
        truth["files"][key] = {k_: os.path.relpath(v, out_dir) for k_, v in result.paths.items()}
    truth["files"]["dem"] = "dem.tif"
    return results


def _write_image(scene: SimScene, im: SimImage, d: str, g, windows, render_options: Optional[Dict],
                 check_grid_n: int, written: list, p, sensor_name: str) -> "ImageResult":
    """One image's files in folder ``d``: its RPC fitted from the current model, the image (rendered, a
    placeholder, or left to the sensor's own writer when ``render_options`` is None), GCPs, check grid and
    cameras; every path written appended to ``written``."""
    report(p, 0.0, f"{im.name or sensor_name}: fitting the RPC")
    rpc, rep = fit_rpc_from_model(im.current)
    paths = {k_: os.path.join(d, f) for k_, f in (
        ("image", "scene.tif"), ("rpc", "product.RPB" if windows else "scene.RPB"), ("gcps_csv", "gcps.csv"),
        ("gcps_gpkg", "gcps.gpkg"), ("check_grid", "check_grid.csv"),
        ("camera_current", "camera_current.json"), ("camera_true", "camera_true.json"))}
    if render_options is not None:                 # else the sensor writes its images after every image folder
        if render_options["render"]:
            _render(scene, im, d, paths, written, p, sensor_name, **render_options)
        else:
            write_placeholder_tif(paths["image"], im.size)
        written.append(paths["image"])
    rpc.write_rpb(paths["rpc"], overwrite=True)
    written.append(paths["rpc"])
    report(p, 0.92, f"{im.name or sensor_name}: GCPs and check grid")
    with warnings.catch_warnings():
        # geopandas warns when writing an empty table (a tiny crop may contain no GCP); that is fine.
        warnings.simplefilter("ignore", UserWarning)
        write_gcps(g, paths["gcps_csv"], overwrite=True)
        write_gcps(g, paths["gcps_gpkg"], overwrite=True)
    written += [paths["gcps_csv"], paths["gcps_gpkg"]]
    grid = check_grid(im, scene.dem, check_grid_n)
    _write_csv(grid, paths["check_grid"])
    written.append(paths["check_grid"])
    for key_, cam in (("camera_current", im.current.camera), ("camera_true", im.true.camera)):
        cam.to_json(paths[key_], overwrite=True)
    written += [paths["camera_current"], paths["camera_true"]]
    return ImageResult(im.name, d, rpc, rep, g, grid, paths)


def _render(scene: SimScene, im: SimImage, d: str, paths: Dict[str, str], written: list, p, sensor_name: str, *,
            render, reference, seed, paint_clouds, workers, tile, reference_ortho) -> None:
    """Render ``scene.tif`` through the true model (with its cloud mask), and the built-in texture's reference
    orthophoto when asked for; adds their paths to ``paths`` and ``written`` (not the image's)."""
    cloud_path = os.path.join(d, "cloud_mask.tif") if paint_clouds > 0 else None
    render_image(im.true, scene.dem, paths["image"], reference=reference, seed=seed, gsd_m=im.gsd_m,
                 paint_clouds=paint_clouds, cloud_mask_path=cloud_path, workers=workers, tile=tile,
                 progress=scaled(p, 0.1, 0.9))
    if cloud_path:
        paths["cloud_mask"] = cloud_path
        written.append(cloud_path)
    if reference is None and reference_ortho:
        report(p, 0.9, f"{im.name or sensor_name}: reference orthophoto")
        paths["reference"] = os.path.join(d, "reference.tif")
        written.append(paths["reference"])
        # The footprint plus >= 128 px on each side: a biased RPC (tests shift it by 50+ px) still
        # finds ground under every window of the image.
        W_, H_ = im.size
        margin = max(0.03, 128.0 / max(1, min(W_, H_)))
        write_reference_ortho(paths["reference"], model_bounds(im.true, margin=margin),
                              im.gsd_m / 111320.0, seed=seed, scale_m=3.0 * im.gsd_m, workers=workers)


def _add_crop_and_observations(truth: Dict, scene: SimScene, windows, out_dir: str, gcps, observation_options,
                               written: list) -> None:
    """The crop windows and their convention into ``truth``; the sensor's observation table written (jl1),
    observation options refused for the other sensors."""
    if windows:
        truth["crop"] = {"windows": {k: list(v) for k, v in windows.items()},
                         "convention": "image pixel (x, y) = product pixel (x0 + x, y0 + y); the images carry "
                                       "(x0, y0) as a pixel-unit geotransform without CRS; product.RPB, the "
                                       "GCPs and the check grid are in product pixels"}
    write_observations = SENSORS[scene.sensor].write_observations
    if write_observations is not None:
        truth["observations"] = write_observations(scene, out_dir, gcps, observation_options, written)
        truth["files"]["observations"] = "observations.csv"
    elif observation_options:
        raise SimulationError(f"observation_options are for sensors with an observation table (jl1), not "
                              f"{scene.sensor}")


#: Files write_scene may write per image folder (see DESIGN.md "Simulator API").
_IMAGE_FILES = ("scene.tif", "scene.RPB", "product.RPB", "gcps.csv", "gcps.gpkg", "check_grid.csv",
                "camera_current.json", "camera_true.json", "reference.tif", "cloud_mask.tif", "cover_mask.tif",
                "misregistration_truth.tif")


def _crop_windows(spec, sensor_name: str, crop, size):
    """``{image name: window}`` of ``write_scene(crop=...)`` (None without a crop); refuses what cannot be."""
    if crop is None:
        return None
    if size is not None:
        raise SimulationError("give --size (a crop around the centre) or --crop (a crop at its place in the "
                              "product), not both")
    if spec is None or spec.crop_windows is None:
        with_crop = sorted(k for k, v in SENSORS.items() if v.crop_windows is not None)
        raise SimulationError(f"--crop is not available for {sensor_name}; it is for {', '.join(with_crop)} "
                              "(use --size for a crop around the centre)")
    return spec.crop_windows(crop)


def _refuse_inputs_among_outputs(sensor_name: str, out_dir: str, inputs) -> None:
    """Refuse, before anything is written, an input file (reference image, DEM) that is one of the outputs."""
    if sensor_name not in SENSORS:
        return                                   # make_scene gives the error naming the sensors
    outputs = {os.path.realpath(os.path.join(out_dir, f)) for f in ("dem.tif", "truth.json", "observations.csv")}
    for name in SENSORS[sensor_name].images:
        outputs |= {os.path.realpath(os.path.join(out_dir, name, f)) for f in _IMAGE_FILES}
    for p in inputs:
        if isinstance(p, (str, os.PathLike)) and os.path.realpath(os.fspath(p)) in outputs:
            raise SimulationError(f"the input {os.fspath(p)} is where the simulator writes an output; "
                                  "use another --out folder")


def _copy_dem(scene: SimScene, dem_path: str):
    """dem.tif for a user DEM: the DEM resampled (as ellipsoidal heights) over the footprint, or a constant."""
    hr = scene.truth["height_range_m"]
    bounds = None
    lons, lats = [], []
    for im in scene.images:
        W, H = im.size
        s = np.array([0, W, W, 0, W / 2])
        l = np.array([0, 0, H, H, H / 2])
        for h in hr:
            lo, la = im.current.localize(s, l, np.full(5, h))
            lons.append(lo)
            lats.append(la)
    lo, la = np.concatenate(lons), np.concatenate(lats)
    mx, my = 0.05 * (lo.max() - lo.min()) + 0.005, 0.05 * (la.max() - la.min()) + 0.005
    bounds = (lo.min() - mx, la.min() - my, lo.max() + mx, la.max() + my)
    n = 1024
    cell = max(bounds[2] - bounds[0], bounds[3] - bounds[1]) / n
    xs = bounds[0] + (np.arange(int(np.ceil((bounds[2] - bounds[0]) / cell))) + 0.5) * cell
    ys = bounds[3] - (np.arange(int(np.ceil((bounds[3] - bounds[1]) / cell))) + 0.5) * cell
    X, Y = np.meshgrid(xs, ys)
    dem = scene.dem
    heights = np.asarray(dem.sample(X, Y, nodata="nan"), dtype=np.float32)
    write_dem_tif(dem_path, heights, (bounds[0], cell, 0.0, bounds[3], 0.0, -cell))
