"""``gf4cal register-pan-ms``: register an MS image to its pan for halo-free pan-sharpening (METHODS §9, seed 004)."""
from __future__ import annotations

import sys

from .ortho import add_geoid_argument

NAME = "register-pan-ms"
HELP = ("Register a multispectral image to its panchromatic image (sub-CCD jumps, attitude, jitter; Zhang et "
        "al. 2023): write correction.tif, ms_on_pan.tif (for gdal_pansharpen.py), model.json, ms_approx.RPB, "
        "report.json, "
        "cells.gpkg and plots.")


def add_parser(parser):
    parser.add_argument("pan", metavar="PAN", help="panchromatic image with its RPC (raw product)")
    parser.add_argument("ms", metavar="MS", help="multispectral image of the same scene with its RPC")
    parser.add_argument("--dem", required=True, help="DEM covering the scene (SRTM is enough) or a height in m")
    add_geoid_argument(parser)
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--sub-ccds", type=int, default=None, metavar="N",
                        help="N equal sub-CCDs per band, counted on the full product when the crop's place in it is "
                        "known (default: the edges found in the data, else one piece)")
    parser.add_argument("--breaks", metavar="S1,S2,...",
                        help="sub-CCD edges: MS columns, and/or 'ms' (the MS band's N equal edges) and 'pan' (the "
                             "pan's N equal edges mapped into the MS through the RPCs and DEM), e.g. ms,pan")
    parser.add_argument("--cell", type=int, default=None, metavar="PX",
                        help="cell size in MS px, >= 4 (default: from the MS size and texture, 4..64)")
    parser.add_argument("--pan-rpc", metavar="FILE", help="the pan's RPC when not in the image (default: the "
                        "image's own, or a .geom/.RPB/_RPC.TXT named like it beside it; a crop's product RPC is "
                        "shifted by the crop origin its geotransform states)")
    parser.add_argument("--ms-rpc", metavar="FILE", help="the MS image's RPC when not in the image (as --pan-rpc)")
    parser.add_argument("--jitter", default="auto", metavar="auto|none|N",
                        help="jitter components per axis: auto (while significant), none, or N (at most N; refused beyond "
                             "what the usable cell rows resolve)")
    parser.add_argument("--reuse", metavar="MODEL.json",
                        help="keep the sub-CCD term of this model (another scene of the same camera); solve only "
                             "the linear term from <= 200 sparse matches (cloudy or watery scenes)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs (never an input)")


def _f(x, fmt=".3f"):
    return "-" if x is None else format(x, fmt)


def print_summary(rep: dict, stream=None) -> None:
    out = stream or sys.stdout
    print(f"pan-MS registration ({rep['mode']} mode): ratio {rep['sizes']['ratio']}, {rep['cell_px']} px cells: "
          f"{rep['n_usable']} usable of {rep['n_cells']}, {rep['n_outliers']} outliers, sub-CCD edges "
          f"{[round(b, 1) for b in rep['breaks_ms_px']]} (from {rep['breaks_from']})", file=out)
    print(f"{'step':<12} {'rms sample':>10} {'rms line':>9} {'P(<=0.25)':>10}", file=out)
    for st in rep["steps"]:
        print(f"{st['step'].split(' ')[0]:<12} {_f(st['rms_sample_px']):>10} {_f(st['rms_line_px']):>9} "
              f"{100 * st['p_le_0.25']:>9.1f}%", file=out)
    for ax in ("sample", "line"):
        for c in rep["jitter"][ax]["components"]:
            print(f"jitter {ax}: {_f(c.get('frequency_hz'), '.3f')} Hz, amplitude {_f(c['amplitude_px'])} px, "
                  f"attitude {_f(c.get('attitude_amplitude_urad'), '.3f')} urad", file=out)
    for b in rep.get("bands", []):
        r, t = b.get("residual", {}), b.get("to_reference")
        line = (f"band {b['band']} ({b['name']}){' reference' if b['reference'] else ''}: residual "
                f"{_f(r.get('rms_sample_px'))} / {_f(r.get('rms_line_px'))} px")
        if t:
            line += (f", to band {rep['reference_band']} {_f(t['mean_sample_px'])} / {_f(t['mean_line_px'])} px"
                     + (" (own correction)" if b.get("own_correction") else "")
                     + (" (spectral)" if b.get("spectral") else ""))
        print(line, file=out)
    e = rep["ms_approx_rpc"]
    print(f"ms_approx.RPB vs the full model: rms {_f(e['rms_px'])} px, max {_f(e['max_px'])} px", file=out)
    for k, v in rep["outputs"].items():
        print(f"wrote {k}: {v}", file=out)


def run(args) -> int:
    from . import print_warnings
    from ..progress import TextProgressBar
    from ..workflows import register_pan_ms
    rep = register_pan_ms(args.pan, args.ms, dem=args.dem, geoid=args.geoid, out=args.out, n_sub_ccds=args.sub_ccds,
                          breaks=args.breaks, cell=args.cell, jitter=args.jitter, reuse=args.reuse,
                          overwrite=args.overwrite, progress=TextProgressBar(), pan_rpc=args.pan_rpc,
                          ms_rpc=args.ms_rpc)
    print_summary(rep)
    print_warnings(rep)
    return 0
