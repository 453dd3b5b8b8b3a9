"""Crops that state their place in the product: the RPC of an image's own pixel grid (METHODS §1).

Stereo and pan-MS test crops (CNES Shareloc, CARS) keep the product's RPC beside a crop whose GeoTIFF carries its
origin in the product as a *pixel-unit geotransform without CRS*: ``(col0, 1, 0, row0, 0, 1)``. GDAL's meaning of
that geotransform is "crop pixel (x, y) is product pixel (col0 + x, row0 + y)" (corner convention on both sides, so
the shift is the same in GDAL's and RPC00B's pixel conventions). :func:`image_rpc` is the one place every command
turns "an image plus an RPC" into the RPC of the image's pixels:

* the image's own RPC (tags, ``.RPB``/``_RPC.TXT`` sidecars GDAL finds, or any raster of the image's size, such as
  a VRT over it) is the image's: never shifted;
* an image without an RPC of its own takes the RPC file named like it beside it (:data:`SIDECAR_SUFFIXES`, e.g.
  Shareloc's ``left_image.tif`` + ``left_image.geom``; :func:`sidecar_rpc`) as an RPC given apart from it, and the
  note names that file;
* an RPC given apart from the image (an OSSIM ``.geom``, DIMAP ``RPC_*.XML``, ``.RPB`` file, the full product's
  raster, or an :class:`RPCModel`) beside a pixel-unit geotransform without CRS is the product's: it is shifted by
  the origin (``RPCModel.with_image_affine``) when the crop then lies inside the RPC's image domain, and a one-line
  note says so;
* where that RPC already describes the crop's pixels (the crop lies inside its domain as it is, and the domain starts
  farther than half the origin before pixel 0, as an RPC shifted once does), nothing is applied and the note says why;
* refused (:class:`RPCFormatError`, one line): a geotransform without CRS that is rotated or has a pixel size other
  than 1 (a resampled crop: its relation to the product's pixels is not stated exactly), or a crop that, placed at
  its origin, lies outside the RPC's image domain (normalised coordinates beyond ±:data:`DOMAIN_LIMIT`) when the RPC
  is not one already moved to the crop.

A geotransform with a CRS is a map georeference, not a crop origin (nothing applied), except a local (engineering)
CRS of unnamed units, which some tools write for pixel coordinates; a geotransform without CRS whose pixel height is
negative is a north-up map transform whose CRS was lost (nothing applied).
"""
from __future__ import annotations

import os
from typing import List, Mapping, Optional, Sequence, Tuple

import numpy as np

from ._gdal import try_open_raster
from .errors import RPCFormatError
from .rpc import RPCModel

#: Names (``<stem><suffix>``) of an RPC file beside an image that has none of its own, in the order tried; GDAL
#: itself reads ``<stem>.RPB`` / ``<stem>_RPC.TXT`` as the image's own RPC for the formats it knows them for.
SIDECAR_SUFFIXES = (".geom", ".GEOM", ".RPB", ".rpb", "_RPC.TXT", "_rpc.txt", ".XML", ".xml")

#: The end of :func:`image_rpc`'s note when it moved a product's RPC to the crop.
SHIFTED = "RPC shifted by the origin"

#: A crop is inside an RPC's image domain when its corners' normalised image coordinates are within this bound.
DOMAIN_LIMIT = 1.1


def _pixel_geotransform(image_path) -> Tuple[Optional[tuple], Optional[Tuple[int, int]], list]:
    """(geotransform if the image has one without CRS else None, (width, height) or None, the image's files)."""
    ds = try_open_raster(image_path)
    if ds is None or ds.RasterCount == 0:
        return None, None, []
    size = (ds.RasterXSize, ds.RasterYSize)
    files = list(ds.GetFileList() or [])
    gt = ds.GetGeoTransform(can_return_null=True)
    srs = ds.GetSpatialRef()
    if gt is None or (srs is not None and not srs.IsLocal()):      # an engineering CRS is pixel units too
        return None, size, files
    return tuple(float(v) for v in gt), size, files


def _is_unit(gt) -> bool:
    return gt[1] == 1.0 and gt[5] == 1.0 and gt[2] == 0.0 and gt[4] == 0.0


def crop_origin(image_path) -> Optional[Tuple[float, float]]:
    """``(col0, row0)`` of a crop in its product, from a pixel-unit geotransform without CRS
    (``(col0, 1, 0, row0, 0, 1)``, origin not (0, 0)); ``None`` for any other image."""
    gt, _size, _files = _pixel_geotransform(image_path)
    if gt is None or not _is_unit(gt) or (gt[0] == 0.0 and gt[3] == 0.0):
        return None
    return (gt[0], gt[3])


def _normalised_extent(rpc: RPCModel, col0: float, row0: float, size: Tuple[int, int]) -> float:
    """Largest |normalised image coordinate| of the crop's corners placed at (col0, row0) in the RPC's pixels."""
    W, H = size
    s = np.array([col0, col0 + W]) - 0.5        # GDAL corner coordinates -> RPC00B convention
    l = np.array([row0, row0 + H]) - 0.5
    return float(max(np.max(np.abs((s - rpc.samp_off) / rpc.samp_scale)),
                     np.max(np.abs((l - rpc.line_off) / rpc.line_scale))))


def _domain_start(rpc: RPCModel) -> Tuple[float, float]:
    """(sample, line) where the RPC's image domain (offset - |scale|) begins, GDAL convention."""
    return (rpc.samp_off + 0.5 - abs(rpc.samp_scale), rpc.line_off + 0.5 - abs(rpc.line_scale))


def _already_shifted(rpc: RPCModel, col0: float, row0: float) -> bool:
    """True when the RPC's domain starts more than half the origin before pixel 0 on an axis with an origin: an RPC
    already moved to the crop (a product RPC's domain starts near its pixel 0)."""
    s0, l0 = _domain_start(rpc)
    return (col0 > 0 and s0 < -0.5 * col0) or (row0 > 0 and l0 < -0.5 * row0)


def _is_own(image_path, rpc_path, image_files, image_size) -> bool:
    """True when ``rpc_path`` is the image, one of its sidecars, or a raster of the image's size (its RPC is then
    that raster's, i.e. the image's pixel grid)."""
    real = os.path.realpath(os.fspath(rpc_path))
    if real in {os.path.realpath(os.fspath(p)) for p in [image_path, *image_files]}:
        return True
    low = real.lower()
    if low.endswith((".rpb", "_rpc.txt", ".txt", ".json", ".geom", ".xml")):
        return False
    ds = try_open_raster(rpc_path)
    return ds is not None and ds.RasterCount > 0 and (ds.RasterXSize, ds.RasterYSize) == tuple(image_size)


def sidecar_rpc(image_path) -> Optional[str]:
    """The first existing ``<stem><suffix>`` beside ``image_path`` for :data:`SIDECAR_SUFFIXES`, else ``None``."""
    stem = os.path.splitext(os.fspath(image_path))[0]
    for suffix in SIDECAR_SUFFIXES:
        if os.path.isfile(stem + suffix) and os.path.realpath(stem + suffix) != os.path.realpath(image_path):
            return stem + suffix
    return None


def image_and_rpc(entry) -> Tuple[str, Optional[str]]:
    """``IMAGE=RPC`` (an image whose RPC is a separate file, e.g. a crop and its product's ``.geom``) -> the two
    paths; any other entry (an image with its RPC, or an RPC file) -> ``(entry, None)``."""
    entry = os.fspath(entry)
    if "=" in entry and not os.path.exists(entry):
        image, rpc = entry.split("=", 1)
        return image, rpc
    return entry, None


def paired_rpc_files(images: Sequence, pairs, what: str = "--rpc") -> List[Optional[str]]:
    """For each of ``images``, the RPC file ``pairs`` gives it (``["IMAGE=RPC", ...]`` or ``{image: rpc}``; IMAGE
    the image's path or file name), else ``None``. A pair that is not IMAGE=RPC or names no image given is refused
    (:class:`RPCFormatError` naming ``what``)."""
    items = pairs.items() if isinstance(pairs, Mapping) else [image_and_rpc(e) for e in (pairs or ())]
    paths = [os.fspath(p) for p in images]
    out: List[Optional[str]] = [None] * len(paths)
    for image, rpc in items:
        if not image or not rpc:
            raise RPCFormatError(f"{what} {image}: give IMAGE=RPC, the image and its RPC file (e.g. "
                                 "left.tif=left.geom)")
        image = os.fspath(image)
        hits = [i for i, p in enumerate(paths) if os.path.abspath(p) == os.path.abspath(image)] or \
            [i for i, p in enumerate(paths) if os.path.basename(p) == os.path.basename(image)]
        if len(hits) != 1:
            why = "is not among the images given" if not hits else "names more than one of the images given"
            raise RPCFormatError(f"{what} {image}={rpc}: {image} {why}; name the image as you gave it")
        out[hits[0]] = os.fspath(rpc)
    return out


def _own_or_beside(image_path: str):
    """The image's own RPC (note None), else the RPC file beside it (:func:`sidecar_rpc`) through
    :func:`image_rpc`, its note naming the file; the image's own error when there is neither."""
    try:
        return RPCModel.from_file(image_path), None
    except RPCFormatError:
        side = sidecar_rpc(image_path) if try_open_raster(image_path) is not None else None
        if side is None:
            raise
    model, note = image_rpc(image_path, side)
    where = f"RPC from {os.path.basename(side)} beside it"
    return model, (f"{note} ({where})" if note else f"{os.path.basename(image_path)}: {where}")


def image_rpc(image_path, rpc=None):
    """The RPC of ``image_path``'s own pixel grid and a one-line note (``None`` when nothing was applied).

    Parameters
    ----------
    image_path : path of the image (any GDAL raster)
    rpc : None (the image's own RPC, else the RPC file named like it beside it), the path of an RPC source, or an
        :class:`RPCModel` (other sensor models are returned as given)

    Returns
    -------
    (model, note)
        ``note`` e.g. ``"left_image.tif is a crop at (5000, 5000) of the product its RPC describes: RPC shifted by
        the origin"``.

    Raises
    ------
    RPCFormatError
        The RPC cannot be read, or the crop's relation to the RPC is ambiguous (see the module docstring).
    """
    image_path = os.fspath(image_path)
    if rpc is None:
        return _own_or_beside(image_path)
    gt, size, files = _pixel_geotransform(image_path)
    if isinstance(rpc, (str, os.PathLike)):
        model = RPCModel.from_file(os.fspath(rpc))
        if size is not None and _is_own(image_path, rpc, files, size):
            return model, None
    else:
        model = rpc
    if gt is None or not isinstance(model, RPCModel) or size is None:
        return model, None
    return _fit_to_crop(model, image_path, gt, size)


def product_rpc(image_path, rpc=None):
    """``(model, origin, note)``: the RPC :func:`image_rpc` finds for ``image_path`` in the *product's* pixels (a
    camera's or detector's own grid) and the image's origin there, ``(0.0, 0.0)`` when it is not a crop whose
    product's RPC was moved to it. ``model.with_image_affine(-origin[0], -origin[1])`` is the image's RPC."""
    model, note = image_rpc(image_path, rpc)
    origin = crop_origin(image_path) if note and SHIFTED in note else None
    if origin is None:
        return model, (0.0, 0.0), note
    return model.with_image_affine(*origin), origin, note


def _fit_to_crop(model: RPCModel, image_path: str, gt: tuple, size: Tuple[int, int]):
    name = os.path.basename(image_path)
    if gt[5] < 0 and gt[2] == 0.0 and gt[4] == 0.0:
        return model, None                      # a north-up map transform without its CRS: not a crop origin
    if not _is_unit(gt):
        raise RPCFormatError(
            f"{name} has a geotransform without CRS that is not a crop origin in product pixels (pixel size "
            f"{gt[1]:g} x {gt[5]:g}, rotation {gt[2]:g}, {gt[4]:g}): cannot tell which pixels the RPC describes; give "
            "the RPC of this image itself, or remove the geotransform (gdal_edit.py -unsetgt)")
    col0, row0 = gt[0], gt[3]
    if col0 == 0.0 and row0 == 0.0:
        return model, None
    where = f"({col0:g}, {row0:g})"
    shifted = _normalised_extent(model, col0, row0, size) <= DOMAIN_LIMIT
    already = _normalised_extent(model, 0.0, 0.0, size) <= DOMAIN_LIMIT and _already_shifted(model, col0, row0)
    if shifted and not already:
        return (model.with_image_affine(-col0, -row0),
                f"{name} is a crop at {where} of the product its RPC describes: {SHIFTED}")
    if already:
        return model, (f"{name} states a crop origin {where} but its RPC already describes the crop's pixels "
                       "(its image domain starts before the origin): origin not applied")
    s0, l0 = _domain_start(model)
    raise RPCFormatError(
        f"{name} is a crop at {where} ({size[0]} x {size[1]} px) outside the RPC's image domain (from "
        f"({s0:.0f}, {l0:.0f}), {2 * abs(model.samp_scale):.0f} x {2 * abs(model.line_scale):.0f} px): the RPC belongs to another product or "
        "the origin is wrong; give this image's product RPC, or remove the geotransform (gdal_edit.py -unsetgt)")


__all__ = ["DOMAIN_LIMIT", "SHIFTED", "SIDECAR_SUFFIXES", "crop_origin", "image_and_rpc", "image_rpc",
           "paired_rpc_files", "product_rpc", "sidecar_rpc"]
