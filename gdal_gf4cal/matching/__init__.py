"""Automatic GCP collection: sub-pixel matching of a raw image against a reference orthophoto + DEM (issue 7).

- :mod:`.correlate` batched phase correlation with sub-pixel peak and quality measures;
- :mod:`.resample` reference orthophoto -> raw image geometry through RPC + DEM (windowed reads);
- :mod:`.filters` outlier rejection against a low-order image-space model (seeded RANSAC + MAD);
- :mod:`.collect` :func:`collect_gcps` (tiles, parallel executor) and its picklable tile function.
"""
from __future__ import annotations

from .collect import STATUS, TileSpec, assemble_gcps, collect_gcps, match_tile, plan_tiles
from .correlate import CorrelationResult, phase_correlate, texture_strength
from .filters import OutlierResult, reject_outliers
from .resample import ReferenceImage, reference_on_grids

__all__ = ["STATUS", "TileSpec", "assemble_gcps", "collect_gcps", "match_tile", "plan_tiles", "CorrelationResult",
           "phase_correlate", "texture_strength", "OutlierResult", "reject_outliers", "ReferenceImage",
           "reference_on_grids"]
