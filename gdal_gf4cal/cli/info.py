"""``gf4cal info``: summary of an image's or sidecar's RPC (METHODS §1), its footprint, GSD and height range."""
from __future__ import annotations

import json

from .ortho import add_geoid_argument

NAME = "info"
HELP = "Describe the RPC of an image or sidecar: offsets, footprint, approximate GSD, height range."


def add_parser(parser):
    parser.add_argument("source", metavar="IMAGE_OR_RPC", help="image with an RPC, or a standalone RPC file")
    from . import add_rpc_argument
    add_rpc_argument(parser)
    parser.add_argument("--dem", help="DEM to localise the footprint corners on (default: at HEIGHT_OFF)")
    add_geoid_argument(parser)
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")


def run(args) -> int:
    from ..describe import describe_rpc
    info = describe_rpc(args.source, dem=args.dem, geoid=args.geoid, rpc=args.rpc)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(format_info(info))
    return 0


def format_info(info: dict) -> str:
    rpc = info["rpc"]
    lines = [f"RPC of {info['source']} ({info['format']}" + (f" {info['rpc_file']})" if info.get("rpc_file") else ")"),
             f"  image size        {info['size'][0]} x {info['size'][1]} px" + ("" if info["size_from_image"]
                                                                              else " (from the RPC scales)"),
             f"  RPC centre        lon {rpc['LONG_OFF']:.6f}  lat {rpc['LAT_OFF']:.6f}  h {rpc['HEIGHT_OFF']:.1f} m",
             f"  height range      {info['height_range_m'][0]:.1f} .. {info['height_range_m'][1]:.1f} m "
             "(HEIGHT_OFF ± HEIGHT_SCALE)",
             f"  footprint on      {info['footprint_height']}"]
    for name, (lon, lat, h) in zip(("upper-left", "upper-right", "lower-right", "lower-left"), info["corners"]):
        lines.append(f"    {name:<12}    lon {lon:12.6f}  lat {lat:11.6f}  h {h:8.1f} m")
    gsd = info["gsd_m"]
    lines.append(f"  approximate GSD   {gsd['sample']:.3f} m (sample)  {gsd['line']:.3f} m (line)")
    if info.get("dem_height_range_m"):
        lo, hi = info["dem_height_range_m"]
        lines.append(f"  DEM heights       {lo:.1f} .. {hi:.1f} m over the footprint")
    if info.get("err_bias") is not None:
        lines.append(f"  ERR_BIAS/ERR_RAND {info['err_bias']} / {info['err_rand']} m")
    for note in info.get("notes", ()):
        lines.append(f"  note: {note}")
    for warning in info.get("warnings", ()):
        lines.append(f"  warning: {warning}")
    return "\n".join(lines)
