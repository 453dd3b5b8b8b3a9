"""Benchmark of pan-MS registration (issues 13, 20; METHODS §9): simulated GF7 crops registered end to end by
``gf4cal register-pan-ms`` with its default options (dense matching, model, correction.tif, ms_on_pan.tif,
ms_approx.RPB, cells.gpkg, plots), each in a fresh child process: wall time, peak memory (``ru_maxrss`` of that
child), matches/s, stage times from its report, the correction's RMS against the true field; then the scaling:
a straight-line fit of time against MS pixels over the sizes run, extrapolated to the full product (MS 7680²).
The largest size also gets a peer: ``gdalwarp -rpc`` of the same MS over the DEM onto as many pixels as
ms_on_pan.tif has (GDAL's own RPC resampler), against our ms_on_pan stage (which also applies the correction).

Default run (short): pan crops 512, 1024, 2048 px square (MS 128..512) across the first MS sub-CCD edge.
``--full``: 2048, 8192 and 16384 (MS 4096², the largest crop that renders here in under 10 minutes: rendering
the whole 30720² product took 1.5-2 h on 2 cores before issue 23; bench_gf7_full.py renders and registers
it). ``--sizes`` picks any. Crops are simulated once per size in
--workdir (the rendering time is reported, not counted in the registration's).

``--appliers-only``: at full size without rendering (the RPCs, DEM and truth of the full scene; a synthetic
4-band MS texture and an empty pan of the right size carrying their RPCs): the model from cells synthesised from
the truth, then correction.tif, ms_on_pan.tif and ms_approx.RPB, in a child process (time, peak memory) -- the
part of the job that does not depend on the matcher, whose rate (matches/s) the rendered run gives.

Usage: python bench/bench_panms.py [--full | --sizes N ...] [--cell PX] [--true-breaks] [--workdir DIR]
       [--workers N] [--appliers-only]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time


def _scene_kw(size):
    """Full scene, or a crop centred on the first MS sub-CCD edge (so the crop has a jump to model)."""
    if size >= 30720:
        return {"seed": 0, "size": None}
    return {"seed": 0, "size": (size, size), "crop_center_ms_px": 2560}


def build_unrendered(workdir):
    """Full-size GF7 RPCs + DEM (no rendering), a synthetic MS texture and an empty (sparse) pan carrying the RPCs."""
    import numpy as np
    from osgeo import gdal
    from gdal_gf4cal.simulate import write_scene
    gdal.UseExceptions()
    if os.path.exists(os.path.join(workdir, "ms", "fake.tif")):
        return
    write_scene("gf7", workdir, seed=0, n_gcps=10, render=False, reference_ortho=False)
    for name, (W, H), nb in (("pan", (30720, 30720), 1), ("ms", (7680, 7680), 4)):
        from gdal_gf4cal.rpc import RPCModel
        rpc = RPCModel.from_file(os.path.join(workdir, name, "scene.RPB"))
        ds = gdal.GetDriverByName("GTiff").Create(os.path.join(workdir, name, "fake.tif"), W, H, nb, gdal.GDT_Byte,
                                                  ["TILED=YES", "COMPRESS=DEFLATE", "SPARSE_OK=TRUE",
                                                   "BIGTIFF=YES"])
        ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
        if name == "ms":
            y, x = np.mgrid[0:512, 0:512]
            for y0 in range(0, H, 512):
                for x0 in range(0, W, 512):
                    v = (127 + 60 * np.sin((x + x0) / 3.1) * np.cos((y + y0) / 4.3)).astype(np.uint8)
                    for b in range(nb):
                        ds.GetRasterBand(b + 1).WriteArray(v, x0, y0)
        ds = None


APPLIERS_CHILD = r"""
import json, resource, sys, time
import numpy as np, pandas as pd
from gdal_gf4cal import panms
from gdal_gf4cal.dem import DEM
from gdal_gf4cal.rpc import RPCModel
from gdal_gf4cal.simulate.gf7 import make_gf7_scene, true_misregistration
d = sys.argv[1]
t = {}
t0 = time.perf_counter()
scene = make_gf7_scene(seed=0)
s, l = np.meshgrid(np.arange(120) * 64 + 32.0, np.arange(120) * 64 + 32.0)
ds, dl = true_misregistration(scene, s.ravel(), l.ravel())
rng = np.random.default_rng(0)
cells = pd.DataFrame({"sample": s.ravel(), "line": l.ravel(), "d_sample": ds + rng.normal(0, 0.03, ds.size),
                      "d_line": dl + rng.normal(0, 0.03, ds.size), "sigma_sample": 0.03, "sigma_line": 0.03,
                      "usable": True})
t["synthesise_cells"] = time.perf_counter() - t0
t0 = time.perf_counter()
model = panms.estimate(cells, ms_size=(7680, 7680))
t["estimate"] = time.perf_counter() - t0
pan, ms = d + "/pan/fake.tif", d + "/ms/fake.tif"
pan_rpc, ms_rpc = RPCModel.from_file(d + "/pan/scene.RPB"), RPCModel.from_file(d + "/ms/scene.RPB")
dem = DEM.from_user_input(d + "/dem.tif")
t0 = time.perf_counter()
panms.write_correction(model, d + "/out_correction.tif")
t["correction"] = time.perf_counter() - t0
t0 = time.perf_counter()
panms.resample_ms_on_pan(model, pan, ms, d + "/out_ms_on_pan.tif", pan_rpc=pan_rpc, ms_rpc=ms_rpc, dem=dem, ratio=4)
t["ms_on_pan"] = time.perf_counter() - t0
t0 = time.perf_counter()
rpc, err = panms.approximate_rpc(model, ms_rpc)
t["ms_approx_rpc"] = time.perf_counter() - t0
print(json.dumps({"stages_s": {k: round(v, 1) for k, v in t.items()}, "ms_approx_rpc": err,
                  "peak_memory_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2}))
"""


def appliers_only(workdir, workers):
    import tempfile
    build_unrendered(workdir)
    for f in ("out_correction.tif", "out_ms_on_pan.tif"):
        if os.path.exists(os.path.join(workdir, f)):
            os.remove(os.path.join(workdir, f))
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as fh:
        fh.write(APPLIERS_CHILD)
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, fh.name, workdir], capture_output=True, text=True)
    wall = time.perf_counter() - t
    os.remove(fh.name)
    if proc.returncode != 0:
        print(proc.stderr)
        return 1
    rep = json.loads(proc.stdout.strip().splitlines()[-1])
    from osgeo import gdal
    gdal.UseExceptions()
    t = time.perf_counter()
    gdal.Warp(os.path.join(workdir, "peer_warp.tif"), os.path.join(workdir, "ms", "fake.tif"), options=gdal.WarpOptions(
        rpc=True, transformerOptions=[f"RPC_DEM={os.path.join(workdir, 'dem.tif')}"], width=7680, height=7680,
        resampleAlg="cubic", creationOptions=["TILED=YES", "COMPRESS=DEFLATE", "BIGTIFF=YES"], multithread=True,
        warpOptions=[f"NUM_THREADS={workers}"]))
    peer = time.perf_counter() - t
    rep.update(wall_s=round(wall, 1), gdalwarp_rpc_s=round(peer, 1))
    print(json.dumps(rep, indent=1))
    st = rep["stages_s"]
    print(f"summary (full GF7 scene, appliers): estimate {st['estimate']} s, correction.tif {st['correction']} s, "
          f"ms_on_pan.tif {st['ms_on_pan']} s (gdalwarp -rpc of the same MS: {peer:.0f} s, ratio "
          f"{st['ms_on_pan'] / max(peer, 1e-9):.2f}), ms_approx.RPB {st['ms_approx_rpc']} s, peak "
          f"{rep['peak_memory_gb']:.2f} GB, child wall {wall:.0f} s")
    return 0


def build(workdir, size, workers) -> float:
    """Simulate the crop once (pan ``size``², MS (size/4)², across the first MS sub-CCD edge); the time taken."""
    from gdal_gf4cal.simulate.gf7 import write_gf7_scene
    done = os.path.join(workdir, "truth.json")
    if os.path.exists(done) and os.path.exists(os.path.join(workdir, "ms", "misregistration_truth.tif")):
        return float("nan")
    t = time.perf_counter()
    write_gf7_scene(workdir, **_scene_kw(size), workers=workers, n_gcps=10)
    return time.perf_counter() - t


#: A fresh child per run: ``RUSAGE_CHILDREN`` of this wrapper is the registration's own peak memory.
MEASURE = r"""
import json, resource, subprocess, sys, time
t = time.perf_counter()
p = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "register-pan-ms", *sys.argv[1:]], capture_output=True,
                   text=True)
r = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"rc": p.returncode, "stderr": p.stderr[-2000:], "wall_s": time.perf_counter() - t,
                  "peak_gb": r.ru_maxrss / 1024 ** 2, "cpu_s": r.ru_utime + r.ru_stime}))
"""


def _true_breaks(workdir) -> list:
    edges = json.load(open(os.path.join(workdir, "truth.json")))["gf7"]["misregistration_before"][
        "ms_sub_ccd_edges_px"]
    return ["--breaks", ",".join(f"{e:g}" for e in edges)] if edges else ["--sub-ccds", "1"]


def run_size(workdir, size, workers, options=(), threads=None) -> dict:
    """One registration of the crop in a fresh child (its wall time and peak memory), its report and accuracy;
    ``threads``: its ``GF4CAL_NUM_THREADS`` (None: the environment's, else all cores)."""
    import numpy as np
    from osgeo import gdal
    render_s = build(workdir, size, workers)
    pan, ms, dem = (os.path.join(workdir, p) for p in ("pan/scene.tif", "ms/scene.tif", "dem.tif"))
    out = os.path.join(workdir, "out")
    options = [o for opt in options for o in (_true_breaks(workdir) if opt == "TRUE_BREAKS" else [opt])]
    env = dict(os.environ, **({} if threads is None else {"GF4CAL_NUM_THREADS": str(threads)}))
    proc = subprocess.run([sys.executable, "-c", MEASURE, pan, ms, "--dem", dem, "--out", out, "--overwrite",
                           *options], capture_output=True, text=True, env=env)
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    if res["rc"] != 0:
        return {"pan_size": size, "error": res["stderr"].strip().splitlines()[-1:], "render_s": render_s}
    rep = json.load(open(os.path.join(out, "report.json")))
    tm = rep["timings_s"]
    mw, mh = rep["sizes"]["ms"]
    gdal.UseExceptions()                      # a script: process-wide GDAL state is ours
    e = (gdal.Open(os.path.join(out, "correction.tif")).ReadAsArray()[:2].astype(float)      # the reference band's
         - gdal.Open(os.path.join(workdir, "ms", "misregistration_truth.tif")).ReadAsArray())
    return {"pan_size": size, "ms_size": [mw, mh], "ms_pixels": mw * mh, "render_s": round(render_s, 1),
            "wall_s": round(res["wall_s"], 1), "cpu_s": round(res["cpu_s"], 1),
            "peak_memory_gb": round(res["peak_gb"], 3), "stages_s": tm,
            "matches": rep["n_matches"], "matches_per_s": round(rep["n_matches"] / max(tm["matching"], 1e-9)),
            "breaks_ms_px": rep["breaks_ms_px"],
            "correction_vs_truth_rms_px": [round(float(np.sqrt(np.mean(e[k] ** 2))), 4) for k in (0, 1)],
            "ms_on_pan": rep["sizes"]["ms_on_pan"]}


def peer_warp(workdir, ms_on_pan, workers) -> float:
    from osgeo import gdal
    w, h = ms_on_pan
    t = time.perf_counter()
    gdal.UseExceptions()
    gdal.Warp(os.path.join(workdir, "peer_warp.tif"), os.path.join(workdir, "ms", "scene.tif"),
              options=gdal.WarpOptions(rpc=True, transformerOptions=[f"RPC_DEM={workdir}/dem.tif"], width=w, height=h,
                                       resampleAlg="cubic", multithread=True,
                                       creationOptions=["TILED=YES", "COMPRESS=DEFLATE"],
                                       warpOptions=[f"NUM_THREADS={workers}"]))
    return time.perf_counter() - t


def scaling(rows) -> dict:
    """Straight-line fits of registration and rendering time against MS pixels, extrapolated to MS 7680²."""
    import numpy as np
    ok = [r for r in rows if "wall_s" in r]
    if len(ok) < 2:
        return {}
    px = np.array([r["ms_pixels"] for r in ok], float)
    out = {"sizes": len(ok)}
    for key in ("wall_s", "cpu_s", "render_s"):
        t = np.array([r[key] for r in ok], float)
        if not np.all(np.isfinite(t)):
            continue
        b, a = np.polyfit(px, t, 1)
        out[key] = {"s_per_mpx": round(b * 1e6, 2), "intercept_s": round(a, 1),
                    "full_product_s": round(a + b * 7680 ** 2)}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=None, help="pan crop sizes (default 512 1024 2048)")
    ap.add_argument("--full", action="store_true", help="sizes 2048 8192 16384 (the largest renders in < 10 min)")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--appliers-only", action="store_true", help="full size, no rendering: the appliers alone")
    ap.add_argument("--cell", type=int, help="register-pan-ms --cell (default: the command's default)")
    ap.add_argument("--true-breaks", action="store_true",
                    help="give the crop's true sub-CCD edges as --breaks (default: the command finds them)")
    a = ap.parse_args(argv)
    options = (["--cell", str(a.cell)] if a.cell else []) + (["TRUE_BREAKS"] if a.true_breaks else [])
    root = a.workdir or os.path.join(os.environ.get("TMPDIR", "/tmp"), "gf4cal_bench_panms")
    if a.appliers_only:
        workdir = root + "_appliers"
        os.makedirs(workdir, exist_ok=True)
        return appliers_only(workdir, a.workers)
    sizes = a.sizes or ([2048, 8192, 16384] if a.full else [512, 1024, 2048])
    rows = []
    for size in sorted(sizes):
        workdir = os.path.join(root, f"pan{size}")
        os.makedirs(workdir, exist_ok=True)
        rows.append(run_size(workdir, size, a.workers, options))
        print(json.dumps(rows[-1]), flush=True)
    big = rows[-1]
    if "wall_s" in big:
        big["gdalwarp_rpc_s"] = round(peer_warp(os.path.join(root, f"pan{big['pan_size']}"), big["ms_on_pan"],
                                                a.workers), 1)
    fit = scaling(rows)
    print(json.dumps({"scaling": fit}, indent=1))
    for r in rows:
        if "wall_s" not in r:
            print(f"pan {r['pan_size']}: register-pan-ms failed: {r['error']}")
            continue
        print(f"pan {r['pan_size']}² / MS {r['ms_size'][0]}²: end to end {r['wall_s']:.1f} s, peak "
              f"{r['peak_memory_gb']:.2f} GB, {r['matches_per_s']} matches/s, correction vs truth RMS "
              f"{r['correction_vs_truth_rms_px']} px (rendering {r['render_s']} s)")
    if fit.get("wall_s"):
        print(f"scaling: {fit['wall_s']['s_per_mpx']} s per MS Mpx -> full product (MS 7680²) ~"
              f"{fit['wall_s']['full_product_s']} s (target 600 s)" + (
                  f"; rendering ~{fit['render_s']['full_product_s']} s" if fit.get("render_s") else ""))
    if "gdalwarp_rpc_s" in big:
        print(f"peer at pan {big['pan_size']}: ms_on_pan+correction {big['stages_s']['correction_and_ms_on_pan']}"
              f" s vs gdalwarp -rpc {big['gdalwarp_rpc_s']} s")
    return 0 if all("wall_s" in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
