"""Headless QGIS for the provider tests: one QgsApplication per session, Processing initialised, the gf4cal
provider registered. QGIS comes from Debian's python3-qgis (the venv sees system site packages).

Without QGIS these tests are skipped, except in CI (``CI`` set) where a missing QGIS is an error.
"""
from __future__ import annotations

import os
import sys

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
if not os.environ.get("XDG_RUNTIME_DIR"):  # Qt warns on stderr without a private runtime dir
    import tempfile
    os.environ["XDG_RUNTIME_DIR"] = tempfile.mkdtemp(prefix="xdg-runtime-")
QGIS_PLUGINS = "/usr/share/qgis/python/plugins"  # the 'processing' package
if os.path.isdir(QGIS_PLUGINS) and QGIS_PLUGINS not in sys.path:
    sys.path.append(QGIS_PLUGINS)

try:
    import qgis.core  # noqa: F401
    HAVE_QGIS = True
except ImportError:  # pragma: no cover - QGIS is installed by `make test`
    HAVE_QGIS = False

ARTIFACTS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                         "test-artifacts")


def pytest_collection_modifyitems(config, items):
    if HAVE_QGIS:
        return
    if os.environ.get("CI"):
        raise pytest.UsageError("QGIS (python3-qgis) is required in CI: run `make test`, which installs it")
    here = os.path.dirname(os.path.abspath(__file__))
    skip = pytest.mark.skip(reason="QGIS is not installed (apt install python3-qgis qgis-providers)")
    for item in items:
        # test_engine_isolation checks the engine without QGIS: it always runs.
        if str(item.fspath).startswith(here) and not str(item.fspath).endswith("test_engine_isolation.py"):
            item.add_marker(skip)


@pytest.fixture(scope="session")
def qgis_app():
    """The session's QgsApplication (headless) with Processing and the gf4cal provider."""
    from qgis.core import QgsApplication
    app = QgsApplication.instance()
    if app is None:
        QgsApplication.setPrefixPath("/usr", True)
        app = QgsApplication([], False)
        app.initQgis()
    from processing.core.Processing import Processing
    Processing.initialize()
    from processing_provider.provider import Gf4calProvider
    registry = QgsApplication.processingRegistry()
    if registry.providerById("gf4cal") is None:
        registry.addProvider(Gf4calProvider())
    yield app
    # No exitQgis(): tearing QGIS down at interpreter exit is racy with pytest's own shutdown.


@pytest.fixture(scope="session")
def run_alg(qgis_app):
    """Run a gf4cal algorithm through processing.run; returns (results, feedback log)."""
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback, QgsProject

    class Feedback(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.log, self.progress = [], []
            self.progressChanged.connect(self.progress.append)

        def reportError(self, error, fatalError=False):
            self.log.append(("error", error))

        def pushInfo(self, info):
            self.log.append(("info", info))

        def pushWarning(self, warning):
            self.log.append(("warning", warning))

        def text(self):
            return "\n".join(m for _, m in self.log)

    def run(alg_id, params, context=None):
        fb = Feedback()
        ctx = context or QgsProcessingContext()
        ctx.setProject(QgsProject.instance())
        res = processing.run(alg_id, params, feedback=fb, context=ctx)
        return res, fb

    return run


@pytest.fixture(scope="session")
def artifacts_dir():
    os.makedirs(ARTIFACTS, exist_ok=True)
    return ARTIFACTS


# ---------------------------------------------------------------------------------------------------------------
# A small scene with known truth: a real RPC (DigitalGlobe sample shipped with GDAL's autotest, tests/data/rpc),
# GCPs whose image positions are the RPC's projection + a known affine bias + seeded noise, one blunder.
# ---------------------------------------------------------------------------------------------------------------
DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data")
BIAS = {"s0": 3.0, "s_s": 1.5e-3, "s_l": -0.8e-3, "l0": -2.0, "l_s": 0.6e-3, "l_l": 1.2e-3}  # px, px/px
NOISE_PX = 0.15
BLUNDER_ID = "G007"
N_GCPS = 48


def bias(sample, line):
    """The injected affine image-space error (measured - RPC), px."""
    b = BIAS
    return (b["s0"] + b["s_s"] * sample + b["s_l"] * line, b["l0"] + b["l_s"] * sample + b["l_l"] * line)


@pytest.fixture(scope="session")
def scene(tmp_path_factory):
    """Files of the test scene: image.tif (RPC in TIFF tags), norpc.tif, gcps.gpkg (UTM, fields id/sample/line/h/
    role), gcps_colrow.gpkg (same points, fields col/row/elev), gcps_few.gpkg (2 points), dem.tif; plus truth."""
    import numpy as np
    from osgeo import gdal, ogr, osr

    from gdal_gf4cal.rpc import RPCModel

    gdal.UseExceptions()
    d = tmp_path_factory.mktemp("scene")
    rpc = RPCModel.from_file(os.path.join(DATA, "rpc", "md_dg.RPB"))
    W, H = rpc.image_size
    img = str(d / "image.tif")
    ds = gdal.GetDriverByName("GTiff").Create(img, W, H, 1, gdal.GDT_Byte, ["COMPRESS=DEFLATE", "TILED=YES"])
    ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    ds = None
    norpc = str(d / "norpc.tif")
    ds = gdal.GetDriverByName("GTiff").Create(norpc, 64, 64, 1, gdal.GDT_Byte)
    ds.SetGeoTransform((12.5, 1e-4, 0, 41.9, 0, -1e-4))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    ds.SetProjection(srs.ExportToWkt())
    ds = None

    # DEM (ellipsoidal heights): a smooth hill over the scene, a little larger than the footprint.
    lon_c, lat_c = rpc.long_off, rpc.lat_off
    dem_path = str(d / "dem.tif")
    n = 200
    ds = gdal.GetDriverByName("GTiff").Create(dem_path, n, n, 1, gdal.GDT_Float32)
    x0, y0, step = lon_c - 0.05, lat_c + 0.05, 0.1 / n
    ds.SetGeoTransform((x0, step, 0, y0, 0, -step))
    ds.SetProjection(srs.ExportToWkt())
    yy, xx = np.mgrid[0:n, 0:n]
    ds.GetRasterBand(1).WriteArray(100.0 + 60.0 * np.exp(-((xx - n / 2) ** 2 + (yy - n / 2) ** 2) / (n / 3) ** 2))
    ds = None
    from gdal_gf4cal.dem import DEM
    dem = DEM.from_file(dem_path)

    rng = np.random.default_rng(20240607)
    gs, gl = np.meshgrid(np.linspace(80, W - 80, 8), np.linspace(80, H - 80, 6))
    s_rpc = gs.ravel() + rng.uniform(-30, 30, N_GCPS)
    l_rpc = gl.ravel() + rng.uniform(-30, 30, N_GCPS)
    lon, lat, h = rpc.localize_dem(s_rpc, l_rpc, dem)
    ds_, dl_ = bias(s_rpc, l_rpc)
    sample = s_rpc + ds_ + rng.normal(0, NOISE_PX, N_GCPS)
    line = l_rpc + dl_ + rng.normal(0, NOISE_PX, N_GCPS)
    ids = [f"G{i:03d}" for i in range(N_GCPS)]
    blunder = ids.index(BLUNDER_ID)
    sample[blunder] += 25.0
    role = np.where(np.arange(N_GCPS) % 4 == 3, "check", "control")
    role[blunder] = "control"

    utm = osr.SpatialReference()
    utm.ImportFromEPSG(32633)
    utm.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    to_utm = osr.CoordinateTransformation(srs, utm)

    def write_gcps(path, names, idx, crs=utm, with_h=True):
        drv = ogr.GetDriverByName("GPKG")
        out = drv.CreateDataSource(path)
        lyr = out.CreateLayer("gcps", crs, ogr.wkbPoint)
        lyr.CreateField(ogr.FieldDefn("id", ogr.OFTString))
        for key in ("sample", "line") + (("h",) if with_h else ()):
            lyr.CreateField(ogr.FieldDefn(names[key], ogr.OFTReal))
        lyr.CreateField(ogr.FieldDefn("role", ogr.OFTString))
        for i in idx:
            f = ogr.Feature(lyr.GetLayerDefn())
            f["id"], f[names["sample"]], f[names["line"]], f["role"] = ids[i], sample[i], line[i], str(role[i])
            if with_h:
                f[names["h"]] = float(h[i])
            x, y, _ = to_utm.TransformPoint(float(lon[i]), float(lat[i]))
            g = ogr.Geometry(ogr.wkbPoint)
            g.AddPoint_2D(x, y)
            f.SetGeometry(g)
            lyr.CreateFeature(f)
        out = None
        return path

    std = {"sample": "sample", "line": "line", "h": "h"}
    files = {
        "dir": str(d), "image": img, "norpc": norpc, "dem": dem_path,
        "rpc_file": os.path.join(DATA, "rpc", "md_dg.RPB"),
        "gcps": write_gcps(str(d / "gcps.gpkg"), std, range(N_GCPS)),
        "gcps_colrow": write_gcps(str(d / "gcps_colrow.gpkg"), {"sample": "col", "line": "row", "h": "elev"},
                                  range(N_GCPS)),
        "gcps_noh": write_gcps(str(d / "gcps_noh.gpkg"), std, range(N_GCPS), with_h=False),
        "gcps_few": write_gcps(str(d / "gcps_few.gpkg"), std, [0, 9]),
    }
    truth = {"rpc": rpc, "size": (W, H), "lon": lon, "lat": lat, "h": h, "ids": ids, "role": role,
             "sample": sample, "line": line, "blunder": BLUNDER_ID, "noise_px": NOISE_PX,
             "bias": bias}
    return files, truth
