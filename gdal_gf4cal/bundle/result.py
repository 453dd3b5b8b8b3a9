"""The result of a bundle adjustment and its report numbers (METHODS §6, §11).

:class:`BundleEstimate` is the core's :class:`~gdal_gf4cal.estimation.Estimate` (parameters: every view's
correction; per ray two residuals, sample then line) plus the views' corrections as
:class:`~gdal_gf4cal.compensation.CompensationResult` (the one correction class, folded or refitted into a new RPC
by :func:`~gdal_gf4cal.compensation.apply_compensation`), the tie points' ground, the reprojection before and after
(per view, per pair of views, all: RMS of the residual components over the rays in the estimate), the datum
drift and the residual table.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np
import pandas as pd

from ..compensation import CompensationResult, apply_compensation
from ..estimation import Estimate
from ..geodesy import metres_per_degree
from .model import Rays, ViewLayout

__all__ = ["BundleEstimate", "corrected_models", "reprojection", "view_correction"]


@dataclass
class BundleEstimate(Estimate):
    """A bundle adjustment (module docstring). Extra attributes:

    ``views``; ``corrections`` (view -> CompensationResult, frame ``(w/2, w/2, h/2, h/2)``); ``model_used`` (view ->
    model name); ``points`` (DataFrame ``point_id, kind, lon, lat, h, lon_before, lat_before, h_before, n_views,
    sigma_e_m, sigma_n_m, sigma_u_m``); ``reprojection`` (``{'before'|'after': {'per_view', 'per_pair', 'all'}}``,
    px); ``datum_drift_m`` (length of the mean move of the ties, m) and ``datum_drift_enu_m``; ``table`` (the
    observations with ``pred_/res_{sample,line}_{before,after}``, ``outlier``, ``outlier_level``, ``weight``);
    ``prior_px`` (per parameter); ``sizes``; ``reduced_size`` (the reduced system's side, = number of parameters);
    ``converged``.
    """

    views: List[str] = field(default_factory=list)
    corrections: Dict[str, CompensationResult] = field(default_factory=dict)
    model_used: Dict[str, str] = field(default_factory=dict)
    points: Any = None
    reprojection: Dict[str, Any] = field(default_factory=dict)
    datum_drift_m: float = float("nan")
    datum_drift_enu_m: Tuple[float, float, float] = (float("nan"),) * 3
    table: Any = None
    prior_px: Optional[np.ndarray] = None
    sizes: Dict[str, Tuple[int, int]] = field(default_factory=dict)
    reduced_size: int = 0
    converged: bool = False

    def to_dict(self) -> Dict[str, Any]:
        out = super().to_dict()
        out.update({"views": list(self.views), "model_used": dict(self.model_used),
                    "corrections": {v: {"parameters_px": c.parameters, "parameter_std_px": c.parameter_std}
                                    for v, c in self.corrections.items()},
                    "reprojection_px": self.reprojection, "datum_drift_m": float(self.datum_drift_m),
                    "datum_drift_enu_m": [float(t) for t in self.datum_drift_enu_m],
                    "reduced_size": int(self.reduced_size), "converged": bool(self.converged)})
        return out


def reprojection(res: np.ndarray, rays: Rays, layout: ViewLayout, used: np.ndarray) -> Dict[str, Any]:
    """``{'per_view': {view: rms}, 'per_pair': {'a|b': rms}, 'all': rms}`` of residuals ``res`` (n_rays, 2) over the
    rays ``used``: RMS over both axes' components, ``sqrt(mean(ds^2, dl^2))`` px (METHODS §6); a pair's over the
    rays in ``a`` and ``b`` of the points both see."""
    m = len(layout.views)
    sq = np.where(used, np.sum(res * res, axis=1), 0.0)
    seen = np.zeros((rays.n_points, m))
    sqp = np.zeros((rays.n_points, m))
    seen[rays.point[used], rays.view[used]] = 1.0
    sqp[rays.point[used], rays.view[used]] = sq[used]
    n_view, s_view = seen.sum(axis=0), sqp.sum(axis=0)
    count = seen.T @ seen                                         # points seen by both views
    pair_sq = seen.T @ sqp + sqp.T @ seen                         # [a, b]: both rays' squares of those points
    per_view = {v: (float(np.sqrt(s_view[j] / (2.0 * n_view[j]))) if n_view[j] else None)
                for j, v in enumerate(layout.views)}
    per_pair = {f"{layout.views[a]}|{layout.views[b]}": float(np.sqrt(pair_sq[a, b] / (4.0 * count[a, b])))
                for a in range(m) for b in range(a + 1, m) if count[a, b] > 0}
    n = int(np.count_nonzero(used))
    return {"per_view": per_view, "per_pair": per_pair, "all": float(np.sqrt(sq.sum() / (2.0 * n))) if n else None}


def view_correction(layout: ViewLayout, view: str, x: np.ndarray, cov: np.ndarray, sigma0: float,
                    table: pd.DataFrame, rows: Optional[np.ndarray] = None) -> CompensationResult:
    """The view's correction as the one correction class (coefficients, covariance per axis, its rows: ``rows``
    (positions in ``table``) when known, else the table's rows of the view)."""
    sl_s, sl_l = layout.slices(view)
    res = CompensationResult.from_coefficients(layout.models_used[view], layout.frame(view), x[sl_s], x[sl_l])
    res.cov_sample, res.cov_line = cov[sl_s, sl_s].copy(), cov[sl_l, sl_l].copy()
    res.sigma0_px = (float(sigma0), float(sigma0))
    sub = table[table["image_id"] == view] if rows is None else table.iloc[rows]
    res.gcps = sub.rename(columns={"point_id": "id"}).reset_index(drop=True)
    return res


def datum_drift(before: np.ndarray, after: np.ndarray, ties: np.ndarray) -> Tuple[float, Tuple[float, float, float]]:
    """Length (m) of the mean move of the ties' ground from ``before`` to ``after`` (and its east, north, up)."""
    b, a = before[ties], after[ties]
    ok = np.all(np.isfinite(b) & np.isfinite(a), axis=1)
    if not ok.any():
        return float("nan"), (float("nan"),) * 3
    mx, my = metres_per_degree(b[ok, 1], b[ok, 2])
    d = np.stack([(a[ok, 0] - b[ok, 0]) * mx, (a[ok, 1] - b[ok, 1]) * my, a[ok, 2] - b[ok, 2]], axis=1).mean(axis=0)
    return float(np.linalg.norm(d)), tuple(float(t) for t in d)


def corrected_models(est: BundleEstimate, models: Mapping[str, Any], sizes=None, **fit_kw) -> Dict[str, Any]:
    """``view -> RPCModel`` with the view's correction applied (METHODS §4.2): folded exactly (translation,
    shift-drift) or refitted (affine) over the image (``sizes``, default the adjustment's) and the RPC's heights."""
    out = {}
    for v in est.views:
        size = (sizes or {}).get(v) or est.sizes.get(v)
        out[v] = apply_compensation(models[v], est.corrections[v], image_size=size, **fit_kw).rpc
    return out
