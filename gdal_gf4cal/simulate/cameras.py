"""Camera helpers for the simulator (METHODS §5, §10): building, cropping and distorting look-angle models.

The simulator's cameras are :class:`gdal_gf4cal.camera.LookAngleModel` objects (cubic in the detector numbers)
so that every injected error stays inside the model the calibration solves for. :class:`PiecewiseCamera` joins
several sub-CCD cubics along the sample axis (GF7's three sub-CCDs per band, METHODS §9).
"""
from __future__ import annotations

import json
from math import comb
from typing import List, Sequence, Tuple

import numpy as np

from ..atomic import atomic_output
from ..camera import LookAngleModel, lookangle_terms
from ..outputs import check_output_path

#: Exponents (of s, of l) of the ten look-angle terms, in the camera module's order.
TERM_EXPONENTS = [(0, 0), (1, 0), (0, 1), (1, 1), (2, 0), (0, 2), (2, 1), (1, 2), (3, 0), (0, 3)]


def shift_coefficients(coef, ds: float, dl: float) -> np.ndarray:
    """Coefficients ``c'`` with ``p'(s, l) = p(s + ds, l + dl)`` for a cubic ``p`` in the ten-term basis (exact).

    Used by ``--size`` crops: the crop's detector ``(s, l)`` is the full array's ``(s + ds, l + dl)``.
    """
    coef = np.asarray(coef, dtype=float)
    index = {e: k for k, e in enumerate(TERM_EXPONENTS)}
    out = np.zeros(10)
    for k, (i, j) in enumerate(TERM_EXPONENTS):
        # (s + ds)^i (l + dl)^j expanded binomially; every produced monomial is in the basis.
        for a in range(i + 1):
            for b in range(j + 1):
                out[index[(a, b)]] += coef[k] * comb(i, a) * ds ** (i - a) * comb(j, b) * dl ** (j - b)
    return out


def crop_camera(cam: LookAngleModel, offset: Tuple[float, float], size: Tuple[int, int], **kw) -> LookAngleModel:
    """The camera of a crop starting at detector ``offset`` (full-array pixels) with ``size`` (W, H)."""
    return LookAngleModel(size=size, x=shift_coefficients(cam.x, *offset), y=shift_coefficients(cam.y, *offset),
                          name=kw.get("name", cam.name), notes=kw.get("notes", cam.notes))


def camera_from_normalised_polys(size, fx, fy, name="", notes="") -> LookAngleModel:
    """A camera from two callables ``f(u, v)`` in normalised coordinates (u, v in [-1, 1]); must be cubic.

    Fitted on a 7 x 7 grid in normalised coordinates, which is exact for cubic callables.
    """
    W, H = size
    g = np.linspace(-1, 1, 7)
    u, v = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    A = lookangle_terms(u, v).T
    cx, *_ = np.linalg.lstsq(A, fx(u, v), rcond=None)
    cy, *_ = np.linalg.lstsq(A, fy(u, v), rcond=None)
    return LookAngleModel.from_normalised_coefficients((W, H), cx, cy, name=name, notes=notes)


class PiecewiseCamera:
    """Sub-CCD cubics joined along the sample axis of one image (push-broom only: no l dependence).

    Parameters
    ----------
    pieces : list of :class:`LookAngleModel`, each expressed in the *image's* sample coordinates.
    edges : sample boundaries ``[0, e1, ..., W]`` (len(pieces) + 1); piece k covers ``edges[k] <= s < edges[k+1]``.
    """

    model_name = "lookangle-piecewise"

    def __init__(self, size, pieces: Sequence[LookAngleModel], edges: Sequence[float], name: str = "", notes: str = ""):
        self.size = (int(size[0]), int(size[1]))
        self.pieces: List[LookAngleModel] = list(pieces)
        self.edges = np.asarray(edges, dtype=float)
        if self.edges.size != len(self.pieces) + 1:
            raise ValueError("edges must have one more entry than pieces")
        self.name, self.notes = name, notes

    def piece_index(self, s):
        return np.clip(np.searchsorted(self.edges, np.asarray(s, dtype=float), side="right") - 1, 0,
                       len(self.pieces) - 1)

    def tan_angles(self, s, l):
        s, l = np.broadcast_arrays(np.asarray(s, dtype=float), np.asarray(l, dtype=float))
        k = self.piece_index(s)
        tx, ty = np.empty(s.shape), np.empty(s.shape)
        for i, cam in enumerate(self.pieces):
            m = k == i
            if np.any(m):
                tx[m], ty[m] = cam.tan_angles(s[m], l[m])
        if s.shape == ():
            return float(tx), float(ty)
        return tx, ty

    def jacobian(self, s, l):
        s, l = np.broadcast_arrays(np.asarray(s, dtype=float), np.asarray(l, dtype=float))
        k = self.piece_index(s)
        J = np.empty(s.shape + (2, 2))
        for i, cam in enumerate(self.pieces):
            m = k == i
            if np.any(m):
                J[m] = cam.jacobian(s[m], l[m])
        return J

    def to_dict(self) -> dict:
        return {"model": self.model_name, "size": list(self.size), "edges": [float(e) for e in self.edges],
                "pieces": [p.to_dict() for p in self.pieces], "pixel_convention": "gdal", "name": self.name,
                "notes": self.notes}

    @classmethod
    def from_dict(cls, d: dict) -> "PiecewiseCamera":
        return cls(d["size"], [LookAngleModel.from_dict(p) for p in d["pieces"]], d["edges"], d.get("name", ""),
                   d.get("notes", ""))

    def to_json(self, path, overwrite: bool = False) -> str:
        return write_json_atomic(path, self.to_dict(), overwrite=overwrite)


def camera_from_dict(d: dict):
    """A :class:`LookAngleModel` or :class:`PiecewiseCamera` from its JSON dict."""
    if d.get("model") == PiecewiseCamera.model_name:
        return PiecewiseCamera.from_dict(d)
    return LookAngleModel.from_dict(d)


def write_json_atomic(path, obj, overwrite: bool = False) -> str:
    path = check_output_path(path, overwrite=overwrite)
    with atomic_output(path) as tmp, open(tmp, "w") as fh:
        json.dump(obj, fh, indent=2, default=_json_default)
        fh.write("\n")
    return path


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if hasattr(o, "to_dict"):
        return o.to_dict()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
