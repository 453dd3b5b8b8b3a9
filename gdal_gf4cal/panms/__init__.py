"""Pan-to-multispectral registration compensation (METHODS §9, seed 004, Gaofen-7).

Estimate, then apply:

* :func:`estimate` solves METHODS §9's model ``delta(s, l) = delta_L + delta_I(s) + delta_J(s, l)`` per axis from
  the dense cell observations (``gdal_gf4cal.matching.pan_ms_cells``: MS cell centres ``sample, line`` and
  ``nabla = p' - p''`` as ``d_sample, d_line``), **stepwise** (eqs. 14-16): the linear term (6 parameters) on all
  usable cells, the piecewise quartic per sub-CCD in the MS column (5 x 2 per piece, 30 for 3 sub-CCDs) on what
  remains, the trigonometric jitter series in the line scaled by ``(1 + B s)`` with frequencies picked from the
  residual spectrum (a component is accepted only when significant). Every step is a robust estimate of the
  estimation core (high-breakdown start + data snooping) with the earlier terms' datum frozen. **Reuse mode**
  (eq. 17): the piecewise term of another scene of the same camera is frozen and only the linear term is solved
  from a few sparse cells.
* :class:`PanMSModel` is the plain result: ``predict(sample, line) -> (d_sample, d_line)`` (MS pixels, GDAL
  convention), per-step statistics ``steps``, JSON round trip.
* :func:`write_correction` writes ``correction.tif`` (delta at every MS pixel centre, MS grid, tile by tile),
  :func:`resample_ms_on_pan` writes the MS bands resampled onto the pan's raw grid at MS resolution (what
  ``gdal_pansharpen.py`` needs: same extent as the pan, no halos), :func:`approximate_rpc` refits the MS RPC
  with the model (a smooth approximation: an RPC cannot carry the sub-CCD jumps; its error is reported).

``delta`` is where the MS image shows a ground point minus where the pan, the DEM and the MS RPC predict it: the
MS image shows the ground point predicted at ``p''`` at ``p' = p'' + delta(p')``.
"""
from __future__ import annotations

from .apply import TILE_PX, approximate_rpc, edge_misregistration, resample_ms_on_pan, write_correction
from .breaks import (JUMP_FAP, JUMP_SMOOTH_ORDER, RAMP_SHARE, column_profile, default_breaks, detect_breaks,
                     merge_breaks, pan_edges_in_ms)
from .design import LINEAR_ORDER, linear_design
from .jitter import JITTER_FAP, MAX_JITTER_COMPONENTS, supported_sines
from .model import (AXES, GF7_LOOK_TIME_S, GF7_MS_IFOV_RAD, GF7_MS_LINE_TIME_S, ORDER, P_THRESHOLD_PX, PanMSError,
                    PanMSModel)
from .screen import SCREEN_FLOOR_PX, SCREEN_GROSS_PX, SCREEN_K, SCREEN_ROWS, screen_matches
from .solve import REUSE_MAX_FLOOR_RATIO, REUSE_MAX_OUTLIER_SHARE, REUSE_MAX_RMS_PX, estimate, step_residuals
from .spectrum import residual_spectrum, row_means, spectrum_peaks

__all__ = ["PanMSModel", "estimate", "default_breaks", "screen_matches", "detect_breaks", "column_profile",
           "pan_edges_in_ms", "merge_breaks", "write_correction", "resample_ms_on_pan", "approximate_rpc",
           "GF7_MS_LINE_TIME_S", "GF7_MS_IFOV_RAD", "GF7_LOOK_TIME_S", "PanMSError", "edge_misregistration",
           "step_residuals", "row_means", "residual_spectrum", "spectrum_peaks", "linear_design", "LINEAR_ORDER",
           "JUMP_FAP", "JUMP_SMOOTH_ORDER", "RAMP_SHARE", "JITTER_FAP", "MAX_JITTER_COMPONENTS", "AXES", "ORDER",
           "P_THRESHOLD_PX", "SCREEN_FLOOR_PX", "SCREEN_GROSS_PX", "SCREEN_K", "SCREEN_ROWS", "REUSE_MAX_FLOOR_RATIO",
           "REUSE_MAX_OUTLIER_SHARE", "REUSE_MAX_RMS_PX", "supported_sines", "TILE_PX"]
