"""Image-space bias compensation of an RPC and detector-position polynomials (METHODS §4).

The observation model of every GCP (METHODS §4) is::

    line_meas   = line_rpc(lon, lat, h)   + dl(s', l')
    sample_meas = sample_rpc(lon, lat, h) + ds(s', l')

where ``(s', l') = rpc.project(lon, lat, h)`` are the RPC's own (GDAL-convention) image coordinates (see
:mod:`.model` for the normalisation and the exact fold into offsets and scales).

- :mod:`.model`: :class:`CompensationModel` (which terms), :class:`CompensationResult` (the correction),
  :class:`CompensatedRPC` and :func:`apply_compensation` (exact fold or refit);
- :mod:`.solve`: :func:`fit_compensation`, on the one robust driver (:func:`gdal_gf4cal.estimation.robust_fit`);
- :mod:`.outputs`: accuracy per role (:func:`gdal_gf4cal.stats.accuracy_by_role`), suspected blunders, warnings.
"""
from __future__ import annotations

from .model import (MODEL_NAMES, AppliedCompensation, CompensatedRPC, CompensationModel, CompensationResult,
                    apply_compensation)
from .outputs import (accuracy_by_role, check_point_warnings, describe_suspects, ground_jacobian, ground_offsets_m,
                      report_axis_stats, suspected_blunders)
from .solve import CompensationProblem, fit_compensation

__all__ = [
    "MODEL_NAMES", "CompensationModel", "CompensationResult", "CompensatedRPC", "AppliedCompensation",
    "fit_compensation", "apply_compensation", "ground_offsets_m", "ground_jacobian", "accuracy_by_role",
    "suspected_blunders", "describe_suspects", "check_point_warnings", "CompensationProblem", "report_axis_stats",
]
