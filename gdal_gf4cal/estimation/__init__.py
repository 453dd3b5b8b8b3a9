"""One estimation core (METHODS §4, §5, §7): weighted least squares with named, freezable parameter blocks,
Schur elimination of point blocks, one high-breakdown robust estimator and one :class:`Estimate` result.

Every least-squares user of the engine goes through :func:`weighted_lsq` / :func:`solve_with_points` (a-posteriori
covariances through :func:`sigma0_and_cov`) and flags blunders with the one robust driver :func:`robust_fit`
(high-breakdown start, then a pluggable norm: :class:`Snooping`, :class:`RadialHuber`, :class:`Huber`,
:class:`Tukey`; a problem is a :class:`LinearProblem` or anything with its small protocol, see ``driver.py``).
"""
from __future__ import annotations

from .result import Estimate
from .lsq import Block, normal_solve, weighted_lsq
from .indexed import IndexedJacobian
from .schur import solve_with_points
from .lsq import sigma0_and_cov, unit_weight_sigma
from .robust import critical_value, high_breakdown_start, min_subset_points, radial_huber_weights, readmissible, \
    subset_count, tukey_weights
from .driver import (ESTIMATE_LEVELS, Huber, IRLSSolution, LinearProblem, RadialHuber, RobustState, Snooping, Tukey,
                     irls, robust_fit, robust_lsq)

__all__ = ["Estimate", "Block", "weighted_lsq", "solve_with_points", "critical_value", "high_breakdown_start",
           "robust_lsq", "normal_solve", "irls", "IRLSSolution", "radial_huber_weights", "readmissible", "tukey_weights",
           "min_subset_points", "subset_count", "sigma0_and_cov", "unit_weight_sigma", "robust_fit", "LinearProblem", "Snooping",
           "RadialHuber", "Huber", "Tukey", "RobustState", "ESTIMATE_LEVELS", "IndexedJacobian"]
