"""``gf4cal block-adjust``: multi-CCD / band-to-band block calibration of one group from its RPC images (METHODS §8)."""
from __future__ import annotations

from .ortho import add_geoid_argument

NAME = "block-adjust"
HELP = ("Block calibration of one multi-CCD group (Wu et al., Jilin1-KF01A): recalibrated RPCs per CCD image "
        "and band (seams removed, bands registered), calibration.json, report.json, residuals.gpkg and seams.png "
        "in --out.")


def add_parser(parser):
    parser.add_argument("images", nargs="+", metavar="IMAGE",
                        help="the group's images with their RPCs: the reference-band CCD images in their order across "
                             "track (adjacent ones overlap), then the other bands' images (see --bands-of)")
    parser.add_argument("--dem", required=True, help="DEM (any GDAL raster) or a constant height in metres: "
                                                     "tie-point heights")
    add_geoid_argument(parser)
    parser.add_argument("--gcps", metavar="OBS", help="GCP observations (CSV/GeoPackage: point_id,image,sample,line,"
                                                      "lon,lat,h[,role][,sigma]; image = the image's file or folder "
                                                      "name)")
    parser.add_argument("--ties", metavar="OBS", help="tie-point observations (point_id,image,sample,line[,sigma]); "
                                                      "may be the same file as --gcps")
    parser.add_argument("--match-ties", action="store_true", help="find tie points by raw-to-raw matching (adjacent "
                                                                   "CCDs, each band against its reference band)")
    parser.add_argument("--reference-ortho", metavar="ORTHO", help="collect GCPs for the reference-band images "
                                                                    "from this orthophoto")
    parser.add_argument("--bands-of", nargs="+", action="extend", metavar="IMAGE=REFIMAGE",
                        help="IMAGE is another band of the CCD whose reference-band image is REFIMAGE (relative "
                             "calibration: interior only, reference exterior fixed)")
    from . import add_rpc_pairs_argument
    add_rpc_pairs_argument(parser)
    parser.add_argument("--solver", choices=("simultaneous", "alternating"), default="simultaneous",
                        help="one sparse Gauss-Newton solve (default) or the paper's alternation of exterior and "
                             "interior (compared with the simultaneous solve in report.json)")
    from . import add_plausibility_argument
    add_plausibility_argument(parser, "GCPs and tie points")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs (never an input)")


def run(args) -> int:
    from ..progress import TextProgressBar
    from ..workflows import block_adjust
    rep = block_adjust(args.images, dem=args.dem, geoid=args.geoid, gcps=args.gcps, ties=args.ties,
                       match_ties=args.match_ties, reference_ortho=args.reference_ortho, bands_of=args.bands_of,
                       solver=args.solver, out=args.out, overwrite=args.overwrite, progress=TextProgressBar(),
                       check_plausibility=not args.no_plausibility_check, rpcs=args.rpc)
    for st in rep["stages"]:
        print(f"{st['stage']} stage ({st['solver']}): {st['iterations']} iterations, "
              f"{'converged' if st['converged'] else 'NOT converged'}, {st['n_tie_points']} tie points, "
              f"reduced system {st['reduced_system_size']} unknowns, {st['n_rejected']} observations rejected")
    for s in rep["seams"]:
        if s.get("n"):
            print(f"seam {s['pair'][0]} | {s['pair'][1]}: mean offset {s['before']['mean_px']:.3f} px before, "
                  f"{s['after']['mean_px']:.3f} px after; largest along the overlap {s['before']['seam_max_px']:.3f} "
                  f"-> {s['after']['seam_max_px']:.3f} px ({s['n']} tie points)")
    for k, v in rep["band_to_band"].items():
        if v["rms_px_after"] is not None:
            print(f"band {k} vs {v['reference']}: tie RMS {v['rms_px_before']:.3f} -> {v['rms_px_after']:.3f} px")
    if "solver_comparison" in rep:
        c = rep["solver_comparison"]
        print("solvers: " + "; ".join(f"{k} {v['iterations']} iterations" for k, v in c.items() if isinstance(v, dict))
              + f"; largest prediction difference {c['max_prediction_difference_px']:.3g} px")
    print(f"wrote {len(rep['images'])} RPCs, calibration.json, report.json, residuals.gpkg, seams.png in "
          f"{rep['outputs']['report'].rsplit('/', 1)[0] if '/' in rep['outputs']['report'] else '.'}")
    from . import print_warnings
    print_warnings(rep)
    return 0
