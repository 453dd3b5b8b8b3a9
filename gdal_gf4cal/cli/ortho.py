"""``gf4cal ortho``: orthorectify an image with its (refined) RPC over a DEM made ellipsoidal."""
from __future__ import annotations

NAME = "ortho"
HELP = ("Orthorectify an image with its RPC (or a refined one, --rpc) over a DEM with GDAL's warper; heights above "
        "a geoid are made ellipsoidal first (the grid is found through PROJ), else the run is refused.")

#: One ``--geoid`` for every command, the words and order of the QGIS "DEM heights are" choice.
GEOID_HELP = ("what the DEM's heights are above: auto (default: what the DEM's CRS declares, ellipsoidal when it "
              "declares none), egm96, egm2008, none (ellipsoidal: never converted), or the PATH of a geoid grid "
              "(.gtx/.tif)")


def add_geoid_argument(parser):
    """The ``--geoid`` option of every command taking a DEM (same words, order and default everywhere)."""
    parser.add_argument("--geoid", default="auto", metavar="auto|egm96|egm2008|none|PATH", help=GEOID_HELP)


def add_ortho_arguments(parser, out_required=True):
    """``--crs``, ``--res`` and ``--resampling`` (shared with ``refine --ortho``)."""
    from ..workflows.ortho import RESAMPLING
    parser.add_argument("--crs", default="utm",
                        help="output CRS: EPSG:XXXX or 'utm' (default: the UTM zone of the scene centre)")
    parser.add_argument("--res", type=float, metavar="METRES", help="output pixel size (default: GDAL's choice)")
    parser.add_argument("--resampling", choices=RESAMPLING, default="bilinear", help="resampling (default bilinear)")
    parser.add_argument("--force", action="store_true",
                        help="write an ortho larger than the size limit (4e9 px) or than the free space uncompressed "
                             "(without it such a --res is refused before anything is written)")


def add_parser(parser):
    parser.add_argument("image", metavar="IMAGE", help="the image (any GDAL raster); its own RPC unless --rpc")
    parser.add_argument("--rpc", help="RPC to use instead of the image's: refined .vrt, .RPB, _RPC.TXT")
    parser.add_argument("--dem", required=True, help="DEM covering the scene (any GDAL raster, any CRS)")
    add_geoid_argument(parser)
    parser.add_argument("--out", required=True, metavar="ORTHO.tif", help="output GeoTIFF (tiled, compressed)")
    add_ortho_arguments(parser)
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output (never an input)")


def cli_geoid_errors(func, *args, **kwargs):
    """Call ``func``; a missing geoid grid is reported in the CLI's words (``--geoid PATH``)."""
    from ..geoid import GeoidGridMissing
    try:
        return func(*args, **kwargs)
    except GeoidGridMissing as exc:
        raise exc.phrase("--geoid PATH") from None


def print_ortho(rep) -> None:
    g = rep.get("geoid")
    heights = f"DEM heights above {g['name']} made ellipsoidal" if g else "DEM heights used as ellipsoidal"
    print(f"ortho: {rep['size_px'][0]} x {rep['size_px'][1]} px of {rep['res_m']:.3f} in {rep['crs']}, "
          f"{rep['resampling']}; {heights}")


def run(args) -> int:
    from . import print_warnings
    from ..progress import TextProgressBar
    from ..workflows import orthorectify
    rep = cli_geoid_errors(orthorectify, args.image, dem=args.dem, out=args.out, rpc=args.rpc, geoid=args.geoid,
                           crs=args.crs, res_m=args.res, resampling=args.resampling, force=args.force,
                           overwrite=args.overwrite,
                           progress=TextProgressBar())
    print_ortho(rep)
    for k, v in rep["outputs"].items():
        print(f"wrote {k}: {v}")
    print_warnings(rep)
    return 0
