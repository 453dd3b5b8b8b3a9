"""``gf4cal calibrate-lookangle``: recalibrate an area-array camera's look angles from a scene's RPC and GCPs
(METHODS §5, seed 000), and write the new camera file and the recalibrated RPC."""
from __future__ import annotations

import sys

from .ortho import add_geoid_argument

NAME = "calibrate-lookangle"
HELP = ("Calibrate the detector look-angle model (GF4-type area array) from a scene's RPC, its camera file and "
        "GCPs; write camera_new.json, the recalibrated RPC (.RPB, VRT), residuals and report.json.")


def add_parser(parser):
    parser.add_argument("--rpc", required=True, metavar="SCENE",
                        help="the scene's RPC: image with an RPC or a sidecar (.RPB, _RPC.TXT, ...), made with "
                             "--camera")
    parser.add_argument("--gcps", required=True,
                        help="GCPs: CSV (id,lon,lat,h,sample,line[,role][,sigma]), GeoPackage or GeoJSON; "
                             "'check' rows are only evaluated")
    from . import add_gcp_reader_arguments
    add_gcp_reader_arguments(parser)
    parser.add_argument("--camera", required=True, metavar="CAMERA.json",
                        help="the camera file the RPC was made with ({\"model\": \"lookangle-cubic\", ...}); "
                             "without one, write a nominal camera (see the README) and use it")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--image", help="the scene's image: also write DIR/<image>.vrt carrying the new RPC")
    parser.add_argument("--dem", help="DEM for GCPs without height")
    add_geoid_argument(parser)
    parser.add_argument("--no-robust", action="store_true", help="plain least squares: no blunder detection")
    parser.add_argument("--max-condition", type=float, default=None,
                        help="refuse GCP layouts whose condition number exceeds this (default 1e6)")
    from . import add_plausibility_argument
    add_plausibility_argument(parser)
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs (never an input)")


def _f(x, fmt=".3f"):
    return "-" if x is None else format(x, fmt)


def print_summary(rep: dict, stream=None) -> None:
    out = stream or sys.stdout
    cal = rep["calibration"]
    print(f"look-angle calibration: {cal['n_control']} control GCPs, {cal['n_outliers']} outliers, "
          f"{cal['iterations']} iterations, condition number {cal['condition_number']:.3g}, "
          f"sigma0 {_f(cal['sigma0'])}", file=out)
    print(f"{'':8} {'n':>4}  {'before rms s/l (px)':>21}  {'after rms s/l (px)':>21}", file=out)
    for role in ("control", "check"):
        st = cal.get(role)
        if not st:
            continue
        b, a = st["before"], st["after"]
        print(f"{role:8} {st['n']:>4}  {_f(b['sample']['rms']):>10} / {_f(b['line']['rms']):<8}"
              f"  {_f(a['sample']['rms']):>10} / {_f(a['line']['rms']):<8}", file=out)
    pr = cal["precision_px"]
    print(f"precision of the new camera over the array (propagated GCP noise): rms {_f(pr['sample']['rms'])} / "
          f"{_f(pr['line']['rms'])} px, max {_f(pr['sample']['max'])} / {_f(pr['line']['max'])} px (sample/line)",
          file=out)
    ch = rep["camera_change_px"]
    print(f"camera change over the array: max {_f(ch['sample']['max'], '.2f')} px (sample), "
          f"{_f(ch['line']['max'], '.2f')} px (line)", file=out)
    fit = rep["recalibrated_rpc"]["check"] or rep["recalibrated_rpc"]["fit"]
    print(f"recalibrated RPC fit: max {fit['max_px']:.2e} px, rms {fit['rms_px']:.2e} px", file=out)
    for ident in cal.get("outlier_ids", [])[:20]:
        print(f"outlier {ident}", file=out)
    for k, v in rep["outputs"].items():
        print(f"wrote {k}: {v}", file=out)


def run(args) -> int:
    from . import print_warnings
    from ..progress import TextProgressBar
    from ..workflows import calibrate_lookangle_files
    rep = calibrate_lookangle_files(args.rpc, args.gcps, args.camera, args.out, image=args.image, dem=args.dem,
                                    geoid=args.geoid, robust=not args.no_robust, max_condition=args.max_condition,
                                    overwrite=args.overwrite, progress=TextProgressBar(), gcp_columns=args.columns,
                                    gcp_pixel_convention=args.gcp_pixel_convention,
                                    check_plausibility=not args.no_plausibility_check)
    print_summary(rep)
    print_warnings(rep)
    return 0
