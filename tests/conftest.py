"""Shared fixtures: paths of the real test data (tests/data/*, each folder with a PROVENANCE.txt)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"
os.environ.setdefault("PROJ_DATA", "/usr/share/proj")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA


@pytest.fixture(scope="session")
def srtm_path() -> Path:
    """Real SRTM3 tile N44E005 (Mont Ventoux), heights above EGM96."""
    return DATA / "dem" / "N44E005.hgt"


@pytest.fixture(scope="session")
def ventoux_rpc_path() -> Path:
    """Real Pleiades-1B DIMAP v2 RPC of the Ventoux left image (covers the SRTM tile)."""
    return DATA / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML"


# ---------------------------------------------------------------------------------------------- sensor contract
#: The input shapes every sensor model must accept (as pyproj's ``scalar_and_array``): a Python float, a 1-D
#: array and a 2-D array. Outputs keep the shape; scalars give Python floats.
INPUT_KINDS = ("scalar", "1d", "2d")


@pytest.fixture(params=INPUT_KINDS)
def scalar_and_array(request):
    """``shape(values)``: six values as a Python float (the first), a (6,) array or a (2, 3) array."""
    import numpy as np

    def shape(values):
        values = np.asarray(values, dtype=float).ravel()[:6]
        if request.param == "scalar":
            return float(values[0])
        if request.param == "1d":
            return values.copy()
        return values.reshape(2, 3).copy()

    shape.kind = request.param
    return shape


#: Every kind of sensor model of the engine (issue 10): a real RPC, an RPC with a correction, an RPC with a
#: recalibrated camera, and each model type of the simulator.
SENSOR_MODELS = ("rpc", "compensated_rpc", "recalibrated_sensor", "sim_frame", "sim_pushbroom")


def _plane_dem(path, model, relief_m: float = 40.0):
    """A smooth synthetic DEM (GeoTIFF, EPSG:4326, ellipsoidal) over the footprint of ``model``, inside its height
    range: h = mid + relief * sin * cos over the footprint (real file, real GDAL reads)."""
    import numpy as np
    from gdal_gf4cal.dem import DEM
    from rasters import write_tif
    W, H = model.size if hasattr(model, "size") else model.rpc.image_size
    lo, hi = model.height_range
    mid = 0.5 * (lo + hi)
    s = np.array([0.0, W, W, 0.0, W / 2])
    l = np.array([0.0, 0.0, H, H, H / 2])
    lon, lat = model.localize(s, l, np.full(5, mid))
    x0, x1, y0, y1 = lon.min(), lon.max(), lat.min(), lat.max()
    mx, my = 0.3 * (x1 - x0) + 1e-4, 0.3 * (y1 - y0) + 1e-4
    x0, x1, y0, y1 = x0 - mx, x1 + mx, y0 - my, y1 + my
    n = 200
    cx, cy = (x1 - x0) / n, (y1 - y0) / n
    X, Y = np.meshgrid(x0 + (np.arange(n) + 0.5) * cx, y1 - (np.arange(n) + 0.5) * cy)
    amp = min(relief_m, 0.4 * (hi - lo))
    Z = mid + amp * np.sin(6.0 * (X - x0) / (x1 - x0)) * np.cos(5.0 * (Y - y0) / (y1 - y0))
    write_tif(path, Z.astype(np.float32), gt=(x0, cx, 0.0, y1, 0.0, -cy), epsg=4326)
    return DEM.from_user_input(str(path), geoid=False, nodata="nan")


@pytest.fixture(scope="session", params=SENSOR_MODELS)
def sensor_model(request, tmp_path_factory, ventoux_rpc_path, srtm_path):
    """``(name, model, dem, size)``: one model of each kind with a DEM under its footprint and its image size."""
    from gdal_gf4cal.compensation import CompensatedRPC, CompensationModel, CompensationResult
    from gdal_gf4cal.dem import DEM
    from gdal_gf4cal.lookangle import RecalibratedSensor
    from gdal_gf4cal.rpc import RPCModel
    from gdal_gf4cal.rpc_fit import fit_rpc_from_model
    from gdal_gf4cal.simulate import make_scene
    name = request.param
    tmp = tmp_path_factory.mktemp(f"sensor_{name}")
    if name in ("rpc", "compensated_rpc"):
        rpc = RPCModel.from_file(ventoux_rpc_path)
        dem = DEM.from_user_input(srtm_path, nodata="nan")
        # A 4000 x 4000 px window of the Ventoux image, over the SRTM tile.
        size = (4000, 4000)
        if name == "rpc":
            return name, rpc, dem, size
        frame = (rpc.samp_off + 0.5, rpc.samp_scale, rpc.line_off + 0.5, rpc.line_scale)
        result = CompensationResult.from_coefficients(CompensationModel.from_name("affine"), frame,
                                                      [4.3, 1.8, -0.9], [-2.7, 0.6, -1.2])
        return name, CompensatedRPC(rpc, result), dem, size
    if name == "sim_pushbroom":
        model = make_scene("hj1", seed=3, size=(300, 300), dem=500.0).images[0].current
        return name, model, _plane_dem(tmp / "dem.tif", model), tuple(model.size)
    image = make_scene("gf4", seed=3, size=(300, 300), dem=500.0).images[0]
    if name == "sim_frame":
        return name, image.current, _plane_dem(tmp / "dem.tif", image.current), tuple(image.current.size)
    rpc, _ = fit_rpc_from_model(image.current, height_range=image.current.height_range)
    model = RecalibratedSensor(rpc, image.current.camera, image.true.camera)
    return name, model, _plane_dem(tmp / "dem.tif", model), tuple(model.size)


@pytest.fixture(scope="session")
def simulate_gcps():
    """:func:`gcpsim.gcps_from_truth`, the shared seeded GCP simulator, as a fixture."""
    from gcpsim import gcps_from_truth
    return gcps_from_truth
