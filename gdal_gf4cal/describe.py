"""A summary of an RPC: size, footprint localised on a DEM (or at HEIGHT_OFF), approximate GSD, height range.

Used by ``gf4cal info`` and the QGIS ``rpcinfo`` algorithm.
"""
from __future__ import annotations

import os
from typing import Optional

import numpy as np
from osgeo import gdal

from .crop import image_rpc, sidecar_rpc
from .dem import DEM
from .errors import DEMError, RPCFormatError
from .rpc import RPCModel
from .rpc_io import rpc_file_format


def image_size_of(path) -> Optional[tuple]:
    """(width, height) of a raster GDAL opens, or None for a sidecar / non-raster."""
    try:
        with gdal.ExceptionMgr(useExceptions=False):
            ds = gdal.OpenEx(os.fspath(path), gdal.OF_RASTER)
    except AttributeError:  # GDAL < 3.7 has no ExceptionMgr
        gdal.PushErrorHandler("CPLQuietErrorHandler")
        try:
            ds = gdal.OpenEx(os.fspath(path), gdal.OF_RASTER)
        except RuntimeError:
            ds = None
        finally:
            gdal.PopErrorHandler()
    if ds is None:
        return None
    return (ds.RasterXSize, ds.RasterYSize)


_CORNERS = ("upper-left", "upper-right", "lower-right", "lower-left")
_IMAGE_EXTENSIONS = (".tif", ".TIF", ".tiff", ".TIFF", ".ntf", ".NTF", ".jp2", ".JP2", ".vrt", ".VRT")


def _image_of(source, fmt: str):
    """The raster whose size the RPC describes: ``source`` itself when GDAL opens it as an image, else the image a
    ``.RPB`` / ``_RPC.TXT`` sidecar sits next to (``x.RPB`` / ``x_RPC.TXT`` -> ``x.tif`` ...), else None."""
    path = os.fspath(source)
    if fmt in ("gdal", "gdal_xml"):
        return path
    if fmt not in ("rpb", "rpc_txt"):
        return None
    base, ext = os.path.splitext(path)
    if fmt == "rpc_txt" and base.lower().endswith("_rpc"):
        base = base[:-4]
    for candidate in (base + e for e in _IMAGE_EXTENSIONS):
        if os.path.isfile(candidate):
            return candidate
    return None


def _uncovered(rpc: RPCModel, W: int, H: int) -> str:
    """'' when the RPC's image domain (OFF ± |SCALE|, GDAL pixel convention, 1 px slack) covers [0, W] x [0, H];
    else a description of that domain."""
    s0, s1 = rpc.samp_off + 0.5 - abs(rpc.samp_scale), rpc.samp_off + 0.5 + abs(rpc.samp_scale)
    l0, l1 = rpc.line_off + 0.5 - abs(rpc.line_scale), rpc.line_off + 0.5 + abs(rpc.line_scale)
    if s0 <= 1.0 and s1 >= W - 1.0 and l0 <= 1.0 and l1 >= H - 1.0:
        return ""
    return f"samples {s0:.0f}..{s1:.0f}, lines {l0:.0f}..{l1:.0f}"


def describe_rpc(source, dem=None, geoid=None, rpc=None) -> dict:
    """Describe the RPC of ``source`` (image or RPC file).

    Parameters
    ----------
    source : path of an image with an RPC or of a standalone RPC file.
    dem : optional DEM (path or :class:`DEM`); the footprint corners are localised on it, else at HEIGHT_OFF.
    geoid : the DEM's vertical datum when it is a path (``"egm96"``, ...).
    rpc : an :class:`RPCModel` (``source``'s RPC as it is), or the path of the RPC file of an image that carries none
        (a crop and its product's ``.geom``: the crop's origin is applied, :func:`gdal_gf4cal.crop.image_rpc`);
        default the image's own RPC, else the RPC file named like it beside it.

    Returns
    -------
    dict with ``source``, ``format``, ``size`` (w, h), ``corners`` [(lon, lat, h)] clockwise from upper-left
    (GDAL pixel corners), ``footprint_wkt``, ``gsd_m`` {sample, line}, ``height_range_m``, ``rpc`` (offsets/scales),
    ``warnings`` (one-line strings: an image the RPC's image domain does not cover, corners that do not localise),
    ``notes`` (the RPC file paired with the image, the crop origin applied).
    The size is the image's when there is one (``source`` itself, or the image next to a .RPB/_RPC.TXT sidecar),
    else guessed from the RPC's offsets and scales.
    """
    rpc, rpc_file, fmt, note = _rpc_of(source, rpc)
    image = os.fspath(source) if rpc_file else _image_of(source, fmt)
    size = image_size_of(image) if image is not None else None
    size_from_image = size is not None
    warnings = []
    if size is None:
        size = rpc.image_size
    W, H = size
    if size_from_image:
        uncovered = _uncovered(rpc, W, H)
        if uncovered:
            warnings.append(f"the RPC's image domain ({uncovered}) does not cover the {W} x {H} px image: "
                            "localisation extrapolates the RPC there (a cropped RPC?)")
    lon, lat, h, where = _footprint(rpc, source, W, H, dem, geoid)
    failed = [name for name, a in zip(_CORNERS, lon) if not np.isfinite(a)]
    if failed:
        warnings.append(f"the RPC does not localise the {', '.join(failed)} corner(s) (NaN): the image lies outside "
                        "what the RPC can invert; check that this RPC belongs to this image")
    gsd_s, gsd_l = _gsd_m(rpc, W, H)
    md = rpc.to_gdal_metadata()
    info = {
        "source": os.fspath(source),
        "format": fmt,
        "size": [int(W), int(H)],
        "size_from_image": size_from_image,
        "footprint_height": where,
        "corners": [[float(a), float(b), float(c)] for a, b, c in zip(lon, lat, h)],
        "footprint_wkt": "POLYGON ((" + ", ".join(f"{a:.9f} {b:.9f}" for a, b in
                                                  list(zip(lon, lat)) + [(lon[0], lat[0])]) + "))",
        "gsd_m": {"sample": gsd_s, "line": gsd_l},
        "height_range_m": list(rpc.height_range),
        "rpc": {k: float(md[k]) for k in ("LINE_OFF", "SAMP_OFF", "LAT_OFF", "LONG_OFF", "HEIGHT_OFF",
                                          "LINE_SCALE", "SAMP_SCALE", "LAT_SCALE", "LONG_SCALE", "HEIGHT_SCALE")},
        "err_bias": rpc.err_bias,
        "err_rand": rpc.err_rand,
    }
    info["warnings"] = warnings
    if rpc_file:
        info["rpc_file"] = rpc_file
    if note:
        info["notes"] = [note]
    if dem is not None:
        info["dem_height_range_m"] = [float(np.min(h)), float(np.max(h))]
    return info


def _rpc_of(source, rpc):
    """``(rpc, rpc_file, format, note)`` of ``source``: the model given, or read from ``rpc`` / the image / the
    RPC file beside it (``rpc_file`` None when the image carries its RPC)."""
    note = None
    if isinstance(rpc, RPCModel):
        rpc_file = None
    else:
        rpc_file = os.fspath(rpc) if rpc is not None else None
        rpc, note = image_rpc(source, rpc_file)
    try:
        fmt = rpc_file_format(rpc_file or source)
    except RPCFormatError:                      # an image without an RPC: the file beside it image_rpc took
        rpc_file = sidecar_rpc(source)
        fmt = rpc_file_format(rpc_file)
    return rpc, rpc_file, fmt, note


def _footprint(rpc: RPCModel, source, W: int, H: int, dem, geoid):
    """``(lon, lat, h, where)`` of the image corners (clockwise from upper-left) localised on the DEM (refused
    where it does not cover them) or at HEIGHT_OFF; ``where`` says which."""
    s = np.array([0.0, W, W, 0.0])
    l = np.array([0.0, 0.0, H, H])
    if dem is not None:
        dem_obj = DEM.from_user_input(dem, geoid=geoid)
        lon, lat, h = rpc.localize_dem(s, l, dem_obj)
        if not np.all(np.isfinite(h)):
            raise DEMError(f"the footprint of {source} is not covered by the DEM {getattr(dem_obj, 'path', dem)}; "
                           "use a DEM covering the scene or omit --dem")
        return lon, lat, h, f"DEM {getattr(dem_obj, 'path', dem)}"
    h = np.full(4, rpc.height_off)
    lon, lat = rpc.localize(s, l, h)
    return lon, lat, h, f"constant height HEIGHT_OFF = {rpc.height_off:.1f} m"


def _gsd_m(rpc: RPCModel, W: int, H: int):
    """GSD at the image centre from the localisation Jacobian: metres on the ground per pixel along each axis."""
    cs, cl = W / 2.0, H / 2.0
    hc = rpc.height_off
    lo, la = rpc.localize(np.array([cs, cs + 1, cs]), np.array([cl, cl, cl + 1]), hc)
    m_per_deg_lat = 111132.954 - 559.822 * np.cos(2 * np.radians(la[0]))
    m_per_deg_lon = 111412.84 * np.cos(np.radians(la[0]))
    gsd_s = float(np.hypot((lo[1] - lo[0]) * m_per_deg_lon, (la[1] - la[0]) * m_per_deg_lat))
    gsd_l = float(np.hypot((lo[2] - lo[0]) * m_per_deg_lon, (la[2] - la[0]) * m_per_deg_lat))
    return gsd_s, gsd_l
