"""Which polynomial terms the observations support (METHODS §8, coverage): terms whose extrapolation over the
detector or the strip the observations cannot bound are held at 0 before solving."""
from __future__ import annotations

from typing import List, Mapping

import numpy as np

from ..basis import detector_polynomial
from .layout import BlockLayout
from .model import EXTERIOR_NAMES, INTERIOR_NAMES

#: A polynomial term is estimated only where its observations support it (METHODS §8, coverage): the largest
#: prediction variance of the polynomial over the whole detector (interior, in ``u``) or the whole strip (exterior
#: drifts, in ``t``) at most this many times its largest at an observation (5x the standard deviation: a cubic
#: needs about 70 % of the detector when centred, 78 % from one edge; a slope a third of it). Higher terms are held
#: at 0 before solving: an interior cubic fitted on 800 of 40,000 detector columns extrapolated to tens of pixels.
#: Full coverage gives 1.
MAX_EXTRAPOLATION_VARIANCE = 25.0


def supported_degree(x, max_degree: int = 3) -> int:
    """The highest polynomial degree (<= ``max_degree``) in ``x`` (normalised to [-1, 1] over the detector or strip)
    that observations at ``x`` support: its largest prediction variance (leverage) over [-1, 1] at most
    :data:`MAX_EXTRAPOLATION_VARIANCE` x its largest at the observations. Computed in coordinates centred on the
    observations (the leverage does not depend on the polynomial basis)."""
    x = np.unique(np.asarray(x, float)[np.isfinite(x)])
    if x.size < 2:
        return 0
    c, r = 0.5 * (x.max() + x.min()), 0.5 * (x.max() - x.min())
    if not r > 0:
        return 0
    grid = (np.linspace(-1.0, 1.0, 201) - c) / r
    for d in range(min(max_degree, x.size - 1), 0, -1):
        q, rr = np.linalg.qr(detector_polynomial((x - c) / r, d))
        if not np.all(np.abs(np.diag(rr)) > 1e-9 * np.abs(rr).max()):
            continue
        g = np.linalg.solve(rr.T, detector_polynomial(grid, d).T)      # R^-T p: its squared norm is the leverage
        if np.max(np.sum(g * g, axis=0)) <= MAX_EXTRAPOLATION_VARIANCE * np.max(np.sum(q * q, axis=1)):
            return d
    return 0


def unsupported_terms(tab, layout: "BlockLayout", index: Mapping[str, np.ndarray], p: int, interiors: bool = True):
    """Parameters the observations cannot support (held at 0 before solving) and the warnings saying so: per image
    the interior terms above :func:`supported_degree` of its observations' detector positions ``u``; the exterior
    drifts ``e3, e4`` when the observations' times ``t`` do not support a slope (METHODS §8). ``interiors=False``:
    the interiors are not estimated (a calibration's), only the drifts are judged."""
    used = (tab["kind"] == "tie").to_numpy() | (tab["role"] == "control").to_numpy()
    img = tab["image_id"].to_numpy(object)
    s_all, l_all = tab["sample"].to_numpy(float), tab["line"].to_numpy(float)
    off = np.zeros(p, bool)
    warns: List[str] = []
    times = []
    for im, lay in layout.images.items():
        m = used & (img == im)
        W, H = lay.size
        times.append(lay.ratio * (l_all[m] - H / 2.0) / layout.time_scale)
        d = supported_degree((s_all[m] - W / 2.0) / (W / 2.0)) if interiors else 3
        if d < 3:
            held = [n for n in INTERIOR_NAMES if int(n[1]) > d]
            off[index[im][5:][[INTERIOR_NAMES.index(n) for n in held]]] = True
            lo, hi = (np.nanmin(s_all[m]), np.nanmax(s_all[m])) if m.any() else (0.0, 0.0)
            warns.append(f"{im}: the observations cover detector columns {lo:.0f}..{hi:.0f} of {W} "
                         f"({(hi - lo) / W:.0%}): its interior is estimated to degree {d} only ({', '.join(held)} "
                         "held at 0, not extrapolated over the detector); add ties or GCPs across the whole width "
                         "for a full calibration")
    t = np.concatenate(times) if times else np.zeros(0)
    if supported_degree(t, 1) < 1:
        off[[EXTERIOR_NAMES.index("e3"), EXTERIOR_NAMES.index("e4")]] = True
        warns.append(f"the observations cover {np.ptp(t) / 2 if t.size else 0:.0%} of the strip's time (lines): "
                     "the exterior drifts e3, e4 are held at 0 (not extrapolated); add GCPs or ties along the whole "
                     "image height to estimate them")
    return off, warns


