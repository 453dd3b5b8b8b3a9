"""One estimation core (METHODS §4, §5, §7): weighted least squares with named, freezable parameter blocks,
Schur elimination of point blocks, one high-breakdown robust estimator and one :class:`Estimate` result.

Every least-squares user of the engine (compensation, look-angle calibration, intersection; block calibration and
pan-MS registration next) goes through :func:`weighted_lsq` / :func:`solve_with_points` and flags blunders with
:func:`high_breakdown_start` + data snooping (:func:`critical_value`).
"""
from __future__ import annotations

from .result import Estimate
from .lsq import Block, normal_solve, weighted_lsq
from .schur import solve_with_points
from .robust import (IRLSSolution, critical_value, high_breakdown_start, irls, min_subset_points, radial_huber_weights,
                     readmissible, robust_lsq)

__all__ = ["Estimate", "Block", "weighted_lsq", "solve_with_points", "critical_value", "high_breakdown_start",
           "robust_lsq", "normal_solve", "irls", "IRLSSolution", "radial_huber_weights", "readmissible",
           "min_subset_points"]
from .indexed import IndexedJacobian  # noqa: E402  (bundle adjustment: rows touching a few globals)
__all__ += ["IndexedJacobian"]
