"""The result of a block adjustment (:class:`BlockEstimate`, an :class:`~gdal_gf4cal.estimation.Estimate`), the
corrected model of one of its images and the propagated precision of its corrections."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from ..estimation import Estimate
from .layout import BlockLayout
from .model import BlockCorrectedRPC, ImageCorrection, local_design, parameter_blocks
from .stage import propagate_frozen

@dataclass
class BlockEstimate(Estimate):
    """The core's :class:`~gdal_gf4cal.estimation.Estimate` of a block adjustment (per observation row: 2 residuals,
    sample then line, in :attr:`residuals`), plus the block's own results.

    ``table``: the observation table with ``pred_sample_before/after``, ``res_sample_before/after`` (and line),
    ``outlier`` flags, tie-point ground coordinates estimated (``lon, lat, h``); ``layout``; ``stages``: per stage
    (``reference`` band, ``bands``) the images, solver, iterations (normal-equation solves), convergence and the
    size of the reduced system; ``comparison``: the other solver's stages when asked (:func:`adjust_block`).
    """

    table: Any = None
    layout: Optional[BlockLayout] = None
    stages: List[Dict[str, Any]] = field(default_factory=list)
    comparison: Optional[Dict[str, Any]] = None
    cov_pending: List[Any] = field(default_factory=list, repr=False)

    def complete_covariance(self) -> np.ndarray:
        """Add to :attr:`cov` what the earlier stages' errors do to the band stage's parameters
        (:func:`propagate_frozen`; computed once, on demand: :func:`prediction_std` calls it). Returns ``cov``."""
        while self.cov_pending:
            propagate_frozen(*self.cov_pending.pop(0), self.cov)
        return self.cov

    def correction(self, image_id: str) -> ImageCorrection:
        idx = parameter_blocks(self.layout)[1][image_id]
        v = self.x[idx]
        return ImageCorrection(self.layout.images[image_id], self.layout.time_scale, v[:5].copy(), v[5:].copy())


def corrected_model(estimate: BlockEstimate, image_id: str, rpc) -> BlockCorrectedRPC:
    """The corrected sensor model of one image of the block."""
    return BlockCorrectedRPC(rpc, estimate.correction(image_id))




def prediction_std(estimate: BlockEstimate, image_id: str, sample, line) -> Tuple[np.ndarray, np.ndarray]:
    """Propagated 1-sigma of the correction of ``image_id`` at ``(sample, line)`` (px, per axis) from the estimate's
    covariance: the precision floor the GCP and matching noise allow (METHODS §6). A band image's interior carries
    the reference band's errors it absorbed (its covariance with the frozen exterior and reference interiors,
    :func:`propagate_frozen`), so its floor is the reference image's plus the band-to-band matching noise."""
    estimate.complete_covariance()
    idx = parameter_blocks(estimate.layout)[1][image_id]
    d = local_design(estimate.layout.images[image_id], estimate.layout.time_scale, sample, line)
    c = estimate.cov[np.ix_(idx, idx)]
    var = np.einsum("nkc,cd,nkd->nk", d, c, d)
    return np.sqrt(np.maximum(var[:, 0], 0.0)), np.sqrt(np.maximum(var[:, 1], 0.0))
