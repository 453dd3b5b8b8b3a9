"""Line of sight x DSM with holes (issue 19): localize_dem against GDAL's RPC_DEM, measured in the same run.

A synthetic 0.5 m urban DSM (400 x 400 px, UTM 31N; buildings 5-40 m on the real SRTM terrain of Mont Ventoux,
11 % no-data in blobs at building walls, gdal_gf4cal.simulate.dsm, seed 0) under the real Pleiades Ventoux RPC.
GDAL cannot bridge holes, so it gets the same DSM hole-filled (GDAL FillNodata); we get the DSM with its holes.
  dsm 20k         20,000 image points over the DSM's footprint
  dsm 200k half   200,000 image points, half of them outside the DSM's coverage (NaN for both)
7 interleaved runs each (bench/_timing.py); ours/GDAL is the median of the 7 pairs' ratios: the machine is shared,
compare the ratios (same run), not absolute rates. "median m": median distance between our points and GDAL's
where both found one (different surfaces in the holes: ours bridged, GDAL's filled).
Goal (issue 19): ours/GDAL >= 1.

Run: .venv/bin/python bench/bench_localize_dsm.py
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from osgeo import gdal

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import timed  # noqa: E402

from gdal_gf4cal import DEM, RPCModel  # noqa: E402
from gdal_gf4cal.simulate.dsm import urban_dsm  # noqa: E402

gdal.UseExceptions()
DATA = Path(__file__).resolve().parent.parent / "tests" / "data"
CENTER = (5.2872, 44.1357)


def image_box(rpc, dem, h):
    """Image bounding box of the DSM's footprint at height h."""
    b = dem.bounds_lonlat()
    s, l = rpc.project(np.array([b[0], b[2], b[0], b[2]]), np.array([b[1], b[1], b[3], b[3]]), np.full(4, h))
    return s.min(), s.max(), l.min(), l.max()


def main():
    rpc = RPCModel.from_file(DATA / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    terrain = DEM.from_file(DATA / "dem" / "N44E005.hgt", geoid="egm96")
    tmp = Path(tempfile.mkdtemp())
    holed, filled = str(tmp / "dsm.tif"), str(tmp / "dsm_filled.tif")
    info = urban_dsm(holed, terrain, CENTER, filled_path=filled, seed=0)
    w, h = rpc.image_size
    ds = gdal.GetDriverByName("MEM").Create("", w, h)
    ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    tr = gdal.Transformer(ds, None, ["METHOD=RPC", f"RPC_DEM={filled}", "RPC_PIXEL_ERROR_THRESHOLD=1e-6",
                                     "RPC_DEM_APPLY_VDATUM_SHIFT=FALSE"])
    dem = DEM.from_file(holed, nodata="nan")
    s0, s1, l0, l1 = image_box(rpc, dem, float(np.mean(info["height_range"])))
    rng = np.random.default_rng(0)
    cases = {"dsm 20k": (rng.uniform(s0, s1, 20_000), rng.uniform(l0, l1, 20_000))}
    n = 200_000     # half of the box outside the DSM: sample twice as wide a box
    cases["dsm 200k half"] = (rng.uniform(s0, s1 + (s1 - s0), n), rng.uniform(l0, l1, n))
    t = time.perf_counter()
    rpc.localize_dem(cases["dsm 20k"][0][:10], cases["dsm 20k"][1][:10], dem)   # first call: reads the DSM
    t_first = time.perf_counter() - t
    print(f"DSM 400 x 400 px at 0.5 m, {info['hole_fraction']:.1%} no-data, {info['n_buildings']} buildings, "
          f"heights {info['height_range'][0]:.0f}..{info['height_range'][1]:.0f} m (GDAL {gdal.__version__}); "
          f"first call (reads the DSM) {t_first * 1e3:.0f} ms")
    print(f"{'case':<14} {'points':>7} {'ours ms':>8} {'GDAL ms':>8} {'ours/GDAL':>9} {'ours found':>10} "
          f"{'GDAL found':>10} {'median m':>8}")
    for name, (s, l) in cases.items():
        pts = np.column_stack([s, l, np.zeros(s.size)])
        tr.TransformPoints(0, pts[:10])
        # Interleaved runs (the machine is shared): the ratio is the median of each pair's ratio.
        pairs = [(timed(lambda: rpc.localize_dem(s, l, dem), 1), timed(lambda: tr.TransformPoints(0, pts), 1))
                 for _ in range(7)]
        (_, (lon, lat, hh)), (_, (out, ok)) = pairs[-1]
        t_ours = float(np.median([p[0][0] for p in pairs]))
        t_gdal = float(np.median([p[1][0] for p in pairs]))
        ratio = float(np.median([p[1][0] / p[0][0] for p in pairs]))
        out, ok = np.asarray(out), np.asarray(ok, dtype=bool)
        both = ok & np.isfinite(hh)
        d = np.hypot((out[both, 0] - lon[both]) * 111320.0 * np.cos(np.radians(lat[both])),
                     (out[both, 1] - lat[both]) * 110574.0)
        print(f"{name:<14} {s.size:>7} {t_ours * 1e3:>8.1f} {t_gdal * 1e3:>8.1f} {ratio:>9.2f} "
              f"{np.isfinite(hh).mean():>10.1%} {ok.mean():>10.1%} {np.median(d):>8.3f}")


if __name__ == "__main__":
    main()
