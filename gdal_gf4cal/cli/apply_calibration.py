"""``gf4cal apply-calibration``: recalibrate the RPCs of other scenes with a calibrated camera (METHODS §5 step 4)."""
from __future__ import annotations

from ..batch import apply_calibration_batch
from ..errors import GCPError
from ..progress import TextProgressBar
from ..workflows import apply_block_calibration, apply_calibration
from . import add_rpc_pairs_argument, print_warnings
from .batch_options import add_batch_options, run_batch_command

NAME = "apply-calibration"
HELP = ("Recalibrate the RPCs of scenes made with the --current camera for the --new camera (from "
        "calibrate-lookangle), or of another scene of a block-calibrated group (--calibration from block-adjust); "
        "write DIR/<scene>.RPB (+ .vrt for images) and report.json.")


def add_parser(parser):
    parser.add_argument("scenes", nargs="+", metavar="SCENE", help="images with an RPC or RPC sidecars (paths, "
                        "globs or @list.txt)")
    parser.add_argument("--current", metavar="OLD.json", help="the camera the scenes' RPCs were made with")
    parser.add_argument("--new", metavar="NEW.json", help="the recalibrated camera")
    parser.add_argument("--calibration", metavar="CAL.json", help="instead of --current/--new: a block calibration "
                        "(calibration.json of block-adjust); SCENEs are the group's images, named as calibrated")
    add_rpc_pairs_argument(parser)
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs (never an input)")
    add_batch_options(parser, flag=True)


def run(args) -> int:
    if args.calibration:
        if args.current or args.new:
            raise GCPError("give either --calibration (block) or --current and --new (camera files), not both")
        if args.batch or args.dask:
            raise GCPError("--calibration recalibrates the images of one group together; drop --batch/--dask")
        return _run_block(args)
    if not (args.current and args.new):
        raise GCPError("give --current and --new (camera files) or --calibration (block calibration)")
    if args.batch or args.dask:
        if args.rpc:
            raise GCPError("--rpc pairs the scenes of one run with their RPCs; in a batch each scene must carry its "
                           "own RPC")
        return run_batch_command(args, lambda ex, pr: apply_calibration_batch(
            args.current, args.new, args.scenes, args.out, executor=ex, overwrite=args.overwrite, progress=pr))
    rep = apply_calibration(args.current, args.new, args.scenes, args.out, overwrite=args.overwrite,
                            progress=TextProgressBar(), rpcs=args.rpc)
    for e in rep["scenes"]:
        fit = e["fit"]["check"] or e["fit"]["fit"]
        print(f"{e['scene']}: image moved by mean {e['image_shift_px']['mean']:.2f} px, max "
              f"{e['image_shift_px']['max']:.2f} px; RPC fit max {fit['max_px']:.2e} px -> {e['rpb']}"
              + (f" and {e['vrt']}" if e["vrt"] else ""))
    print(f"wrote report: {rep['outputs']['report']}")
    print_warnings(rep)
    return 0


def _run_block(args) -> int:
    rep = apply_block_calibration(args.calibration, args.scenes, args.out, overwrite=args.overwrite,
                                  progress=TextProgressBar(), rpcs=args.rpc)
    for e in rep["scenes"]:
        fit = e["fit"]["check"] or e["fit"]["fit"]
        print(f"{e['scene']} ({e['image']}): image moved by mean {e['image_shift_px']['mean']:.2f} px, max "
              f"{e['image_shift_px']['max']:.2f} px; RPC fit max {fit['max_px']:.2e} px -> {e['rpb']}")
    print(f"wrote report: {rep['outputs']['report']}")
    print_warnings(rep)
    return 0
