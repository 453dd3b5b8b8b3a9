"""collect-gcps against AROSICS COREG_LOCAL on a real Sentinel-2 pair (issue 23), and which sub-pixel estimator is
right on a real texture shifted by known amounts.

Pair: AROSICS's own test case ``testcase_inter1_S2A_S2A`` (Sentinel-2A L1C band 3, T33UUU, 2016-06-08 reference and
2016-05-29 target, 10 m, UTM 33N; from the arosics 1.0.0 sdist, tests/data; Apache-2.0). ``--data`` is the folder
holding the two GeoTIFFs. The target is an ortho: its "RPC" is fitted to its own geotransform (constant height),
so collect-gcps measures exactly what COREG_LOCAL measures: the target's displacement against the reference.

Both run on the same tie points (AROSICS's grid: target pixel corners ``0, grid, 2 grid, ...``), the same window
(64 and 256 px), one core each (AROSICS ``CPUs=1``, ours ``workers=1``), in separate child processes, interleaved
(``--repeat`` rounds; the best time counts; wall time and, less sensitive to a shared machine's load, the
process's CPU time). Time per *valid* tie point: ours = accepted, non-outlier GCPs;
AROSICS = rows of ``CoRegPoints_table`` with a shift and ``OUTLIER == False``. Point by point, on points valid in
both: our offset and AROSICS's in metres (sign: AROSICS ``X_SHIFT_M`` is the correction of the target, so
``ours_dx * 10 = -X_SHIFT_M`` and ``ours_dy * 10 = +Y_SHIFT_M``, rows pointing south).

``--truth``: a crop of the reference shifted by known sub-pixel amounts (exact Fourier shift, and GDAL bilinear
and cubic warps of a shifted geotransform); both estimators on the same 64-px windows; error against the truth.

AROSICS runs in its own venv (``--arosics-python``, default /work/wt/arosics-venv/bin/python); without it the
AROSICS side is skipped with a clear line and ours is still timed.

Usage: python bench/bench_arosics.py [--data DIR] [--windows 64 256] [--grid 128] [--repeat 2] [--truth]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

REF = "ref_S2A_20160608T153121_T33UUU_sub.tif"
TGT = "tgt_S2A_20160529T153631_T33UUU_sub.tif"
HEIGHT = 50.0
DEFAULT_DATA = "/work/wt/arosics-data/arosics-1.0.0/tests/data/testcase_inter1_S2A_S2A"
DEFAULT_PY = "/work/wt/arosics-venv/bin/python"


def _pair(args):
    return (args.ref or os.path.join(args.data, REF)), (args.tgt or os.path.join(args.data, TGT))


# ------------------------------------------------------------------------------------------------ AROSICS side
def _arosics_local(args):
    """COREG_LOCAL on the pair: its table and its time (runs in the AROSICS venv)."""
    from arosics import COREG_LOCAL
    ref, tgt = _pair(args)
    t, c0 = time.perf_counter(), time.process_time()
    cr = COREG_LOCAL(ref, tgt, grid_res=args.grid, window_size=(args.window, args.window), max_shift=5,
                     nodata=(0, 0), CPUs=1, progress=False, q=True)
    tbl = cr.CoRegPoints_table
    dt, cpu = time.perf_counter() - t, time.process_time() - c0
    shifted = tbl["X_SHIFT_M"] != cr.outFillVal
    ok = shifted & ~tbl["OUTLIER"].astype(bool)
    sel = tbl[ok]
    return dict(seconds=dt, cpu=cpu, points=int(len(tbl)), valid=int(ok.sum()), shifted=int(shifted.sum()),
                x_im=sel["X_IM"].tolist(),
                y_im=sel["Y_IM"].tolist(), x_m=sel["X_SHIFT_M"].tolist(), y_m=sel["Y_SHIFT_M"].tolist())


def _arosics_truth(args):
    """COREG (one window) on every shifted copy of the crop written by the parent (``--npz``)."""
    from arosics import COREG
    from geoarray import GeoArray
    from osgeo import osr
    z = np.load(args.npz)
    fixed, moving, centers = z["fixed"], z["moving"], z["centers"]
    w = int(z["window"])
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(32633)
    gt = (0.0, 10.0, 0.0, 0.0, 0.0, -10.0)
    out = np.full(moving.shape[:1] + (centers.shape[0], 2), np.nan)
    ga0 = GeoArray(fixed.astype(np.float32), gt, srs.ExportToWkt())
    for k in range(moving.shape[0]):
        ga1 = GeoArray(moving[k].astype(np.float32), gt, srs.ExportToWkt())
        for j, (cx, cy) in enumerate(centers):
            cr = COREG(ga0, ga1, wp=(gt[0] + cx * 10.0, gt[3] - cy * 10.0), ws=(w, w), max_shift=5, q=True,
                       progress=False, CPUs=1, ignore_errors=True, calc_corners=False)
            cr.calculate_spatial_shifts()
            if cr.success:
                # AROSICS gives the correction of the target: the content moved by -x_shift_px, -y_shift_px.
                out[k, j] = (-cr.x_shift_px, -cr.y_shift_px)
    return dict(shifts=out.tolist())


# ------------------------------------------------------------------------------------------------ our side
def _target_rpc(path):
    """RPC of an ortho: fitted to its geotransform (UTM -> lon/lat) at one height; GDAL pixel convention."""
    from osgeo import gdal, osr
    from gdal_gf4cal.rpc_fit import fit_rpc
    ds = gdal.Open(path)
    gt = ds.GetGeoTransform()
    W, H = ds.RasterXSize, ds.RasterYSize
    s, l = np.meshgrid(np.linspace(0, W, 41), np.linspace(0, H, 41))
    s, l = s.ravel(), l.ravel()
    src = osr.SpatialReference(wkt=ds.GetProjection())
    dst = osr.SpatialReference()
    dst.ImportFromEPSG(4326)
    dst.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    src.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    ct = osr.CoordinateTransformation(src, dst)
    pts = np.array(ct.TransformPoints(np.column_stack([gt[0] + s * gt[1], gt[3] + l * gt[5]])))
    rpc, rep = fit_rpc(pts[:, 0], pts[:, 1], np.full(s.size, HEIGHT), s, l)
    return rpc


def _our_run(args, rpc, centers):
    import dataclasses
    from gdal_gf4cal.matching import assemble_gcps, plan_tiles, run_tiles
    ref, tgt = _pair(args)
    t, c0 = time.perf_counter(), time.process_time()
    specs, ctx = plan_tiles(tgt, rpc, ref, HEIGHT, args.grid, args.window, search_px=16, margin_px=0)
    # AROSICS's tie points instead of our centred grid (same density, point-by-point comparison).
    per = 64
    specs = [dataclasses.replace(specs[0], centers=centers[k:k + per]) for k in range(0, len(centers), per)]
    g = assemble_gcps(run_tiles(specs, workers=1), ctx)
    return time.perf_counter() - t, time.process_time() - c0, g


def _ours(args):
    from osgeo import gdal
    tgt = _pair(args)[1]
    ds = gdal.Open(tgt)
    W, H = ds.RasterXSize, ds.RasterYSize
    rpc = _target_rpc(tgt)
    gx, gy = np.meshgrid(np.arange(0, W + args.grid, args.grid), np.arange(0, H + args.grid, args.grid))
    # Every tie point of AROSICS's grid: windows are shrunk about their centre where they cross an edge (or
    # no-data) of either image, as AROSICS does; points outside the overlap are flagged before any read.
    c = np.column_stack([gx.ravel(), gy.ravel()]).astype(float)
    c = c[(c[:, 0] <= W) & (c[:, 1] <= H)]
    _our_run(args, rpc, c[:64])  # warm-up: imports, caches
    dt, cpu, g = _our_run(args, rpc, c)
    ok = ~g["outlier"].to_numpy(bool)
    gg = g[ok]
    return dict(seconds=dt, cpu=cpu, points=int(g.attrs["windows"]["total"]), valid=int(ok.sum()),
                x_im=(gg["sample"] - gg["dsample"]).tolist(), y_im=(gg["line"] - gg["dline"]).tolist(),
                dx=gg["dsample"].tolist(), dy=gg["dline"].tolist())


def _shifted_stack(crop, shifts, method):
    """``crop`` with its content moved by ``(sx, sy)`` px (x right, y down) for every shift: exact Fourier shift,
    or GDAL's bilinear / cubic warp onto a grid offset by the shift."""
    from osgeo import gdal
    from scipy import ndimage
    out = []
    H, W = crop.shape
    for sx, sy in shifts:
        if method == "fourier":
            f = ndimage.fourier_shift(np.fft.fft2(crop), (sy, sx))
            out.append(np.fft.ifft2(f).real)
            continue
        src = gdal.GetDriverByName("MEM").Create("", W, H, 1, gdal.GDT_Float64)
        src.SetGeoTransform((0.0, 1.0, 0.0, 0.0, 0.0, -1.0))
        src.GetRasterBand(1).WriteArray(crop)
        # Output pixel (x, y) samples the input at (x - sx, y - sy): origin moved by -sx east, +sy north.
        dst = gdal.GetDriverByName("MEM").Create("", W, H, 1, gdal.GDT_Float64)
        dst.SetGeoTransform((-sx, 1.0, 0.0, sy, 0.0, -1.0))
        gdal.ReprojectImage(src, dst, None, None, {"bilinear": gdal.GRA_Bilinear, "cubic": gdal.GRA_Cubic}[method])
        out.append(dst.GetRasterBand(1).ReadAsArray())
    return np.array(out)


def _truth_setup(args):
    from osgeo import gdal
    ds = gdal.Open(os.path.join(args.data, REF))
    n = 448
    crop = ds.GetRasterBand(1).ReadAsArray(args.crop[0], args.crop[1], n, n).astype(np.float64)
    steps = np.round(np.arange(10) * 0.1, 1)
    shifts = [(s, 0.0) for s in steps] + [(0.0, s) for s in steps] + [(s, s) for s in steps[1:]]
    w = 64
    cs = np.arange(n // 2 - 96, n // 2 + 97, 96)  # 3 x 3 windows, corners >= 96 px from the crop's edge
    cx, cy = np.meshgrid(cs, cs)
    centers = np.column_stack([cx.ravel(), cy.ravel()]).astype(float)
    return crop, shifts, centers, w


def _our_truth(crop, moving, centers, w):
    from gdal_gf4cal.matching.correlate import phase_correlate
    x0 = (centers[:, 0] - w // 2).astype(int)
    y0 = (centers[:, 1] - w // 2).astype(int)
    a = np.array([crop[y:y + w, x:x + w] for x, y in zip(x0, y0)])
    b = np.array([[m[y:y + w, x:x + w] for x, y in zip(x0, y0)] for m in moving])
    r = phase_correlate(np.broadcast_to(a, b.shape), b)
    return np.stack([r.dx, r.dy], axis=-1)


def truth(args):
    crop, shifts, centers, w = _truth_setup(args)
    truth_xy = np.array(shifts)
    have = os.path.exists(args.arosics_python)
    print(f"real texture: {REF} crop at {tuple(args.crop)}, 448 px; 9 windows of {w} px; shifts 0.0..0.9 px in x, "
          "in y and in both")
    for method in ("fourier", "bilinear", "cubic"):
        moving = _shifted_stack(crop, shifts, method)
        ours = _our_truth(crop, moving, centers, w)
        e_o = ours - truth_xy[:, None, :]
        res = {"ours": e_o}
        if have:
            with tempfile.TemporaryDirectory() as tmp:
                npz = os.path.join(tmp, "t.npz")
                np.savez(npz, fixed=crop, moving=moving, centers=centers, window=w)
                r = _child_json([args.arosics_python, os.path.abspath(__file__), "--child", "arosics_truth", "--npz",
                                 npz, "--data", args.data])
            res["AROSICS"] = np.array(r["shifts"]) - truth_xy[:, None, :]
        for name, e in res.items():
            bx = np.nanmean(e[..., 0], axis=1)
            by = np.nanmean(e[..., 1], axis=1)
            print(f"{method:8s} {name:7s} error (px): mean x {np.nanmean(e[..., 0]):+.3f} y {np.nanmean(e[..., 1]):+.3f}"
                  f"  max |x| {np.nanmax(np.abs(e[..., 0])):.3f} |y| {np.nanmax(np.abs(e[..., 1])):.3f}  per shift "
                  f"(x-only rows: x err) {' '.join(f'{v:+.2f}' for v in bx[:10])}  (y-only rows: y err) "
                  f"{' '.join(f'{v:+.2f}' for v in by[10:20])}")
        if not have:
            print("AROSICS not installed, skipped")


def _closure_pair(args, tmp, steps):
    """Crops of the pair inside their overlap; the target's crop moved by ``(t, t)`` px (exact Fourier shift) for
    every ``t`` of ``steps``. Returns the reference crop's path and the target crops' paths."""
    from osgeo import gdal
    from scipy import ndimage
    x, y, n = args.closure_win
    ref = os.path.join(tmp, "ref.tif")
    # Target pixel (s, l) is reference pixel (s + 544, l - 449): both grids are the same 10 m lattice.
    gdal.Translate(ref, os.path.join(args.data, REF), srcWin=[x + 544, y - 449, n, n], outputType=gdal.GDT_Float32)
    base = os.path.join(tmp, "tgt.tif")
    gdal.Translate(base, os.path.join(args.data, TGT), srcWin=[x, y, n, n], outputType=gdal.GDT_Float32)
    src = gdal.Open(base)
    a = src.GetRasterBand(1).ReadAsArray().astype(np.float64)
    paths = []
    for t in steps:
        out = os.path.join(tmp, f"tgt_{t:.2f}.tif")
        ds = gdal.GetDriverByName("GTiff").CreateCopy(out, src)
        moved = np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(a), (t, t))).real
        ds.GetRasterBand(1).WriteArray(np.maximum(moved, 1.0).astype(np.float32))
        ds = None
        paths.append(out)
    return ref, paths


def closure(args):
    """Both estimators on the real pair with the target moved by known amounts: a right estimator's offsets move
    by exactly the amounts applied (its offset minus the amount stays constant)."""
    steps = [0.0, 0.25, 0.5, 0.75]
    print(f"load average {os.getloadavg()[0]:.2f}; real pair crops {args.closure_win}, target moved by (t, t) px")
    with tempfile.TemporaryDirectory() as tmp:
        ref, tgts = _closure_pair(args, tmp, steps)
        for w in args.windows:
            rows = []
            for t, tgt in zip(steps, tgts):
                base = ["--data", args.data, "--window", str(w), "--grid", str(args.grid), "--ref", ref, "--tgt", tgt]
                o = _child_json([sys.executable, os.path.abspath(__file__), "--child", "ours"] + base)
                a = _child_json([args.arosics_python, os.path.abspath(__file__), "--child", "arosics"] + base)
                ko = {(round(x), round(y)): (dx, dy) for x, y, dx, dy in zip(o["x_im"], o["y_im"], o["dx"], o["dy"])}
                pr = np.array([ko[(round(x), round(y))] + (-xm / 10.0, ym / 10.0) for x, y, xm, ym
                               in zip(a["x_im"], a["y_im"], a["x_m"], a["y_m"]) if (round(x), round(y)) in ko])
                rows.append((t, len(pr), np.median(pr, axis=0) - np.array([t, t, t, t])))
            for t, k, m in rows:
                print(f"window {w}: t = {t:.2f} px, {k} common points: offset - t (median px) ours x {m[0]:+.3f} "
                      f"y {m[1]:+.3f} | AROSICS x {m[2]:+.3f} y {m[3]:+.3f}")
            m = np.array([r[2] for r in rows])
            print(f"window {w}: spread over t (max - min, px): ours x {np.ptp(m[:, 0]):.3f} y {np.ptp(m[:, 1]):.3f} | "
                  f"AROSICS x {np.ptp(m[:, 2]):.3f} y {np.ptp(m[:, 3]):.3f}; mean over t: ours "
                  f"({m[:, 0].mean():+.3f}, {m[:, 1].mean():+.3f}) AROSICS ({m[:, 2].mean():+.3f}, {m[:, 3].mean():+.3f})",
                  flush=True)


# ------------------------------------------------------------------------------------------------ parent
def _child_json(cmd):
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd[:4])} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def _compare(o, a):
    """Point-by-point differences (m) on the tie points valid in both."""
    ko = {(round(x), round(y)): (dx, dy) for x, y, dx, dy in zip(o["x_im"], o["y_im"], o["dx"], o["dy"])}
    pairs = [(ko[(round(x), round(y))], (xm, ym)) for x, y, xm, ym in zip(a["x_im"], a["y_im"], a["x_m"], a["y_m"])
             if (round(x), round(y)) in ko]
    if not pairs:
        return "no common valid point"
    d = np.array([[10.0 * od[0] + am[0], 10.0 * od[1] - am[1]] for od, am in pairs])  # ours - AROSICS, metres
    return (f"{len(pairs)} common points: ours - AROSICS x {np.median(d[:, 0]):+.2f} m (median; MAD "
            f"{np.median(np.abs(d[:, 0] - np.median(d[:, 0]))):.2f}), y {np.median(d[:, 1]):+.2f} m (MAD "
            f"{np.median(np.abs(d[:, 1] - np.median(d[:, 1]))):.2f}) [+y = south]")


def speed(args):
    have = os.path.exists(args.arosics_python) and subprocess.run(
        [args.arosics_python, "-c", "import arosics"], capture_output=True).returncode == 0
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}; pair {args.data}")
    if not have:
        print(f"AROSICS not installed ({args.arosics_python}), skipped: timing ours only")
    for w in args.windows:
        best_o, best_a, best_s, cpu_o, cpu_a, o, a = np.inf, np.inf, np.inf, np.inf, np.inf, None, None
        base = ["--data", args.data, "--window", str(w), "--grid", str(args.grid)]
        for _ in range(args.repeat):  # interleaved rounds
            o = _child_json([sys.executable, os.path.abspath(__file__), "--child", "ours"] + base)
            best_o = min(best_o, o["seconds"] / max(o["valid"], 1))
            cpu_o = min(cpu_o, o["cpu"] / max(o["valid"], 1))
            if have:
                a = _child_json([args.arosics_python, os.path.abspath(__file__), "--child", "arosics"] + base)
                best_a = min(best_a, a["seconds"] / max(a["valid"], 1))
                best_s = min(best_s, a["seconds"] / max(a["shifted"], 1))
                cpu_a = min(cpu_a, a["cpu"] / max(a["valid"], 1))
        line = (f"window {w}, grid {args.grid}: ours {o['valid']}/{o['points']} valid, {best_o * 1e3:.2f} ms per "
                f"valid point")
        if have:
            line += (f"; AROSICS {a['valid']}/{a['points']} valid, {best_a * 1e3:.2f} ms per valid point; ratio "
                     f"{best_a / best_o:.1f}x (counting every AROSICS point with a shift, its outliers too: "
                     f"{a['shifted']} points, {best_s / best_o:.1f}x); CPU time per valid point: ours "
                     f"{cpu_o * 1e3:.2f} ms, AROSICS {cpu_a * 1e3:.2f} ms: {cpu_a / cpu_o:.1f}x (less sensitive to "
                     f"the other users' load); {_compare(o, a)}")
        print(line, flush=True)
    print(f"load average after {os.getloadavg()[0]:.2f}")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=DEFAULT_DATA)
    p.add_argument("--windows", type=int, nargs="+", default=[64, 256])
    p.add_argument("--window", type=int, default=64)
    p.add_argument("--grid", type=int, default=128, help="tie-point spacing, px (both methods)")
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--truth", action="store_true", help="known sub-pixel shifts of a real texture")
    p.add_argument("--crop", type=int, nargs=2, default=[900, 1500], help="truth crop's corner in the reference")
    p.add_argument("--closure-win", type=int, nargs=3, default=[300, 1000, 1152], help="target crop x y size")
    p.add_argument("--arosics-python", default=DEFAULT_PY)
    p.add_argument("--child", choices=("ours", "arosics", "arosics_truth"))
    p.add_argument("--npz")
    p.add_argument("--ref")
    p.add_argument("--tgt")
    p.add_argument("--closure", action="store_true",
                   help="the real pair with the target moved by known sub-pixel amounts (Fourier shift)")
    args = p.parse_args()
    if args.child:
        fn = {"ours": _ours, "arosics": _arosics_local, "arosics_truth": _arosics_truth}[args.child]
        print(json.dumps(fn(args)))
        return
    if not os.path.exists(os.path.join(args.data, REF)):
        raise SystemExit(f"pair not found in {args.data}: give --data (AROSICS sdist tests/data/testcase_inter1_S2A_S2A)")
    if args.truth:
        truth(args)
    elif args.closure:
        closure(args)
    else:
        speed(args)


if __name__ == "__main__":
    main()
