"""``gf4cal collect-gcps``: automatic GCPs by matching a raw image against a reference orthophoto + DEM (issue 7)."""
from __future__ import annotations

from ..batch import collect_gcps_batch, expand_scenes
from ..errors import Gf4calError
from ..executors import get_executor
from ..progress import TextProgressBar
from ..workflows import collect_gcps_file
from . import print_warnings
from .batch_options import add_batch_options, run_batch_command
from .ortho import add_geoid_argument

NAME = "collect-gcps"
HELP = ("Collect GCPs automatically: sub-pixel matching of the raw image (with its RPC) against a reference "
        "orthophoto and a DEM; writes a GCP table that refine and calibrate-lookangle read directly.")


def add_parser(parser):
    parser.add_argument("image", nargs="+", metavar="IMAGE", help="raw image with an RPC (TIFF tags, .RPB, "
                        "_RPC.TXT, NITF); several (paths, globs, @list.txt): a batch, --out is a folder")
    parser.add_argument("--reference", required=True, metavar="ORTHO",
                        help="reference orthophoto: any GDAL raster with a CRS (overviews are used when finer)")
    parser.add_argument("--dem", required=True, help="DEM (any GDAL raster, any CRS) or a constant height in metres")
    add_geoid_argument(parser)
    parser.add_argument("--rpc", help="read the RPC from this file instead of the image")
    parser.add_argument("--out", required=True, help="output GCP table: .gpkg, .csv or .geojson")
    parser.add_argument("--spacing", type=int, metavar="PX", help="grid step in pixels (default 256, finer on "
                        "images under ~1,900 px: eight windows across the shorter side, never closer than a window)")
    parser.add_argument("--window", type=int, default=64, metavar="PX", help="window size in pixels (default 64)")
    parser.add_argument("--search", type=float, default=64, metavar="PX",
                        help="largest initial offset to find, pixels (default 64)")
    parser.add_argument("--workers", type=int, help="parallel threads (default: all cores; 1 = no pool)")
    parser.add_argument("--min-peak", type=float, default=0.2, help="correlation peak threshold (default 0.2)")
    parser.add_argument("--outlier-model", default="affine", choices=("translation", "affine", "poly2", "poly3"),
                        help="low-order model for RANSAC + MAD outlier rejection (default affine)")
    parser.add_argument("--seed", type=int, default=0, help="RANSAC seed (default 0)")
    parser.add_argument("--band", type=int, default=1, help="image band (default 1)")
    parser.add_argument("--reference-band", type=int, default=1, help="reference band (default 1)")
    parser.add_argument("--keep-outliers", action="store_true",
                        help="also write the flagged outliers (column outlier=True); by default only inliers")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output (never an input)")
    add_batch_options(parser)


def run(args) -> int:
    scenes = expand_scenes(args.image)
    opts = dict(rpc=args.rpc, geoid=args.geoid, keep_outliers=args.keep_outliers, spacing_px=args.spacing,
                window_px=args.window, min_peak=args.min_peak, search_px=args.search,
                outlier_model=args.outlier_model, seed=args.seed, band=args.band, reference_band=args.reference_band)
    if len(scenes) > 1 or args.batch:
        if args.rpc:
            raise Gf4calError("--rpc names one scene's RPC; in a batch each scene must carry its own RPC")
        return run_batch_command(args, lambda ex, pr: collect_gcps_batch(
            scenes, args.reference, args.dem, args.out, executor=ex, overwrite=args.overwrite, progress=pr, **opts))
    args.image = scenes[0]
    with get_executor(args.dask or (None if args.workers is None else f"threads:{args.workers}")) as ex:
        rep = collect_gcps_file(args.image, args.reference, args.dem, args.out, rpc=args.rpc, geoid=args.geoid,
                            keep_outliers=args.keep_outliers, overwrite=args.overwrite, progress=TextProgressBar(),
                            spacing_px=args.spacing, window_px=args.window, executor=ex,
                            min_peak=args.min_peak, search_px=args.search, outlier_model=args.outlier_model,
                            seed=args.seed, band=args.band, reference_band=args.reference_band)
    gcps, w = rep["gcps"], rep["windows"]
    inl = ~gcps["outlier"].to_numpy(bool)
    print(f"windows {w['total']} every {rep['spacing_px']} px: accepted {w['accepted']}, featureless "
          f"{w['featureless']}, weak correlation {w['weak_correlation']}, cloud/change {w['cloud_or_change']}, no "
          f"data {w['nodata']}, outside {w['outside_image']}; outliers {w['outliers']}")
    if inl.any():
        ds, dl = gcps["dsample"].to_numpy()[inl], gcps["dline"].to_numpy()[inl]
        print(f"offset measured - RPC: mean {ds.mean():+.3f} / {dl.mean():+.3f} px (sample/line), "
              f"median precision {float(gcps['precision_px'][inl].median()):.3f} px")
    print(f"wrote {rep['n_gcps']} GCPs: {args.out}")
    print_warnings(rep)
    return 0
