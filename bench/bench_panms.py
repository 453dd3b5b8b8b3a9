"""Benchmark of pan-MS registration (issue 13, METHODS §9): a simulated GF7 scene registered end to end by
``gf4cal register-pan-ms`` (dense matching, model, correction.tif, ms_on_pan.tif, ms_approx.RPB, cells.gpkg,
plots) in a child process: wall time, peak memory (the child's ``ru_maxrss``), matches/s and cells/s, and the
stage times from its report. Peer measured in the same run: ``gdalwarp -rpc`` of the same MS image over the DEM
onto as many pixels as ms_on_pan.tif has (GDAL's own RPC resampler), against our ms_on_pan stage (which also
applies the correction).

Targets (issue 13): full scene (pan 30720², MS 7680²) in <= 10 min with peak memory <= 3 GB, reading windows only.
The scene is simulated once in --workdir (rendering the full scene takes long: pass ``--size`` for a crop; the
timings then scale with the MS pixel count).

``--appliers-only``: at full size without rendering (the RPCs, DEM and truth of the full scene; a synthetic
4-band MS texture and an empty pan of the right size carrying their RPCs): the model from cells synthesised from
the truth, then correction.tif, ms_on_pan.tif and ms_approx.RPB, in a child process (time, peak memory) -- the
part of the job that does not depend on the matcher, whose rate (matches/s) the rendered run gives.

Usage: python bench/bench_panms.py [--size 30720] [--workdir DIR] [--workers N] [--cell 64] [--appliers-only]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time


def _scene_kw(size):
    """Full scene, or a crop centred on the first MS sub-CCD edge (so the crop has a jump to model)."""
    if size >= 30720:
        return {"seed": 0, "size": None}
    return {"seed": 0, "size": (size, size), "crop_center_ms_px": 2560}


def _breaks(size):
    from gdal_gf4cal.simulate.gf7 import make_gf7_scene
    edges = make_gf7_scene(**_scene_kw(size)).image("ms").true.camera.edges_in_image()
    return ["--breaks", ",".join(f"{e:g}" for e in edges)] if edges else ["--sub-ccds", "1"]


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


def build(workdir, size, workers):
    from gdal_gf4cal.simulate.gf7 import write_gf7_scene
    done = os.path.join(workdir, "truth.json")
    if os.path.exists(done) and os.path.exists(os.path.join(workdir, "ms", "misregistration_truth.tif")):
        return
    t = time.perf_counter()
    write_gf7_scene(workdir, **_scene_kw(size), workers=workers)
    print(f"simulated the scene in {time.perf_counter() - t:.0f} s (not part of the benchmark)", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=30720, help="pan size (default: full GF7, 30720)")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cell", type=int, default=64)
    ap.add_argument("--appliers-only", action="store_true", help="full size, no rendering: the appliers alone")
    a = ap.parse_args(argv)
    workdir = a.workdir or os.path.join(os.environ.get("TMPDIR", "/tmp"), f"gf4cal_bench_panms_{a.size}" + (
        "_appliers" if a.appliers_only else ""))
    os.makedirs(workdir, exist_ok=True)
    if a.appliers_only:
        return appliers_only(workdir, a.workers)
    build(workdir, a.size, a.workers)
    pan, ms, dem = (os.path.join(workdir, p) for p in ("pan/scene.tif", "ms/scene.tif", "dem.tif"))
    out = os.path.join(workdir, "out")
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "register-pan-ms", pan, ms, "--dem", dem,
                           "--out", out, "--cell", str(a.cell), "--overwrite", *_breaks(a.size)], capture_output=True, text=True)
    wall = time.perf_counter() - t
    peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024 ** 2
    if proc.returncode != 0:
        print(proc.stderr)
        return 1
    rep = json.load(open(os.path.join(out, "report.json")))
    tm = rep["timings_s"]
    mw, mh = rep["sizes"]["ms"]
    # peer: GDAL's RPC warp of the MS over the DEM onto as many pixels as ms_on_pan.tif
    from osgeo import gdal
    gdal.UseExceptions()
    w, h = rep["sizes"]["ms_on_pan"]
    t = time.perf_counter()
    gdal.Warp(os.path.join(workdir, "peer_warp.tif"), ms, options=gdal.WarpOptions(
        rpc=True, transformerOptions=[f"RPC_DEM={dem}"], width=w, height=h, resampleAlg="cubic",
        creationOptions=["TILED=YES", "COMPRESS=DEFLATE"], multithread=True,
        warpOptions=[f"NUM_THREADS={a.workers}"]))
    peer = time.perf_counter() - t
    ours_resample = tm["correction_and_ms_on_pan"]
    last = rep["steps"][-1]
    print(json.dumps({"ms_size": [mw, mh], "wall_s": round(wall, 1), "peak_memory_gb": round(peak_gb, 2),
                      "stages_s": tm, "matches": rep["n_matches"], "cells": rep["n_cells"],
                      "matches_per_s": round(rep["n_matches"] / max(tm["matching"], 1e-9)),
                      "cells_per_s": round(rep["n_cells"] / max(tm["matching"] + tm["estimate"], 1e-9)),
                      "after": {"rms_sample_px": last["rms_sample_px"], "rms_line_px": last["rms_line_px"],
                                "p_le_0.25": last["p_le_0.25"]},
                      "gdalwarp_rpc_s": round(peer, 1), "ours_correction_and_ms_on_pan_s": ours_resample}, indent=1))
    full = 7680 * 7680 / (mw * mh)
    print(f"summary: MS {mw}x{mh}: end to end {wall:.0f} s (x{full:.0f} pixels for the full scene: ~{wall * full:.0f}"
          f" s if linear; target 600 s), peak {peak_gb:.2f} GB (target 3), {rep['n_matches'] / tm['matching']:.0f}"
          f" matches/s, ms_on_pan+correction {ours_resample:.1f} s vs gdalwarp -rpc {peer:.1f} s "
          f"(ratio {ours_resample / max(peer, 1e-9):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
