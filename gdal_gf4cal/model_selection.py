"""``--model auto``: choose the compensation model by leave-one-out error with a parsimony rule (METHODS §4, §6).

Every candidate (translation, shift-drift, affine, poly2: nested models, fewest parameters first) is fitted with
:func:`~gdal_gf4cal.compensation.fit_compensation` (``leave_one_out=True``). Each is scored by the RMS of the
leave-one-out residuals (radial, px) of the control points none of the candidates flags as a blunder (the same points
for all), and by the RMS of the check points when there are any. The simplest model is kept unless a model with more
parameters lowers the leave-one-out RMS by more than ``min_improvement`` (default 20 %) AND a nested F-test of the
residual sums of squares says the extra parameters are significant (``alpha``, default 0.01). A candidate needs at
least two redundant control points per axis (``n_control >= n_params + 2``) to be scored. The result says which and
why, with every candidate's numbers.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Sequence

import numpy as np

from .compensation import fit_compensation
from .errors import GCPError

#: Candidates of ``--model auto``, in order of increasing number of parameters (nested).
AUTO_CANDIDATES = ("translation", "shift-drift", "affine", "poly2")


@dataclass
class ModelSelection:
    """The outcome of :func:`select_model`: ``chosen`` model name, the one-line ``reason``, per-candidate numbers
    (``candidates``: name -> dict), and the fitted :class:`~gdal_gf4cal.compensation.CompensationResult` s."""

    chosen: str
    reason: str
    candidates: Dict[str, Dict[str, Any]]
    results: Dict[str, Any] = field(default_factory=dict, repr=False)
    rule: str = ""

    def to_dict(self) -> Dict[str, Any]:
        """The report's ``model_selection`` section (px)."""
        return {"chosen": self.chosen, "reason": self.reason, "rule": self.rule, "candidates": self.candidates}


def _radial_rms(ds, dl) -> Optional[float]:
    ds, dl = np.asarray(ds, float), np.asarray(dl, float)
    ok = np.isfinite(ds) & np.isfinite(dl)
    if not np.any(ok):
        return None
    return float(np.sqrt(np.mean(ds[ok] ** 2 + dl[ok] ** 2)))


def select_model(rpc, gcps, *, candidates: Sequence[str] = AUTO_CANDIDATES, dem=None, robust: bool = True,
                 outlier_threshold: float = 4.0, min_improvement: float = 0.2, alpha: float = 0.01,
                 **fit_options) -> ModelSelection:
    """Choose among ``candidates`` by leave-one-out RMS with a parsimony rule (module docstring; METHODS §4, §6).

    Parameters
    ----------
    rpc, gcps, dem, robust, outlier_threshold : as for :func:`~gdal_gf4cal.compensation.fit_compensation`
    candidates : model names, fewest parameters first (nested)
    min_improvement : relative drop of the leave-one-out RMS a model with more parameters must bring (0.2 = 20 %)
    alpha : significance level of the nested F-test on the control residuals

    Returns
    -------
    ModelSelection
    """
    from scipy import stats          # ~1 s to import: only when first needed (CLI, QGIS start-up)
    results, table = _fit_candidates(rpc, gcps, candidates, dict(fit_options, dem=dem, robust=robust,
                                                                  outlier_threshold=outlier_threshold))
    n_ctrl = _score(results, table)
    scored = [n for n in candidates if table.get(n, {}).get("scored")]
    if not scored:
        simplest = next(iter(results))
        return ModelSelection(simplest, f"{simplest}: too few control points to compare models by leave-one-out "
                              "error; add GCPs to let auto choose", table, results, _rule(min_improvement, alpha))
    chosen = scored[0]
    reason = f"{chosen}: the simplest model (leave-one-out RMS {table[chosen]['loo_rms_px']:.3f} px)"
    for name in scored[1:]:
        cur, new = table[chosen], table[name]
        dof_extra = 2 * (new["params_per_axis"] - cur["params_per_axis"])
        dof_res = 2 * (n_ctrl - new["params_per_axis"])
        if dof_extra <= 0 or dof_res <= 0 or new["ssr_px2"] <= 0:
            continue
        f = ((cur["ssr_px2"] - new["ssr_px2"]) / dof_extra) / (new["ssr_px2"] / dof_res)
        p = float(stats.f.sf(f, dof_extra, dof_res))
        gain = 1.0 - new["loo_rms_px"] / cur["loo_rms_px"] if cur["loo_rms_px"] else 0.0
        new.update(f_test_vs=chosen, f_value=float(f), p_value=p, loo_improvement=float(gain))
        if gain > min_improvement and p < alpha:
            reason = (f"{name}: leave-one-out RMS {new['loo_rms_px']:.3f} px, {100 * gain:.0f} % below {chosen}'s "
                      f"{cur['loo_rms_px']:.3f} px, and its extra parameters are significant (F-test p = {p:.2g})")
            chosen = name
        elif chosen == scored[0] and name == scored[1]:
            change = f"lowers it by {100 * gain:.0f} %" if gain > 0 else f"raises it by {-100 * gain:.0f} %"
            reason = (f"{chosen}: leave-one-out RMS {cur['loo_rms_px']:.3f} px; {name} {change} "
                      f"({new['loo_rms_px']:.3f} px, F-test p = {p:.2g}), not the > {100 * min_improvement:.0f} % "
                      f"with p < {alpha:g} that would justify more parameters")
    table = {n: table[n] for n in candidates if n in table}
    return ModelSelection(chosen, reason, table, results, _rule(min_improvement, alpha))


def _fit_candidates(rpc, gcps, candidates, options):
    """``(results, table)``: each candidate fitted with leave-one-out residuals; those that cannot be fitted (too
    few GCPs, a degenerate layout) get a ``why_not`` row."""
    results: Dict[str, Any] = {}
    table: Dict[str, Dict[str, Any]] = {}
    for name in candidates:
        try:
            results[name] = fit_compensation(rpc, gcps, name, leave_one_out=True, **options)
        except (GCPError, ArithmeticError, ValueError) as exc:
            table[name] = {"scored": False, "why_not": str(exc).splitlines()[0]}
    if not results:
        raise GCPError("no compensation model can be fitted to these GCPs; add control points (translation needs 1)")
    return results, table


def _score(results, table) -> int:
    """Each fitted candidate's row of ``table`` on the control points no candidate flags (the same for all);
    returns their number."""
    first = next(iter(results.values())).gcps
    inlier = (first["role"] == "control").to_numpy()
    for res in results.values():
        inlier &= ~res.gcps["outlier"].to_numpy(bool)
    n_ctrl = int(inlier.sum())
    check = (first["role"] == "check").to_numpy()
    for name, res in results.items():
        tab = res.gcps
        k = int(res.model.n_params) // 2 if res.model.n_params > 1 else 1      # parameters per axis
        row: Dict[str, Any] = {"n_params": int(res.model.n_params), "n_control": n_ctrl}
        if n_ctrl < k + 2:
            row.update(scored=False, why_not=f"needs at least {k + 2} control points, has {n_ctrl}")
            table[name] = row
            continue
        ss = tab["res_sample_after"].to_numpy(float)[inlier]
        sl = tab["res_line_after"].to_numpy(float)[inlier]
        row.update(scored=True, params_per_axis=k,
                   loo_rms_px=_radial_rms(tab["res_sample_loo"].to_numpy(float)[inlier],
                                          tab["res_line_loo"].to_numpy(float)[inlier]),
                   control_rms_px=_radial_rms(ss, sl), ssr_px2=float(np.sum(ss ** 2 + sl ** 2)))
        if np.any(check):
            row["check_rms_px"] = _radial_rms(tab["res_sample_after"].to_numpy(float)[check],
                                              tab["res_line_after"].to_numpy(float)[check])
        table[name] = row
    return n_ctrl


def _rule(min_improvement: float, alpha: float) -> str:
    return (f"simplest model unless one with more parameters lowers the leave-one-out RMS by more than "
            f"{100 * min_improvement:.0f} % and passes a nested F-test at p < {alpha:g}")
