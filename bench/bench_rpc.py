"""RPC throughput against GDAL's RPC transformer and rpcm, measured in the same run, single-threaded.

Same points for everyone, on the real Pleiades Ventoux RPC and the real SRTM tile, our kernels on one thread
(``GF4CAL_NUM_THREADS=1`` through :func:`gdal_gf4cal.threads.limit`: the threaded speed-up is bench_threads.py's):
  project       ground -> image           vs GDAL TransformPoints(bDstToSrc=1) and rpcm's ``projection``
  localize      image -> ground at h      vs GDAL at its default 0.1 px tolerance (we converge to 1e-8 px)
  localize_dem  image -> ground on a DEM  vs GDAL with RPC_DEM at RPC_PIXEL_ERROR_THRESHOLD=1e-6 (we converge to
                1e-8 px / 1e-4 m)
Each timing is the least CPU time of ``--repeat`` interleaved runs (ours, GDAL, rpcm, ours, ...; everything runs
on the calling thread): the machine is shared, compare the ratios (same run), not absolute rates; the load average
is printed. Two rows time the NumPy floor of a projection in the same run (:func:`numpy_floor`): ``floor:
product``, the four polynomials' products and divisions alone on monomials computed beforehand, and ``floor:
minimal``, the whole evaluation without our wrapper; ``ours/rpcm`` of these rows is the most a NumPy projection can
reach over rpcm here. ``page faults``: the minor page faults of the least-CPU run (ours and the floors): the
floors write into one output allocated beforehand, ours allocates its output at every call.
Goals: issue 2: project >= rpcm's speed; localize_dem >= 1.5x GDAL's; issue 23: project >= 6x rpcm single-threaded.

rpcm: its ``rpc_model.py`` (NumPy only for projection) is loaded from wherever ``import rpcm`` would find it, e.g.
``pip download rpcm --no-deps`` unpacked into a folder on PYTHONPATH outside the repository; its package
``__init__`` (rasterio, srtm4, geojson) is not needed. Without it the table says "rpcm not installed".

Run: .venv/bin/python bench/bench_rpc.py [--points N] [--repeat N] [--quick]
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import resource
import sys
import time
import types
from pathlib import Path

import numpy as np
from osgeo import gdal

from gdal_gf4cal import DEM, RPCModel
from gdal_gf4cal.rpc import SERIAL_PROJECT_CHUNK, fill_monomials, monomials
from gdal_gf4cal.threads import limit

gdal.UseExceptions()
DATA = Path(__file__).resolve().parent.parent / "tests" / "data"
GOAL_RPCM = 6.0


def load_rpcm():
    """rpcm's ``rpc_model`` module (its projection needs NumPy only), or None when rpcm is not on the path."""
    try:
        spec = importlib.util.find_spec("rpcm")
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.origin:
        return None
    path = Path(spec.origin).parent / "rpc_model.py"
    stubs = [name for name in ("pyproj", "rasterio", "rpcm", "rpcm.geo", "rpcm.rpc_file_readers")
             if name not in sys.modules]
    for name in stubs:                       # imported at its top, unused by projection / localization
        sys.modules[name] = types.ModuleType(name)
    sys.modules["rpcm.rpc_file_readers"].read_rpc_file = None
    mod = types.ModuleType("rpcm_rpc_model")
    try:
        exec(compile(path.read_text(), str(path), "exec"), mod.__dict__)
    finally:
        for name in stubs:
            sys.modules.pop(name, None)
    return mod


def best_of(fns: dict, repeat: int) -> dict:
    """Least CPU time (``time.process_time``: everything here runs on the calling thread, and on a shared machine
    the CPU seconds of a single-threaded call are what survives the load) of each function over ``repeat``
    interleaved rounds, its last result, and the minor page faults of its least-CPU run (an output's first touch:
    ~4 us a 4 KB page on this VM, ~15 ns per projected point when the allocator hands out fresh pages)."""
    times = {k: [] for k in fns}
    out = {}
    for r in range(repeat):
        for k in (list(fns) if r % 2 == 0 else list(fns)[::-1]):
            f, t = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.process_time()
            out[k] = fns[k]()
            times[k].append((time.process_time() - t, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f))
    return {k: (min(v)[0], out[k], min(v)[1]) for k, v in times.items()}


def numpy_floor(rpc: RPCModel, lon, lat, hh):
    """The least NumPy work of a projection, as two functions to time beside ours: ``product``, the (4, 20) x (20,
    chunk) product of the four polynomials and the division, chunk after chunk on the monomials of the first chunk
    computed beforehand (in cache: what any BLAS evaluation of the polynomials must do at least, the monomials
    free); ``minimal``, the whole evaluation without our wrapper: offsets, the 16 monomial products (5 NumPy calls),
    one product and one division per chunk in reused buffers."""
    C = rpc._project_coeffs(0.5)                     # ours: the pixel affine and ground scales folded in
    off = (rpc.long_off, rpc.lat_off, rpc.height_off)
    n, c = lon.size, SERIAL_PROJECT_CHUNK
    mono = monomials(lon[:c] - off[0], lat[:c] - off[1], hh[:c] - off[2])
    v, out, m = np.empty((4, c)), np.empty((2, n)), np.empty((20, c))
    m[0] = 1.0

    def product():
        for i in range(0, n - c + 1, c):
            np.matmul(C, mono, out=v)
            np.divide(v[0::2], v[1::2], out=out[:, i:i + c])
        return out

    def minimal():
        for i in range(0, n - c + 1, c):
            np.subtract(lon[i:i + c], off[0], out=m[1])
            np.subtract(lat[i:i + c], off[1], out=m[2])
            np.subtract(hh[i:i + c], off[2], out=m[3])
            fill_monomials(m)
            np.matmul(C, m, out=v)
            np.divide(v[0::2], v[1::2], out=out[:, i:i + c])
        return out

    return product, minimal


def measure(n: int = 200_000, repeat: int = 5) -> dict:
    """Rates and round-trip errors per operation: ``{op: {"ours": s, "gdal": s, "rpcm": s or None, "err": px}}``."""
    rpc = RPCModel.from_file(DATA / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    dem_path = str(DATA / "dem" / "N44E005.hgt")
    dem = DEM.from_file(dem_path, nodata="nan")
    rm = load_rpcm()
    w, h = rpc.image_size
    rng = np.random.default_rng(0)
    s, l = rng.uniform(0, w, n), rng.uniform(0, h, n)
    hh = rng.uniform(*rpc.height_range, n)
    ds = gdal.GetDriverByName("MEM").Create("", w, h)
    ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    tr = gdal.Transformer(ds, None, ["METHOD=RPC"])
    tr_dem = gdal.Transformer(ds, None, ["METHOD=RPC", f"RPC_DEM={dem_path}", "RPC_PIXEL_ERROR_THRESHOLD=1e-6",
                                         "RPC_DEM_APPLY_VDATUM_SHIFT=FALSE"])
    rows = {}
    with limit(1):
        lon, lat = rpc.localize(s, l, hh)
        ground, image = np.column_stack([lon, lat, hh]), np.column_stack([s, l, hh])
        fns = {"ours": lambda: rpc.project(lon, lat, hh), "gdal": lambda: tr.TransformPoints(1, ground)}
        if rm is not None:
            r2 = rm.RPCModel(rpc.to_gdal_metadata())
            fns["rpcm"] = lambda: r2.projection(lon, lat, hh)
        product, minimal = numpy_floor(rpc, lon, lat, hh)
        fns.update({"floor_product": product, "floor_minimal": minimal})
        t = best_of(fns, repeat)
        ps, pl = t["ours"][1]
        rows["project"] = {"ours": t["ours"][0], "gdal": t["gdal"][0], "rpcm": t["rpcm"][0] if rm else None,
                           "err": float(np.max(np.hypot(ps - s, pl - l))), "faults": t["ours"][2]}
        m = n - n % SERIAL_PROJECT_CHUNK                       # the floors evaluate whole chunks only
        for key, label in (("floor_minimal", "floor: minimal"), ("floor_product", "floor: product")):
            rows[label] = {"ours": t[key][0] * n / m, "gdal": t["gdal"][0], "rpcm": t["rpcm"][0] if rm else None,
                           "err": float("nan"), "faults": t[key][2]}
        t = best_of({"ours": lambda: rpc.localize(s, l, hh), "gdal": lambda: tr.TransformPoints(0, image)}, repeat)
        ps, pl = rpc.project(*t["ours"][1], hh)
        rows["localize"] = {"ours": t["ours"][0], "gdal": t["gdal"][0], "rpcm": None,
                            "err": float(np.nanmax(np.hypot(ps - s, pl - l)))}
        image0 = np.column_stack([s, l, np.zeros(n)])
        rpc.localize_dem(s[:10], l[:10], dem)      # warm the DEM tile cache like GDAL's first call does
        tr_dem.TransformPoints(0, image0[:10])
        t = best_of({"ours": lambda: rpc.localize_dem(s, l, dem), "gdal": lambda: tr_dem.TransformPoints(0, image0)},
                    repeat)
        lo, la, hd = t["ours"][1]
        ok = np.isfinite(hd)
        ps, pl = rpc.project(lo[ok], la[ok], hd[ok])
        rows["localize_dem"] = {"ours": t["ours"][0], "gdal": t["gdal"][0], "rpcm": None,
                                "err": float(np.max(np.hypot(ps - s[ok], pl - l[ok])))}
    return {"n": n, "rows": rows, "rpcm": rm is not None}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--quick", action="store_true", help="3 rounds")
    args = ap.parse_args()
    n, repeat = (args.points, 3) if args.quick else (args.points, args.repeat)
    res = measure(n, repeat)
    print(f"{n} points, Pleiades Ventoux RPC, SRTM N44E005, one thread (GDAL {gdal.__version__}); load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'operation':<15} {'ours Mpt/s':>10} {'GDAL Mpt/s':>10} {'ours/GDAL':>9} {'rpcm Mpt/s':>10} "
          f"{'ours/rpcm':>9} {'round trip px':>13} {'page faults':>11}")
    for name, r in res["rows"].items():
        rp = (f"{n / r['rpcm'] / 1e6:>10.2f} {r['rpcm'] / r['ours']:>9.2f}" if r["rpcm"] else f"{'-':>10} {'-':>9}")
        print(f"{name:<15} {n / r['ours'] / 1e6:>10.2f} {n / r['gdal'] / 1e6:>10.2f} {r['gdal'] / r['ours']:>9.2f} "
              f"{rp} {r['err']:>13.2e} {r.get('faults', ''):>11}")
    if not res["rpcm"]:
        print("rpcm not installed (pip download rpcm --no-deps, unpack it on PYTHONPATH outside the repository)")
    else:
        print(f"issue 23 goal: project >= {GOAL_RPCM:g}x rpcm single-threaded")


if __name__ == "__main__":
    main()
