#!/usr/bin/env python3
"""``refine --ortho`` against plain ``gdalwarp -rpc`` plus the refine alone, on a real QuickBird-2 crop (issue 23).

Data: orthority's QuickBird-2 basic 1B crop (850 x 1450 px), its 5 field-surveyed GCPs and the DEM of its tests
(``GF4CAL_QB2_DIR``, else ``/work/shared/data/real/orthority_qb2``: the three files from a clone of orthority,
https://github.com/leftfield-geospatial/orthority, tests/data/). Everything runs in this
process, interleaved (refine, gdalwarp, refine --ortho, then again in another order) so that the load of a shared
machine falls on all alike:

  refine        :func:`~gdal_gf4cal.workflows.refine.refine_rpc` (translation, the DEM's heights as they are: it
                declares EGM2008, whose grid is not installed here; plausibility check off: two of the surveyed GCPs
                lie outside the crop) writing the .RPB only
  gdalwarp      ``gdal.Warp`` of the image with the refined RPC (a VRT over it, as refine writes) with RPC_DEM=the
                same DEM (no vertical shift either), bilinear, the same CRS, resolution and extent as our ortho, into a plain GeoTIFF (gdalwarp's
                defaults: untiled, uncompressed, no mask, no overviews), one thread
  refine+ortho  the same refine with ``ortho=`` (tiled, compressed GeoTIFF, internal mask, overviews); its valid
                pixels must equal gdalwarp's (the number that differ is printed)

Goal (issue 23): refine+ortho <= 1.1 x (gdalwarp + refine). Prints the minimum and median of each and the ratios, with
the load average, and the same ratio of CPU times (one thread: on a quiet machine the same as the wall times, on a
loaded one much steadier). Usage: python bench/bench_refine_ortho.py [--repeat N]
"""
from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from osgeo import gdal

from gdal_gf4cal.threads import limit
from gdal_gf4cal.workflows.refine import refine_rpc

gdal.UseExceptions()
GOAL = 1.1


def data_dir() -> Path:
    for d in (os.environ.get("GF4CAL_QB2_DIR"), "/work/shared/data/real/orthority_qb2",
              Path(__file__).resolve().parent.parent / "tests" / "data" / "orthority_qb2"):
        if d and (Path(d) / "qb2_basic1b.tif").exists():
            return Path(d)
    raise SystemExit("QuickBird-2 crop not found: set GF4CAL_QB2_DIR to a folder with orthority's "
                     "tests/data/rpc/qb2_basic1b.tif, gcps.geojson and tests/data/ngi/dem.tif (from a clone of "
                     "https://github.com/leftfield-geospatial/orthority)")


def run_refine(d: Path, tmp: str, tag: str, ortho: bool) -> dict:
    out = os.path.join(tmp, f"{tag}.RPB")
    kw = {"ortho": os.path.join(tmp, f"{tag}_ortho.tif")} if ortho else {}
    return refine_rpc(str(d / "qb2_basic1b.tif"), str(d / "gcps.geojson"), "translation", out=out,
                      dem=str(d / "dem.tif"), geoid="none", check_plausibility=False, overwrite=True, **kw)


def run_gdalwarp(d: Path, tmp: str, rpc_out: str, grid: dict) -> None:
    """Plain gdalwarp -rpc of the image with the refined RPC (a VRT carrying it) on the same output grid."""
    from gdal_gf4cal.rpc import RPCModel
    src = os.path.join(tmp, "src.vrt")
    gdal.Translate(src, str(d / "qb2_basic1b.tif"), format="VRT")
    vrt = gdal.Open(src, gdal.GA_Update)
    vrt.SetMetadata(RPCModel.from_file(rpc_out).to_gdal_metadata(), "RPC")
    vrt = None
    gdal.Warp(os.path.join(tmp, "gdalwarp.tif"), src, format="GTiff", rpc=True, resampleAlg="bilinear",
              dstSRS=grid["crs"], xRes=grid["res"], yRes=grid["res"], outputBounds=grid["bounds"],
              transformerOptions=[f"RPC_DEM={d / 'dem.tif'}", "RPC_DEMINTERPOLATION=bilinear",
                                  "RPC_DEM_APPLY_VDATUM_SHIFT=FALSE"])


def ortho_grid(path: str) -> dict:
    ds = gdal.Open(path)
    gt = ds.GetGeoTransform()
    bounds = (gt[0], gt[3] + gt[5] * ds.RasterYSize, gt[0] + gt[1] * ds.RasterXSize, gt[3])
    return {"crs": ds.GetProjection(), "res": abs(gt[1]), "bounds": bounds, "size": (ds.RasterXSize, ds.RasterYSize)}


def measure(repeat: int) -> dict:
    """Times (s) per step over ``repeat`` interleaved rounds, and the ortho grid."""
    d = data_dir()
    times = {"refine": [], "gdalwarp": [], "refine+ortho": []}
    cpu = {k: [] for k in times}
    with tempfile.TemporaryDirectory() as tmp, limit(1):
        run_refine(d, tmp, "warm", True)                      # imports, PROJ/GDAL caches
        grid = ortho_grid(os.path.join(tmp, "warm_ortho.tif"))
        rpc_out = os.path.join(tmp, "warm.RPB")
        steps = {"refine": lambda: run_refine(d, tmp, "r", False),
                 "gdalwarp": lambda: run_gdalwarp(d, tmp, rpc_out, grid),
                 "refine+ortho": lambda: run_refine(d, tmp, "o", True)}
        order = list(steps)
        for r in range(repeat):
            for name in (order if r % 2 == 0 else order[::-1]):
                t, c = time.perf_counter(), time.process_time()
                steps[name]()
                times[name].append(time.perf_counter() - t)
                cpu[name].append(time.process_time() - c)
        differing = differing_valid_pixels(os.path.join(tmp, "o_ortho.tif"), os.path.join(tmp, "gdalwarp.tif"))
    return {"times": times, "cpu": cpu, "grid": grid, "differing": differing}


def differing_valid_pixels(ortho: str, plain: str) -> tuple:
    """``(valid pixels of our ortho (its mask) whose value differs from gdalwarp's on the same grid, valid pixels)``."""
    import numpy as np
    a, b = gdal.Open(ortho), gdal.Open(plain)
    valid = a.GetRasterBand(1).GetMaskBand().ReadAsArray() > 0
    diff = a.ReadAsArray() != b.ReadAsArray()
    if diff.ndim == 3:                                           # bands first: a pixel differs in any band
        diff = diff.any(axis=0)
    return int(np.count_nonzero(diff & valid)), int(np.count_nonzero(valid))


def summary(res: dict) -> dict:
    """Per step the minimum and median wall time and the minimum CPU time; the ratio of each."""
    out = {"min": {k: min(v) for k, v in res["times"].items()},
           "median": {k: statistics.median(v) for k, v in res["times"].items()},
           "cpu": {k: min(v) for k, v in res["cpu"].items()}}
    for what in ("min", "median", "cpu"):
        t = out[what]
        out[f"ratio_{what}"] = t["refine+ortho"] / (t["gdalwarp"] + t["refine"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    a = ap.parse_args()
    res = measure(a.repeat)
    s = summary(res)
    g = res["grid"]
    print(f"QuickBird-2 crop 850 x 1450 px -> ortho {g['size'][0]} x {g['size'][1]} px at {g['res']:.3g} m, one "
          f"thread; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (GDAL {gdal.__version__})")
    print(f"{'step':<14} {'min s':>8} {'median s':>9} {'min CPU s':>10}")
    for k in s["min"]:
        print(f"{k:<14} {s['min'][k]:>8.3f} {s['median'][k]:>9.3f} {s['cpu'][k]:>10.3f}")
    print(f"refine+ortho / (gdalwarp + refine): {s['ratio_min']:.2f} (min wall), {s['ratio_median']:.2f} (median "
          f"wall), {s['ratio_cpu']:.2f} (min CPU: steadiest on a loaded machine); goal <= {GOAL}")
    print(f"valid pixels of the ortho differing from gdalwarp's: {res['differing'][0]} of {res['differing'][1]}")


if __name__ == "__main__":
    main()
