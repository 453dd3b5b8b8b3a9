"""``gf4cal bundle-adjust``: separate views (stereo, tri-stereo, multi-date) brought into one frame from tie points
alone, each view's RPC corrected in image space (METHODS §11; the help cites the paper, not METHODS)."""
from __future__ import annotations

from .ortho import add_geoid_argument

NAME = "bundle-adjust"
HELP = ("Bundle adjustment of separate views on their RPCs (Grodecki & Dial 2003): tie points from a table or matched "
        "raw to raw, a correction per view, the datum held by each view's RPC; corrected RPCs (<view>.RPB, and "
        "<view>.vrt over each image), report.json, residuals.gpkg and ties.png in --out.")


def add_parser(parser):
    parser.add_argument("images", nargs="+", metavar="IMAGE",
                        help="the views: images with their RPCs (own, the RPC file named like the image beside it, "
                             "or --rpc IMAGE=RPC), or with --ties RPC files alone (.geom, .RPB, _RPC.TXT, DIMAP); "
                             "named in tables and outputs by file name without extension")
    parser.add_argument("--ties", metavar="OBS", help="tie-point observations (CSV/GeoPackage, one row per point and "
                                                      "view: point_id,image,sample,line[,sigma]; GDAL pixel "
                                                      "convention; any number of views per point)")
    parser.add_argument("--match-ties", action="store_true",
                        help="find tie points by raw-to-raw matching through the RPCs and the DEM on the "
                             "overlapping pairs of views (every view joined first, then the largest overlaps)")
    parser.add_argument("--dem", metavar="DEM|HEIGHT", help="DEM (any GDAL raster) or a constant height in metres: "
                                                            "starting heights, matching, and every tie's height "
                                                            "prior (fixes the views' relative bias along the "
                                                            "epipolar direction)")
    parser.add_argument("--dem-sigma", type=float, metavar="M",
                        help="σ (m) of the DEM's height prior on the ties (default 5 m, a global DEM's typical "
                             "absolute accuracy)")
    add_geoid_argument(parser)
    parser.add_argument("--gcps", metavar="OBS", help="GCP observations (point_id,image,sample,line,lon,lat,h"
                                                      "[,role][,sigma]): tie the block to the ground")
    parser.add_argument("--model", choices=("translation", "shift-drift", "affine"), default="affine",
                        help="correction per view (default affine; translation where the ties do not spread "
                             "over a view, with a note)")
    parser.add_argument("--max-pairs", type=int, metavar="N", help="--match-ties: match at most N pairs of views "
                                                                   "(default: every overlapping pair)")
    parser.add_argument("--prior-sigma", nargs="+", metavar="[VIEW=]PX",
                        help="how far (px, 1 sigma) each view's RPC may be off: the datum prior that holds the block "
                             "without GCPs; a number for every view and/or VIEW=PX for one (default: the RPC's "
                             "ERR_BIAS, else 5 m over the pixel size; a pair follows its first view: the second's 1000x wider); "
                             "widen it for a view known to be far off")
    from . import add_plausibility_argument, add_rpc_pairs_argument
    add_rpc_pairs_argument(parser)
    add_plausibility_argument(parser, "GCPs")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs (never an input)")


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.3f}"


def run(args) -> int:
    from ..progress import TextProgressBar
    from ..workflows import bundle_adjust
    rep = bundle_adjust(args.images, ties=args.ties, match_ties=args.match_ties, dem=args.dem, geoid=args.geoid,
                        gcps=args.gcps, model=args.model, max_pairs=args.max_pairs, rpcs=args.rpc,
                        prior_sigma_px=args.prior_sigma, dem_sigma_m=args.dem_sigma, out=args.out,
                        overwrite=args.overwrite, progress=TextProgressBar(),
                        check_plausibility=not args.no_plausibility_check)
    t, est = rep["ties"], rep["estimate"]
    print(f"{t['n_points']} tie points ({t['n_observations']} observations, {t['source']}), {rep['n_outliers']} "
          f"observations rejected; {est['iterations']} iterations, "
          f"{'converged' if est['converged'] else 'NOT converged'}")
    ref = rep["relative_to_first_view_px"]["reference"]
    for k, v in rep["views"].items():
        c = v["correction"]["parameters_px"]
        r = rep["relative_to_first_view_px"]["views"].get(k, {})
        rel = "" if k == ref or not r else (
            f" (relative to {ref}: sample {r['sample']:+.3f} +- {r['sample_std']:.3f}, line {r['line']:+.3f} +- "
            f"{r['line_std']:.3f})")
        print(f"{k}: {v['model_used']} correction sample {c.get('sample_1', 0.0):+.3f} line {c.get('line_1', 0.0):+.3f}"
              f" px at the centre{rel}; tie RMS {_fmt(v['reprojection_px']['before'])} -> "
              f"{_fmt(v['reprojection_px']['after'])} px")
    for pair, after in rep["reprojection_px"]["after"]["per_pair"].items():
        print(f"pair {pair.replace('|', ' | ')}: tie RMS {_fmt(rep['reprojection_px']['before']['per_pair'].get(pair))}"
              f" -> {_fmt(after)} px")
    print(f"datum drift {rep['datum_drift_m']:.3f} m (mean move of the tie points)")
    import os
    vrts = sum("vrt" in v for v in rep["views"].values())
    print(f"wrote {len(rep['views'])} RPCs{f' ({vrts} as VRTs over the images too)' if vrts else ''}, report.json, "
          f"residuals.gpkg, ties.png{', ties.csv' if 'ties' in rep['outputs'] else ''} in "
          f"{os.path.dirname(rep['outputs']['report']) or '.'}")
    from . import print_warnings
    print_warnings(rep)
    return 0
