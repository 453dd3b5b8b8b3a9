"""What a compensation reports besides its coefficients (METHODS §6): accuracy per role, suspected blunders and
the warnings when the check points disagree with the estimate.

The accuracy report is the one :func:`gdal_gf4cal.stats.accuracy_by_role` (re-exported here, with the ground
offsets :func:`~gdal_gf4cal.stats.ground_offsets_m` it uses for ``ce90_m``).
"""
from __future__ import annotations

import math
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..stats import accuracy_by_role, axis_stats, ground_jacobian, ground_offsets_m, model_jacobian

__all__ = ["accuracy_by_role", "ground_offsets_m", "ground_jacobian", "suspected_blunders", "describe_suspects",
           "check_point_warnings"]

#: The sensor Jacobian ``d(sample, line)/d(lon, lat, h)`` (:func:`gdal_gf4cal.stats.model_jacobian`).
_jacobian = model_jacobian


def _f(x) -> Optional[float]:
    x = float(x)
    return x if math.isfinite(x) else None


def report_axis_stats(x) -> Dict[str, Optional[float]]:
    """``{mean, rms, std, max}`` (px) of one axis, :func:`gdal_gf4cal.stats.axis_stats`; None when empty."""
    return {k: _f(v) for k, v in axis_stats(x).items() if k != "n"}


def suspected_blunders(tab, n: int = 3) -> List[Tuple[str, str, float]]:
    """The control points most likely to be blunders when the check points fit worse after compensation than
    before: ``(id, role, planar residual after compensation px)`` of the ``n`` control points in the estimate with
    the largest normalised residuals (a blunder in the fit drags the correction and leaves residuals on its
    fellow points too, so the list is where to look, not a verdict; check points are only its victims). Empty
    when the check points fit as well or better."""
    rms = _check_rms(tab)
    if rms is None or not rms[1] > rms[0]:
        return []
    cand = (tab["role"] == "control").to_numpy() & ~tab["outlier"].to_numpy(bool)
    z = np.hypot(tab["norm_res_sample"].to_numpy(float), tab["norm_res_line"].to_numpy(float))
    z = np.where(cand, np.nan_to_num(z, nan=0.0), -np.inf)
    order = np.lexsort((np.arange(z.size), -z))[:min(n, int(cand.sum()))]   # ties: input order
    r = np.hypot(tab["res_sample_after"].to_numpy(float), tab["res_line_after"].to_numpy(float))
    ids, roles = tab["id"].astype(str).to_numpy(), tab["role"].astype(str).to_numpy()
    return [(ids[i], roles[i], float(r[i])) for i in order]


def _check_rms(tab) -> Optional[Tuple[float, float]]:
    """Planar rms (px) of the unflagged check points before and after compensation; None without any."""
    sel = (tab["role"].to_numpy() == "check") & ~tab["outlier"].to_numpy(bool)
    if not sel.any():
        return None
    return tuple(float(np.sqrt(np.mean(tab[f"res_sample_{w}"].to_numpy(float)[sel] ** 2
                                       + tab[f"res_line_{w}"].to_numpy(float)[sel] ** 2)))
                 for w in ("before", "after"))


def describe_suspects(suspects) -> str:
    """``g1 (control, 31.2 px), ...`` for a message."""
    return ", ".join(f"{i} ({role}, {r:.1f} px)" for i, role, r in suspects)


def check_point_warnings(tab) -> List[str]:
    """Warnings when the check points disagree with the compensation: they fit worse after it than before
    (blunders suspected: the worst points named), or most of them are flagged as blunders."""
    chk = tab["role"].to_numpy() == "check"
    if not chk.any():
        return []
    outl = tab["outlier"].to_numpy(bool)
    out: List[str] = []
    if 2 * int((chk & outl).sum()) > int(chk.sum()):
        out.append(f"{int((chk & outl).sum())} of the {int(chk.sum())} check points are flagged as blunders: the "
                   "check points disagree with the compensation; check the GCPs (wrong heights, other image) or the "
                   "model")
    rms = _check_rms(tab)
    if rms is not None and rms[1] > rms[0]:
        out.append(f"the {int((chk & ~outl).sum())} check points fit worse after compensation than before (planar "
                   f"rms {rms[0]:.3g} -> {rms[1]:.3g} px): blunders are suspected among the GCPs; the worst: "
                   f"{describe_suspects(suspected_blunders(tab))}; check or remove them, or choose a simpler model")
    return out


#: Former private name (tests and callers of the single-module version).
_worse_check_warning = check_point_warnings
