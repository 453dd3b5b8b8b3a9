"""Multi-CCD / multi-band block calibration in RPC space (METHODS §8, seed 003, Jilin1-KF01A wide-field camera).

Model (METHODS §8, one RPC per CCD image and band; image ``i`` of CCD ``k``, band ``b``; GDAL pixel convention)::

    s_meas = s_RPC_i(X) + E_s + I_s(u)        E_s = (e0 + e3 t - kappa Y_i) / r_i
    l_meas = l_RPC_i(X) + E_l + I_l(u)        E_l = (e1 + e4 t + kappa X_i(u)) / r_i
    I_s = sum_j<=3 a_ij u^j,  I_l = sum_j<=3 b_ij u^j,  u = (s_meas - W_i/2) / (W_i/2),  t = r_i (l_meas - H_i/2) / T

* the **exterior** ``e0, e1`` (roll, pitch offsets), ``e3, e4`` (their drifts), ``kappa`` (yaw, in mrad) is shared
  by every CCD and band of the group; ``e*`` are in pixels of the reference band;
* the **interior** (a cubic in the detector position ``u`` per axis) belongs to each image (CCD and band);
* ``r_i`` is the image's pixel size over the reference band's (0.25 for 0.75 m pan against 3 m MS), ``X_i(u)``
  the detector's cross-track focal-plane position and ``Y_i`` its row's along-track offset, in px of the reference
  band, ``T`` half the height of the reference CCD image (so ``t`` is in the same time units for every image);
* the **datum**: the reference CCD's ``a0, b0, b1`` duplicate ``e0, e1, kappa`` and are fixed at 0 (a frozen
  block ``datum:<image>``);
* every **tie point** has unknown ``(lon, lat)`` with ``h`` from the DEM (rays of adjacent CCDs are nearly parallel:
  no height from intersection), eliminated by Schur complement
  (:func:`~gdal_gf4cal.estimation.solve_with_points`, sparse): the reduced system is ``5 + 8 n_images - 3``
  unknowns whatever the number of tie points; GCPs (known ground) add to it directly.

The **layout** comes from what a user has (:func:`derive_layout`): the reference-band CCD images in their order
across track, which image is a band of which CCD (``bands_of``), and the RPCs: ``r_i`` from the RPC Jacobians,
``X_i`` by chaining each CCD's centre into its neighbour's RPC. ``Y_i`` is set to 0: a constant per image, it is
absorbed by the free constant terms of every image but the reference CCD, where it only redefines ``e0``. Adjacent
CCDs must overlap (checked on their RPCs).

**Solvers**: ``"simultaneous"`` (default): Gauss-Newton on exterior + interiors + tie points at once;
``"alternating"`` (the paper's scheme): exterior with interiors fixed, then interiors with the exterior fixed
(frozen columns), repeated until stable. **Band-to-band**: the reference band (all images not in ``bands_of``) is
adjusted absolutely (GCPs + ties); then the other bands' interiors alone, with the reference exterior and interiors
frozen, from their tie points and their own control GCPs if any. **Robust weights**: each stage runs on the
core's one robust driver (:func:`~gdal_gf4cal.estimation.robust_fit`, one Gauss-Newton step per fit) with its radial
Huber weights on residuals normalised by their redundancy: a-priori weights, then down-weighting only, then
rejection (``z > 5``), until the rejected set is stable (:class:`~gdal_gf4cal.block.stage.StageNorm`).

Package layout: :mod:`.layout` (the group's layout from the RPCs), :mod:`.model` (parameters, the correction of one
image, the corrected sensor model), :mod:`.coverage` (terms the observations support), :mod:`.stage` (one stage's
Gauss-Newton with tie points eliminated, robust weights), :mod:`.adjust` (:func:`adjust_block`), :mod:`.estimate`
(:class:`BlockEstimate`, :func:`prediction_std`), :mod:`.seams` (seam offsets), :mod:`.calibration` (the
``calibration.json`` file).
"""
from __future__ import annotations

from .adjust import adjust_block
from .calibration import CALIBRATION_MODEL, calibrated_model, calibration_dict, read_calibration, write_calibration
from .coverage import MAX_EXTRAPOLATION_VARIANCE, supported_degree
from .estimate import BlockEstimate, corrected_model, prediction_std
from .layout import (MAX_VIEW_ANGLE_DEG, BlockError, BlockLayout, ImageLayout, SeparateViewsError, check_one_pass,
                     derive_layout, layout_from_calibration, pair_bands, view_angle)
from .model import (DATUM_TERMS, EXTERIOR_NAMES, INTERIOR_NAMES, BlockCorrectedRPC, ImageCorrection, local_design,
                    parameter_blocks)
from .seams import seam_offsets

__all__ = ["EXTERIOR_NAMES", "DATUM_TERMS", "ImageLayout", "BlockLayout", "BlockEstimate", "BlockCorrectedRPC",
           "derive_layout", "adjust_block", "corrected_model", "seam_offsets", "calibration_dict",
           "write_calibration", "read_calibration", "calibrated_model", "prediction_std", "layout_from_calibration",
           "BlockError", "supported_degree", "INTERIOR_NAMES", "CALIBRATION_MODEL",
           "MAX_EXTRAPOLATION_VARIANCE", "ImageCorrection", "local_design", "parameter_blocks", "SeparateViewsError",
           "MAX_VIEW_ANGLE_DEG", "check_one_pass", "pair_bands", "view_angle"]
