"""The one result of an estimation (METHODS §4, §6)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np


#: The one outlier vocabulary of the engine: why a point was flagged by an estimate (``Estimate.outlier_level``;
#: ``''`` when kept): left out by the high-breakdown start and never re-admitted (``'start'``), by data snooping
#: (``'snooping'``), or rejected by an IRLS norm (``'reject'``). The observation table's filter levels
#: (:data:`gdal_gf4cal.observations.OUTLIER_LEVELS`) are the matcher's ``'match'`` followed by these.
ESTIMATE_LEVELS = ("start", "snooping", "reject")


@dataclass
class Estimate:
    """Parameters, their covariance and the per-observation diagnostics of one (robust) least-squares estimate.

    Attributes
    ----------
    names : list of str
        Parameter names, in the order of :attr:`x`.
    blocks : dict of str -> slice
        Named parameter blocks (slices into :attr:`x`).
    frozen : tuple of str
        Blocks held at their given values (their covariance rows/columns are zero).
    x : ndarray (p,)
        Parameter values (frozen blocks at their given values).
    cov : ndarray (p, p)
        Covariance ``sigma0^2 N^-1`` (a-posteriori) of the free parameters, zero for frozen ones.
    sigma0 : float
        A-posteriori standard deviation of unit weight (1.0 when there is no redundancy).
    dof : int
        Degrees of freedom: observations with non-zero weight minus free parameters.
    redundancy : ndarray (n_obs,)
        Redundancy numbers ``r_i = 1 - h_ii`` (0 for observations not in the estimate).
    residuals : ndarray (n_obs,)
        ``observed - A x`` of every observation (also those left out).
    normalised : ndarray (n_obs,)
        Residual over its standard deviation (Baarda's w; NaN where undefined).
    weights : ndarray (n_obs,)
        Weights used in the final estimate (0: left out).
    outlier : ndarray of bool (n_points,) or (n_obs,)
        Blunder flags (per point when the estimate was made per point).
    outlier_level : ndarray of str
        Why a point was flagged: ``''`` (not flagged), ``'start'`` (high-breakdown start, never re-admitted) or
        ``'snooping'`` (data snooping, Student-t threshold) or ``'reject'`` (an IRLS norm's rejection).
    condition_number : float
        Condition number of the column-scaled design of the free parameters.
    iterations : int
    notes, warnings : list of str
    axis_dof : tuple of int, optional
        Degrees of freedom of the sigma each axis' normalised residuals were scaled with, when the axes are
        estimated separately (e.g. compensation's sample and line); :class:`~gdal_gf4cal.estimation.Snooping`
        then tests each axis with its own critical value.
    point_weights : ndarray (n_points,), optional
        Robust factor per point (0: out of the estimate), set by :func:`~gdal_gf4cal.estimation.robust_fit`.
    normal : ndarray (p, p), optional
        Normal matrix ``A^T W A`` of the final solve (fast solver of
        :class:`~gdal_gf4cal.estimation.LinearProblem`).
    norm_info : dict
        What the robust driver found: ``start_sigma``, an IRLS norm's ``scale`` and ``z`` (normalised residual
        per point), ``degenerate``.
    """

    names: List[str]
    x: np.ndarray
    cov: np.ndarray
    sigma0: float
    dof: int
    redundancy: np.ndarray
    residuals: np.ndarray
    normalised: np.ndarray
    weights: np.ndarray
    blocks: Dict[str, slice] = field(default_factory=dict)
    frozen: Tuple[str, ...] = ()
    outlier: Optional[np.ndarray] = None
    outlier_level: Optional[np.ndarray] = None
    condition_number: float = 1.0
    iterations: int = 0
    notes: List[str] = field(default_factory=list)
    warnings: List[str] = field(default_factory=list)
    axis_dof: Optional[Tuple[int, ...]] = None
    point_weights: Optional[np.ndarray] = None
    normal: Optional[np.ndarray] = None
    norm_info: Dict[str, Any] = field(default_factory=dict)

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the parameters (0 for frozen ones)."""
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    @property
    def parameters(self) -> Dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, self.x)}

    def block(self, name: str) -> np.ndarray:
        """Values of one named block."""
        return self.x[self.blocks[name]]

    def block_cov(self, name: str) -> np.ndarray:
        sl = self.blocks[name]
        return self.cov[sl, sl]

    def to_dict(self) -> Dict[str, Any]:
        """JSON-ready summary (no per-observation arrays)."""
        out: Dict[str, Any] = {"parameters": self.parameters,
                               "parameter_std": {n: float(s) for n, s in zip(self.names, self.std)},
                               "sigma0": float(self.sigma0), "dof": int(self.dof),
                               "condition_number": float(self.condition_number), "iterations": int(self.iterations),
                               "frozen": list(self.frozen), "notes": list(self.notes),
                               "warnings": list(self.warnings)}
        if self.outlier is not None:
            out["n_outliers"] = int(np.count_nonzero(self.outlier))
        return out


def names_and_blocks(blocks: Sequence[Any], n_params: int) -> Tuple[List[str], Dict[str, slice]]:
    """Parameter names and block slices from a sequence of :class:`~gdal_gf4cal.estimation.Block`."""
    if not blocks:
        return [f"x{i}" for i in range(n_params)], {"x": slice(0, n_params)}
    names: List[str] = []
    sl: Dict[str, slice] = {}
    for b in blocks:
        sl[b.name] = slice(len(names), len(names) + len(b.names))
        names.extend(b.names)
    return names, sl
