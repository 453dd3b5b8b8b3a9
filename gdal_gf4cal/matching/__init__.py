"""Automatic GCP collection: sub-pixel matching of a raw image against a reference orthophoto + DEM (issue 7).

- :mod:`.correlate` batched phase correlation with sub-pixel peak and quality measures;
- :mod:`.resample` reference orthophoto -> raw image geometry through RPC + DEM (windowed reads);
- :mod:`.filters` outlier rejection against a low-order image-space model (seeded RANSAC + MAD);
- :mod:`.collect` :func:`collect_gcps` (tiles, parallel executor) and its picklable tile function;
- :mod:`.raw` raw-to-raw matching through two sensor models + DEM: :func:`match_raw`, :func:`match_ties` (CCD
  overlaps, band to band, METHODS §8), :func:`pan_ms_cells` (pan-MS per-cell misregistration, METHODS §9).
"""
from __future__ import annotations

from .collect import STATUS, TileSpec, assemble_gcps, collect_gcps, match_tile, plan_tiles, run_tiles
from .correlate import CorrelationResult, phase_correlate, texture_strength
from .filters import OutlierResult, reject_outliers
from .raw import cells_from_matches, match_raw, match_ties, overlap_region, pan_ms_cells
from .resample import RawReference, ReferenceImage, reference_on_grids

__all__ = ["STATUS", "TileSpec", "assemble_gcps", "collect_gcps", "match_tile", "plan_tiles", "CorrelationResult",
           "phase_correlate", "texture_strength", "OutlierResult", "reject_outliers", "ReferenceImage",
           "reference_on_grids", "RawReference", "run_tiles", "match_raw", "match_ties", "pan_ms_cells",
           "cells_from_matches", "overlap_region"]
