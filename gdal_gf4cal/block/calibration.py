"""The group's calibration file (``calibration.json``, model ``block-rpc-cubic``): written from an estimate, read
back, applied to another scene's image."""
from __future__ import annotations

import json
import os
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np

from ..atomic import atomic_output
from ..report import write_report_json
from .estimate import BlockEstimate
from .layout import BlockError, ImageLayout
from .model import EXTERIOR_NAMES, INTERIOR_NAMES, BlockCorrectedRPC, ImageCorrection

CALIBRATION_MODEL = "block-rpc-cubic"


def calibration_dict(estimate: BlockEstimate, keys: Optional[Mapping[str, str]] = None) -> Dict[str, Any]:
    """The group's calibration (exterior + interior per CCD and band, with the layout) as a JSON-ready dict.

    ``keys`` maps image ids to the names other scenes' images are matched by (default: the ids)."""
    keys = dict(keys or {})
    lay = estimate.layout
    ext = estimate.block("exterior")
    images = {}
    for im in lay.images:
        c = estimate.correction(im).to_dict()
        c["reference"] = keys.get(c["reference"], c["reference"])
        images[keys.get(im, im)] = c
    return {"model": CALIBRATION_MODEL, "method": "METHODS §8 block calibration in RPC space",
            "pixel_convention": "gdal",
            "definition": "s = s_RPC + (e0 + e3 t - kappa Y)/r + sum a_j u^j; l = l_RPC + (e1 + e4 t + kappa X(u))/r + "
                          "sum b_j u^j; u = (s - W/2)/(W/2); t = r (l - H/2)/time_scale; X(u) = x0_px + r (W/2) u; "
                          "kappa = kappa_mrad * 1e-3",
            "exterior": {n: float(v) for n, v in zip(EXTERIOR_NAMES, ext)},
            "reference_ccd": keys.get(lay.reference_ccd, lay.reference_ccd),
            "order": [keys.get(o, o) for o in lay.order], "time_scale": lay.time_scale, "images": images}


def write_calibration(cal: Mapping[str, Any], path) -> str:
    """Write a calibration dict as JSON (atomic)."""
    path = os.fspath(path)
    with atomic_output(path) as tmp:
        write_report_json(dict(cal), tmp)
    return path


def read_calibration(path) -> Dict[str, Any]:
    """Read a block ``calibration.json``; :class:`BlockError` if it is not one."""
    try:
        with open(os.fspath(path), encoding="utf-8") as f:
            cal = json.load(f)
    except (OSError, ValueError) as exc:
        raise BlockError(f"cannot read the calibration {path}: {str(exc).splitlines()[0]}") from None
    if not isinstance(cal, dict) or cal.get("model") != CALIBRATION_MODEL:
        raise BlockError(f"{path} is not a block calibration (model {CALIBRATION_MODEL!r}); give the "
                         "calibration.json written by block-adjust")
    return cal


def calibrated_model(cal: Mapping[str, Any], key: str, rpc, size: Optional[Tuple[int, int]] = None
                     ) -> BlockCorrectedRPC:
    """The model of another scene's image ``key`` (same camera and group) with the calibration applied."""
    images = cal["images"]
    if key not in images:
        raise BlockError(f"image {key!r} is not in the calibration (images: {', '.join(list(images)[:8])}); name the "
                         "scenes' images as in the calibrated group")
    c = images[key]
    sz = tuple(int(v) for v in c["size"])
    if size is not None and tuple(size) != sz:
        raise BlockError(f"{key}: image size {tuple(size)} differs from the calibrated one {sz}; the calibration "
                         "applies to images of the same CCD and band")
    lay = ImageLayout(key, c["reference"], int(c["ccd"]), sz, float(c["ratio"]), float(c["x0_px"]),
                      float(c.get("y_px", 0.0)))
    ext = np.array([float(cal["exterior"][n]) for n in EXTERIOR_NAMES])
    inter = np.array([float(c["interior"][n]) for n in INTERIOR_NAMES])
    return BlockCorrectedRPC(rpc, ImageCorrection(lay, float(cal["time_scale"]), ext, inter))





