"""``gf4cal simulate``: write a simulated scene with known truth (METHODS §10)."""
from __future__ import annotations

from ..progress import TextProgressBar
from ..simulate import SENSORS
from ..workflows import simulate_scene
from . import print_warnings

NAME = "simulate"
HELP = ("Simulate a scene of a known sensor (gf4, zy3, hj1, jl1, gf7) with known truth: image or placeholder, RPC "
        "fitted from the current model, DEM, GCPs from the true model, check grid, cameras, truth.json.")


def add_parser(parser):
    parser.add_argument("--sensor", required=True, choices=sorted(SENSORS), help="sensor family")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of errors, terrain and GCPs (default 0)")
    parser.add_argument("--center", type=float, nargs=2, metavar=("LON", "LAT"),
                        help="scene centre in degrees (default: the sensor's, e.g. 88 31 in Tibet for gf4)")
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                        help="crop the detector array around its centre to W x H pixels (geometry unchanged)")
    parser.add_argument("--crop", type=int, nargs=4, metavar=("X0", "Y0", "W", "H"),
                        help="gf7: simulate the full product, write only the W x H crop at column X0, row Y0 (pan "
                             "pixels of the full product, multiples of 4; the MS crop is the same ground). The "
                             "crop keeps its place: a pixel-unit geotransform (X0, 1, 0, Y0, 0, 1) without CRS, "
                             "and product.RPB is the product's RPC")
    parser.add_argument("--n-gcps", type=int, default=200, help="GCPs per image (default 200)")
    parser.add_argument("--gcp-noise", type=float, default=0.6, metavar="PX",
                        help="GCP image measurement noise, pixels per axis (default 0.6)")
    parser.add_argument("--outlier-fraction", type=float, default=0.0, metavar="F",
                        help="fraction of GCPs given a 5-30 px blunder (default 0)")
    parser.add_argument("--check-fraction", type=float, default=0.3, metavar="F",
                        help="fraction of GCPs with role 'check' (default 0.3)")
    parser.add_argument("--dem", help="use this DEM (ellipsoidal heights) instead of synthetic terrain")
    parser.add_argument("--render", action="store_true", help="render scene.tif through the true model")
    parser.add_argument("--reference", metavar="ORTHO",
                        help="with --render: reference image to render from (any GDAL raster, any CRS); "
                             "default: built-in seeded texture")
    parser.add_argument("--clouds", type=float, default=0.0, metavar="F",
                        help="with --render: fraction of the image covered by clouds (default 0; gf7: clouds on "
                             "the ground, seen by pan and MS alike)")
    parser.add_argument("--no-reference-ortho", action="store_true",
                        help="with --render from the built-in texture: do not write reference.tif (the same "
                             "texture as an EPSG:4326 orthophoto, for collect-gcps --reference)")
    parser.add_argument("--workers", type=int, default=2, help="rendering threads (default 2)")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into an existing, non-empty folder (never over an input)")
    parser.add_argument("--orbit-seed", type=int, metavar="N",
                        help="jl1: seed of a per-orbit random attitude error (3.6 arcsec per axis; validation scenes)")
    parser.add_argument("--n-ties", type=int, metavar="N",
                        help="jl1: tie points per CCD overlap and band, and per CCD between bands (default 40)")
    parser.add_argument("--tie-noise", type=float, metavar="PX",
                        help="jl1: tie-point matching noise, pixels per axis (default 0.1)")


def _observation_options(args):
    opts = {"n_overlap_ties": args.n_ties, "n_band_ties": args.n_ties, "tie_noise_px": args.tie_noise}
    return {k: v for k, v in opts.items() if v is not None} or None


def run(args) -> int:
    res = simulate_scene(args.sensor, args.out, overwrite=args.overwrite, seed=args.seed, center=args.center,
                      size=args.size, crop=args.crop,
                      n_gcps=args.n_gcps, gcp_noise_px=args.gcp_noise, outlier_fraction=args.outlier_fraction,
                      dem=args.dem, render=args.render, reference=args.reference, progress=TextProgressBar(),
                      check_fraction=args.check_fraction, paint_clouds=args.clouds, workers=args.workers,
                      reference_ortho=not args.no_reference_ortho,
                      options=None if args.orbit_seed is None else {"orbit_seed": args.orbit_seed},
                      observation_options=_observation_options(args))
    print(f"{args.sensor} scene written to {res.out_dir} in {res.elapsed_s:.1f} s")
    for name, im in res.images.items():
        chk = im.fit_report.check
        print(f"  {name or 'scene'}: {len(im.gcps)} GCPs; RPC fit on the check grid: max {chk.max_px:.2e} px, "
              f"RMS {chk.rms_px:.2e} px  ({im.dir})")
        if res.crop:
            x0, y0, w, h = res.crop[name]
            print(f"    crop {w} x {h} px at ({x0}, {y0}) of the product; {im.paths['rpc']} is the product's RPC")
        if "reference" in im.paths:
            print(f"  reference orthophoto of the same ground: {im.paths['reference']}")
    print_warnings(res)
    return 0
