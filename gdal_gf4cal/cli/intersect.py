"""``gf4cal intersect``: least-squares forward intersection of tie points from two or more RPC images (METHODS §7)."""
from __future__ import annotations

import math

from ..workflows import intersect_files
from . import print_warnings

NAME = "intersect"
HELP = "Intersect tie points seen in two or more RPC images; planar/height precision (and errors vs truth)."


def add_parser(parser):
    parser.add_argument("--rpc", nargs="+", required=True, metavar="RPC",
                        help="two or more images / RPC files, in the order of the points file's image numbers; "
                             "IMAGE=RPC for an image whose RPC is a separate file (a crop and its product's .geom: "
                             "the crop's origin is applied)")
    parser.add_argument("--points", required=True,
                        help="CSV: id,sample_1,line_1,sample_2,line_2,... or id,image,sample,line "
                             "(GDAL pixel convention; optional lon,lat,h truth columns)")
    parser.add_argument("--sigma", type=float, default=1.0, help="image measurement sigma in px (default 1)")
    parser.add_argument("--out", help="write the points (.csv, .gpkg or .geojson)")
    parser.add_argument("--report", help="write report.json")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs (never an input)")


def run(args) -> int:
    rep = intersect_files(args.rpc, args.points, out=args.out, sigma_px=args.sigma, report=args.report,
                          overwrite=args.overwrite)
    print(f"{rep['n_intersected']} of {rep['n_points']} points intersected from {len(rep['rpcs'])} images")
    p = rep["predicted"]
    if p["sigma_planar_m_median"] is not None:
        print(f"predicted precision (sigma {rep['sigma_px']:g} px): planar {p['sigma_planar_m_median']:.3f} m, "
              f"height {p['sigma_height_m_median']:.3f} m (median)")
    if "accuracy" in rep and rep["accuracy"]["n"]:
        a = rep["accuracy"]
        print(f"errors vs truth (n={a['n']}): planar rms {a['planar_rms_m']:.3f} m, height rms "
              f"{a['height_rms_m']:.3f} m, CE90 {a['ce90_m']:.3f} m, LE90 {a['le90_m']:.3f} m")
    if args.out is None:
        t = rep["table"]
        print("id,lon,lat,h,n_images,sigma_planar_m,sigma_height_m")
        for _, r in t.iterrows():
            vals = [r["lon"], r["lat"], r["h"]]
            if not all(math.isfinite(v) for v in vals):
                print(f"{r['id']},,,,{int(r['n_images'])},,")
                continue
            print(f"{r['id']},{r['lon']:.9f},{r['lat']:.9f},{r['h']:.3f},{int(r['n_images'])},"
                  f"{r['sigma_planar_m']:.3f},{r['sigma_height_m']:.3f}")
    else:
        print(f"wrote {args.out}")
    print_warnings(rep)
    return 0
