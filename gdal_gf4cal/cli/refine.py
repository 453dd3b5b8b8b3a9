"""``gf4cal refine``: bias-compensate the RPC of an image with GCPs and write the refined RPC (METHODS §4)."""
from __future__ import annotations

from .ortho import add_geoid_argument

NAME = "refine"
HELP = ("Refine an image's RPC with GCPs (translation, shift-drift, affine, poly2 or detector-poly) and write "
        "it as .RPB, _RPC.TXT or a VRT over the untouched image.")


def add_parser(parser):
    from ..compensation import MODEL_NAMES
    parser.add_argument("source", nargs="+", metavar="IMAGE_OR_RPC", help="image with an RPC, or a standalone RPC "
                        "file (several with --batch)")
    from . import add_rpc_argument
    add_rpc_argument(parser)
    parser.add_argument("--gcps", required=True,
                        help="GCPs: CSV (id,lon,lat,h,sample,line[,role][,sigma]), GeoPackage/GeoJSON point layer "
                             "(any CRS, sample/line fields), QGIS .points, or a raster with embedded GCPs")
    parser.add_argument("--model", default="auto", choices=("auto",) + tuple(MODEL_NAMES),
                        help="image-space compensation model; auto (default): the simplest of translation, "
                        "shift-drift, affine, poly2 unless more parameters lower the leave-one-out error "
                        "significantly (the report says why)")
    parser.add_argument("--order", type=int, help="detector-poly: polynomial order 1..6 along the CCD")
    parser.add_argument("--along", choices=("translation", "shift-drift", "affine", "poly2"),
                        help="detector-poly: the model it is combined with (default translation)")
    parser.add_argument("--ccd-axis", choices=("sample", "line"), default="sample",
                        help="detector-poly: image axis along the CCD line (default sample)")
    parser.add_argument("--dem", help="DEM for GCPs without height")
    add_geoid_argument(parser)
    parser.add_argument("--gcp-crs", help="CRS of the GCPs' map coordinates when the file does not say")
    from . import add_gcp_reader_arguments
    add_gcp_reader_arguments(parser)
    parser.add_argument("--check-fraction", type=float,
                        help="make this share of the GCPs check points (seeded, spread over the image)")
    parser.add_argument("--seed", type=int, default=0, help="seed of --check-fraction (default 0)")
    parser.add_argument("--leave-one-out", action="store_true",
                        help="also report leave-one-out residuals of the control points")
    parser.add_argument("--no-robust", action="store_true", help="plain least squares: no blunder detection")
    parser.add_argument("--outlier-threshold", type=float, default=4.0,
                        help="normalised residual above which a GCP is a blunder (default 4)")
    parser.add_argument("--max-uncertainty", type=float, metavar="PX",
                        help="refuse a correction whose propagated 1-sigma uncertainty anywhere in the image exceeds "
                        "PX (default 10; a warning above 1 px)")
    from . import add_plausibility_argument
    add_plausibility_argument(parser)
    parser.add_argument("--out", required=True, help="output .RPB, _RPC.TXT, or .vrt (image input)")
    parser.add_argument("--ortho", metavar="ORTHO.tif",
                        help="also orthorectify the image with the refined RPC over --dem into this GeoTIFF")
    from .ortho import add_ortho_arguments
    add_ortho_arguments(parser)
    parser.add_argument("--report", help="write report.json")
    parser.add_argument("--residuals", help="write the GCPs and residuals as a styled GeoPackage (.gpkg)")
    parser.add_argument("--plot", help="write a PNG of the residual vectors before/after")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs (never an input)")
    parser.add_argument("--batch", action="store_true", help="batch form: IMAGE_OR_RPC are many scenes (paths, "
                        "globs, @list.txt), --gcps a folder of <stem>.gpkg tables (or one <stem>.* GCP file each, e.g. header-less "
                        "<stem>.csv with --columns), --out a folder (<stem>.RPB + "
                        "<stem>.report.json per scene, batch_summary.csv/.json); rerun skips finished scenes")
    from .batch_options import add_batch_options
    add_batch_options(parser, flag=False)


def _fmt(x):
    return "-" if x is None else f"{x:.3f}"


def run(args) -> int:
    from . import print_warnings
    from ..progress import TextProgressBar
    from ..workflows import refine_rpc
    if args.batch or args.dask:
        if args.rpc:
            from ..errors import Gf4calError
            raise Gf4calError("--rpc names one scene's RPC; in a batch each scene must carry its own RPC")
        from .batch_options import run_batch_command
        from ..batch import refine_batch
        return run_batch_command(args, lambda ex, pr: refine_batch(
            args.source, args.gcps, args.model, args.out, executor=ex, overwrite=args.overwrite, progress=pr,
            order=args.order, along=args.along, ccd_axis=args.ccd_axis, dem=args.dem, geoid=args.geoid,
            gcp_crs=args.gcp_crs, check_fraction=args.check_fraction, seed=args.seed,
            robust=not args.no_robust, outlier_threshold=args.outlier_threshold, leave_one_out=args.leave_one_out,
            gcp_columns=args.columns, gcp_pixel_convention=args.gcp_pixel_convention,
            max_uncertainty_px=args.max_uncertainty, check_plausibility=not args.no_plausibility_check))
    if len(args.source) != 1:
        from ..errors import Gf4calError
        raise Gf4calError("several scenes: add --batch (then --gcps is a folder of <stem>.gpkg and --out a folder)")
    args.source = args.source[0]
    from .ortho import cli_geoid_errors, print_ortho
    ortho_options = {"crs": args.crs, "res_m": args.res, "resampling": args.resampling, "force": args.force}
    rep = cli_geoid_errors(refine_rpc, args.source, args.gcps, args.model, out=args.out, order=args.order, along=args.along,
                     ccd_axis=args.ccd_axis, dem=args.dem, geoid=args.geoid, gcp_crs=args.gcp_crs,
                     check_fraction=args.check_fraction, seed=args.seed, leave_one_out=args.leave_one_out,
                     robust=not args.no_robust, outlier_threshold=args.outlier_threshold, report=args.report,
                     residuals=args.residuals, plot=args.plot, overwrite=args.overwrite,
                     progress=TextProgressBar(), ortho=args.ortho, ortho_options=ortho_options,
                     check_plausibility=not args.no_plausibility_check, max_uncertainty_px=args.max_uncertainty,
                     gcp_columns=args.columns, gcp_pixel_convention=args.gcp_pixel_convention, rpc=args.rpc)
    _print_report(rep)
    if "ortho" in rep:
        print_ortho(rep["ortho"])
    print_warnings(rep)
    return 0


def _print_report(rep) -> None:
    m = rep["model"]
    if "model_selection" in rep:
        sel = rep["model_selection"]
        print(f"model auto -> {sel['reason']}")
        for name, c in sel["candidates"].items():
            if c.get("scored"):
                chk = f", check rms {c['check_rms_px']:.3f} px" if c.get("check_rms_px") is not None else ""
                print(f"  {name:12} leave-one-out rms {c['loo_rms_px']:.3f} px, control rms "
                      f"{c['control_rms_px']:.3f} px{chk}")
            else:
                print(f"  {name:12} not compared: {c.get('why_not', '')}")
    # sigma0 is the a-posteriori factor of the GCPs' sigma: in px only when their sigma is 1 px.
    print(f"model {m['label']}: {len(m['parameters_px'])} parameters, sigma0 "
          f"{_fmt(m['sigma0_px']['sample'])}/{_fmt(m['sigma0_px']['line'])} (sample/line, x GCP sigma)")
    print(f"{'':8} {'n':>4} {'before rms s/l (px)':>22} {'after rms s/l (px)':>22} {'CE90 before/after (m)':>24}")
    for role in ("control", "check"):
        b, a = rep[role]["before"], rep[role]["after"]
        if not b["n"]:
            continue
        print(f"{role:8} {b['n']:>4} {_fmt(b['sample']['rms']):>10} / {_fmt(b['line']['rms']):<9}"
              f" {_fmt(a['sample']['rms']):>10} / {_fmt(a['line']['rms']):<9}"
              f" {_fmt(b['ce90_m']):>11} / {_fmt(a['ce90_m']):<10}")
    if "leave_one_out" in rep:
        lo = rep["leave_one_out"]
        print(f"leave-one-out rms s/l: {_fmt(lo['sample']['rms'])} / {_fmt(lo['line']['rms'])} px (n={lo['n']})")
    for o in rep["outliers"]:
        print(f"outlier {o['id']} ({o['role']}): normalised residual s/l {_fmt(o['norm_res_sample'])} / "
              f"{_fmt(o['norm_res_line'])}")
    if "precision_px" in rep:
        pr = rep["precision_px"]
        print(f"correction uncertainty over the image (1 sigma): max {pr['max']:.3f} px, rms {pr['rms']:.3f} px")
    ap = rep["apply"]
    if ap["exact"]:
        print("applied exactly (offsets/scales)")
    else:
        print(f"applied by refitting the RPC: max error {ap['refit_max_px']:.2e} px, rms {ap['refit_rms_px']:.2e} px")
    for k, v in rep["outputs"].items():
        print(f"wrote {k}: {v}")
