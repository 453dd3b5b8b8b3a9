"""Agreement with GDAL (METHODS §0, §1): our readers give GDAL's numbers, ``RPCModel.project`` gives GDAL's RPC
transformer's pixels within 1e-6 px, on every real RPC file in tests/data/rpc.

Sidecars without their image are laid next to a tiny placeholder raster named the way GDAL's metadata readers look
for them, so GDAL parses them itself. Set ``GF4CAL_REAL_DATA`` to a folder (e.g. ``../shared/data/real``) to run
the same checks on every RPC file found there as well.
"""
from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal import RPCModel, rpc_io
from gdal_gf4cal.errors import RPCFormatError

DATA = Path(__file__).parents[1] / "data" / "rpc"
LOCAL_FILES = sorted(p for p in DATA.iterdir() if p.name != "PROVENANCE.txt")
NO_GDAL_READER = ("json", "geom", "dimap_v1")  # formats GDAL has no reader for: their model is handed to GDAL as metadata
TOL_PX = 1e-6


def _tiny_tiff(path: Path) -> str:
    ds = gdal.GetDriverByName("GTiff").Create(str(path), 8, 8, 1, gdal.GDT_Byte)
    ds = None
    return str(path)


def gdal_view(path: Path, folder: Path):
    """(GDAL dataset carrying the RPC of ``path`` as GDAL itself reads it, format name).

    For json/geom (no GDAL reader) the dataset is an in-memory raster with our parsed metadata, so only the
    projection is compared there.
    """
    fmt = rpc_io.rpc_file_format(path)
    if fmt == "dimap" and b"PHR_Dimap_Document" in path.read_bytes():
        fmt = "dimap_v1"  # Pleiades DIMAP v1.4: GDAL's DIMAP driver reads no Global_RFM (empty coefficients)
    folder.mkdir(parents=True, exist_ok=True)
    if fmt in ("gdal", "gdal_xml") and not path.name.endswith(".aux.xml"):
        ds = gdal.Open(str(path))
    elif fmt == "rpb":
        shutil.copy(path, folder / "img.RPB")
        ds = gdal.Open(_tiny_tiff(folder / "img.tif"))
    elif fmt == "rpc_txt" and not re.search(r"^\s*LINE_NUM_COEFF_1\s*:", path.read_text(errors="replace"), re.M):
        # GDAL KEY=value dump (GDAL's own test passes it as transformer options): GDAL parses the strings.
        kv = dict(line.strip().split("=", 1) for line in path.read_text().splitlines() if "=" in line)
        ds = gdal.GetDriverByName("MEM").Create("", 1, 1, 1)
        ds.SetMetadata(kv, "RPC")
    elif fmt == "rpc_txt":
        shutil.copy(path, folder / "img_rpc.txt")
        ds = gdal.Open(_tiny_tiff(folder / "img.tif"))
    elif fmt == "dimap":
        # GDAL's Pleiades reader pairs IMG_<name>_R<i>C<j>.<ext> with RPC_<name>.XML
        shutil.copy(path, folder / "RPC_PHR1A_P_001.XML")
        ds = gdal.Open(_tiny_tiff(folder / "IMG_PHR1A_P_001_R1C1.TIF"))
    elif fmt == "isd":
        shutil.copy(path, folder / "img.XML")
        ds = gdal.Open(_tiny_tiff(folder / "img.tif"))
    elif fmt == "alos":
        shutil.copy(path, folder / "RPC-scene.txt")
        (folder / "HDR-scene.txt").write_text("")
        ds = gdal.Open(_tiny_tiff(folder / "IMG-scene.tif"))
    elif fmt == "gdal_xml":  # PAM .aux.xml: next to its image
        shutil.copy(path, folder / "img.tif.aux.xml")
        ds = gdal.Open(_tiny_tiff(folder / "img.tif"))
    elif fmt in NO_GDAL_READER:
        ds = gdal.GetDriverByName("MEM").Create("", 1, 1, 1)
        ds.SetMetadata(rpc_io.read_rpc_metadata(path), "RPC")
    else:
        raise AssertionError(f"no GDAL view for format {fmt}")
    return ds, fmt


def _numbers(value: str) -> list:
    """GDAL's RPC strings as floats: a scalar may carry a unit ('+005124.00 pixels')."""
    tokens = value.split()
    if len(tokens) > 1 and not re.match(r"^[-+.\d]", tokens[1]):
        tokens = tokens[:1]
    return [float(t) for t in tokens]


def _ground_grid(rpc: RPCModel, n: int = 9):
    """n x n x 3 points over the RPC's whole normalised validity cube (|L|, |P|, |H| <= 1)."""
    u = np.linspace(-1.0, 1.0, n)
    L, P, H = (a.ravel() for a in np.meshgrid(u, u, [-1.0, 0.0, 1.0]))
    return (rpc.long_off + L * rpc.long_scale, rpc.lat_off + P * rpc.lat_scale,
            rpc.height_off + H * rpc.height_scale)


def check_against_gdal(path: Path, folder: Path) -> float:
    """Assert metadata and projection agreement for one file; return the largest pixel difference."""
    ours = rpc_io.read_rpc_metadata(path)
    ds, fmt = gdal_view(path, folder)
    theirs = dict(ds.GetMetadata("RPC") or {})
    assert theirs, f"GDAL read no RPC from {path}"
    if fmt not in NO_GDAL_READER:
        assert set(ours) == set(theirs), path
        for key, value in theirs.items():  # bit-identical numbers
            assert [float(t) for t in ours[key].split()] == _numbers(value), (path, key)

    rpc = RPCModel.from_file(path)
    lon, lat, h = _ground_grid(rpc)
    transformer = gdal.Transformer(ds, None, ["METHOD=RPC"])
    result, ok = transformer.TransformPoints(1, list(zip(lon, lat, h)))  # 1 = ground -> image
    assert all(ok), path
    expected = np.array(result)[:, :2]
    sample, line = rpc.project(lon, lat, h)
    diff = float(np.max(np.abs(np.c_[sample, line] - expected)))
    assert diff <= TOL_PX, (path, diff)
    return diff


@pytest.mark.parametrize("path", LOCAL_FILES, ids=[p.name for p in LOCAL_FILES])
def test_local_rpc_agrees_with_gdal(path, tmp_path):
    check_against_gdal(path, tmp_path)


@pytest.mark.parametrize("name, lon, lat, h, expected, tol", [
    # shareloc reference (EXPECTED_VALUES A): DIMAP (line 201, samp 101) = GDAL (100.5, 200.5)
    ("RPC_PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.XML",
     7.048662660737769592, 43.72774839443545858, 0.0, (100.5, 200.5), 1e-3),
    ("PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.geom",
     7.048662660737769592, 43.72774839443545858, 0.0, (100.5, 200.5), 1e-3),
    ("PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif",
     7.048662660737769592, 43.72774839443545858, 0.0, (100.5, 200.5), 1e-3),
    # shareloc reference (EXPECTED_VALUES B): full-image pixel centre (5000.5, 5000.5) on SRTM + EGM96
    ("RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML",
     5.193406151946084, 44.20805807814395, 503.51202179, (5000.5, 5000.5), 1e-2),
    ("ventoux_left_image.geom", 5.193406151946084, 44.20805807814395, 503.51202179, (5000.5, 5000.5), 1e-2),
    # GDAL autotest/alg/transformer.py: image -> ground results (GDAL's 0.05 / 0.1 px inversion threshold)
    ("rpc.vrt", 125.64830100509131, 39.869433991997553, 0.0, (20.5, 10.5), 0.05),
    ("rpc.vrt", 125.64828521533849, 39.869345204440144, 30.0, (20.5, 10.5), 0.05),
    ("transformer_11_rpc.txt", 77.350939956024618, 38.739703990877814, 1150.0, (0.0, 0.0), 0.1),
])
def test_independent_reference_points(name, lon, lat, h, expected, tol):
    """Values produced by other tools (shareloc/OTB, GDAL's test suite): pins the pixel convention of each format."""
    sample, line = RPCModel.from_file(DATA / name).project(lon, lat, h)
    assert (sample, line) == pytest.approx(expected, abs=tol)


def _real_data_files():
    root = os.environ.get("GF4CAL_REAL_DATA")
    if not root:
        return []
    return sorted(p for p in Path(root).rglob("*") if p.is_file())


@pytest.mark.skipif(not os.environ.get("GF4CAL_REAL_DATA"), reason="set GF4CAL_REAL_DATA to a folder of real RPCs")
def test_every_rpc_under_real_data_agrees_with_gdal(tmp_path):
    checked, worst = [], 0.0
    for i, path in enumerate(_real_data_files()):
        try:
            rpc_io.read_rpc_metadata(path)
        except RPCFormatError:
            continue  # not an RPC file (DEMs, grids, PROVENANCE, unsupported vendor formats)
        worst = max(worst, check_against_gdal(path, tmp_path / str(i)))
        checked.append(path.name)
    assert checked, "no RPC file found under GF4CAL_REAL_DATA"
    print(f"{len(checked)} RPC files agree with GDAL; worst difference {worst:.2e} px")
