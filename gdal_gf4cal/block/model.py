"""The block correction of one image (METHODS §8, module docstring of :mod:`gdal_gf4cal.block`): parameter names
and blocks, the local design ``d(ds, dl)/d[exterior, interior]``, the correction and the corrected sensor model."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, List, Tuple

import numpy as np

from ..estimation import Block
from ..sensor import SensorModelMixin
from .layout import BlockLayout, ImageLayout

EXTERIOR_NAMES = ("e0", "e1", "e3", "e4", "kappa_mrad")
INTERIOR_NAMES = ("a0", "a1", "a2", "a3", "b0", "b1", "b2", "b3")
#: Interior terms of the reference CCD that duplicate the exterior (e0, e1, kappa): fixed at 0 (METHODS §8 datum).
DATUM_TERMS = ("a0", "b0", "b1")


def local_design(im: ImageLayout, time_scale: float, s, l) -> np.ndarray:
    """``(n, 2, 13)`` derivatives of the (sample, line) correction of image ``im`` at measured ``(s, l)`` by
    ``[e0, e1, e3, e4, kappa_mrad, a0..a3, b0..b3]`` (module docstring)."""
    s = np.asarray(s, float).ravel()
    l = np.asarray(l, float).ravel()
    W, H = im.size
    u = (s - W / 2.0) / (W / 2.0)
    t = im.ratio * (l - H / 2.0) / time_scale
    r = im.ratio
    n = s.size
    d = np.zeros((n, 2, 13))
    d[:, 0, 0] = 1.0 / r
    d[:, 0, 2] = t / r
    d[:, 0, 4] = -1e-3 * im.y_px / r
    d[:, 1, 1] = 1.0 / r
    d[:, 1, 3] = t / r
    d[:, 1, 4] = 1e-3 * (im.x0_px / r + (W / 2.0) * u)
    pw = np.stack([np.ones(n), u, u * u, u ** 3], axis=1)
    d[:, 0, 5:9] = pw
    d[:, 1, 9:13] = pw
    return d


@dataclass
class ImageCorrection:
    """The block correction of one image: exterior (5) and interior (8) values with its layout entry."""

    layout: ImageLayout
    time_scale: float
    exterior: np.ndarray
    interior: np.ndarray

    def correction(self, sample, line) -> Tuple[np.ndarray, np.ndarray]:
        """(ds, dl) px at measured GDAL-convention ``(sample, line)``."""
        d = local_design(self.layout, self.time_scale, sample, line)
        v = d @ np.concatenate([self.exterior, self.interior])
        return v[:, 0], v[:, 1]

    def to_dict(self) -> Dict[str, Any]:
        im = self.layout
        return {"reference": im.reference, "ccd": im.ccd, "size": list(im.size), "ratio": im.ratio,
                "x0_px": im.x0_px, "y_px": im.y_px,
                "interior": {n: float(v) for n, v in zip(INTERIOR_NAMES, self.interior)}}


class BlockCorrectedRPC(SensorModelMixin):
    """An image's RPC with its block correction (METHODS §8): ``project`` solves ``s = s_RPC + E + I(u(s))`` by
    fixed-point iteration (the correction's slope is far below 1), ``localize`` removes the correction from the
    measured position and localises it with the RPC. GDAL pixel convention. No writers: fit an RPC of it
    (:func:`gdal_gf4cal.rpc_fit.fit_rpc_from_model`)."""

    def __init__(self, rpc, corr: ImageCorrection):
        self.rpc, self.corr = rpc, corr
        self.size = tuple(corr.layout.size)

    @property
    def height_range(self):
        return tuple(self.rpc.height_range)

    def _project_gdal(self, lon, lat, h):
        s0, l0 = self.rpc.project(lon, lat, h)
        s0 = np.asarray(s0, float).ravel()
        l0 = np.asarray(l0, float).ravel()
        s, l = s0.copy(), l0.copy()
        for _ in range(30):
            ds, dl = self.corr.correction(s, l)
            ns, nl = s0 + ds, l0 + dl
            done = np.nanmax(np.abs(np.concatenate([ns - s, nl - l]))) if ns.size else 0.0
            s, l = ns, nl
            if not done > 1e-10:
                break
        return s, l

    def _localize_gdal(self, sample, line, h):
        ds, dl = self.corr.correction(sample, line)
        return self.rpc.localize(np.asarray(sample, float).ravel() - ds, np.asarray(line, float).ravel() - dl, h)


def parameter_blocks(layout: BlockLayout) -> Tuple[List[Block], Dict[str, np.ndarray]]:
    """Named blocks (``exterior``, ``datum:<ref>``, ``interior:<image>``) and per image the 13 global indices of
    ``[exterior, a0..a3, b0..b3]``."""
    blocks = [Block("exterior", EXTERIOR_NAMES)]
    pos = len(EXTERIOR_NAMES)
    index: Dict[str, np.ndarray] = {}
    for im in layout.images:
        if im == layout.reference_ccd:
            datum = [n for n in INTERIOR_NAMES if n in DATUM_TERMS]
            rest = [n for n in INTERIOR_NAMES if n not in DATUM_TERMS]
            blocks.append(Block(f"datum:{im}", [f"{im}.{n}" for n in datum]))
            blocks.append(Block(f"interior:{im}", [f"{im}.{n}" for n in rest]))
            where = {n: pos + i for i, n in enumerate(datum + rest)}
            pos += 8
        else:
            blocks.append(Block(f"interior:{im}", [f"{im}.{n}" for n in INTERIOR_NAMES]))
            where = {n: pos + i for i, n in enumerate(INTERIOR_NAMES)}
            pos += 8
        index[im] = np.array(list(range(len(EXTERIOR_NAMES))) + [where[n] for n in INTERIOR_NAMES])
    return blocks, index


