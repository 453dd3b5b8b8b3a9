"""Plausibility of GCPs against an RPC and an image, and the layout strength of a correction in pixels (issue 11).

:func:`check_gcps_against` refuses GCPs that cannot belong to the image (METHODS §4, §6): measured points outside
the image, heights outside the RPC's height range (metres expected; feet named), ground points the RPC projects
far from where they were measured (lon/lat swapped is detected and named; otherwise the layer's CRS is suspected).
:func:`correction_precision` is the propagated 1-sigma uncertainty of an estimated correction over the whole image
(parameter covariance x measured noise, METHODS §4, §6), on a grid: what the GCP layout leaves unknown.
All vectorised; the workflows call them, the estimators stay pure.
"""
from __future__ import annotations

from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from .compensation import describe_suspects
from .errors import DegenerateGeometryError, GCPError

#: Measured points may lie this share of the image size outside it (edge GCPs, sloppy clicks).
OUTSIDE_MARGIN = 0.05
#: Without the image (a standalone RPC) its size is implied by the RPC's offsets and scales: a wider margin.
IMPLIED_SIZE_MARGIN = 0.25
#: Predicted vs measured is refused beyond max(PREDICTED_MARGIN_PX, PREDICTED_MARGIN_FRACTION x image diagonal).
PREDICTED_MARGIN_PX = 500.0
PREDICTED_MARGIN_FRACTION = 0.10
#: Heights may lie this far (m) outside the RPC's HEIGHT_OFF +/- HEIGHT_SCALE.
HEIGHT_MARGIN_M = 1000.0
#: Ground points farther than this (normalised units) from the RPC's ground offsets are outside its domain.
GROUND_DOMAIN = 3.0
#: Default refusal threshold of the propagated correction uncertainty (px); a warning above 1 px.
MAX_UNCERTAINTY_PX = 10.0
WARN_UNCERTAINTY_PX = 1.0
FEET = 0.3048


def _ids(gcps, mask, k: int = 3) -> str:
    ids = (gcps["id"].astype(str).to_numpy() if "id" in gcps.columns else np.arange(len(gcps)).astype(str))[mask]
    more = f" and {mask.sum() - k} more" if mask.sum() > k else ""
    return ", ".join(ids[:k]) + more


def _distance(rpc, lon, lat, h, s, l):
    """|measured - RPC(ground)| in px; inf outside the RPC's ground domain or where the projection fails."""
    with np.errstate(all="ignore"):
        nl = np.abs((lon - float(rpc.long_off)) / (abs(float(rpc.long_scale)) or 1.0))
        np_ = np.abs((lat - float(rpc.lat_off)) / (abs(float(rpc.lat_scale)) or 1.0))
        inside = (nl <= GROUND_DOMAIN) & (np_ <= GROUND_DOMAIN) & np.isfinite(h)
        ps, pl = (np.asarray(v, float) for v in rpc.project(np.where(inside, lon, float(rpc.long_off)),
                                                            np.where(inside, lat, float(rpc.lat_off)),
                                                            np.where(inside, h, float(rpc.height_off))))
        d = np.hypot(s - ps, l - pl)
    return np.where(inside & np.isfinite(d), d, np.inf)


def check_gcps_against(rpc, gcps, image_size: Optional[Tuple[int, int]] = None, *,
                       outside_margin: float = OUTSIDE_MARGIN, predicted_margin_px: Optional[float] = None,
                       height_margin_m: float = HEIGHT_MARGIN_M) -> Dict[str, Any]:
    """Refuse GCPs that cannot belong to the image of ``rpc`` (METHODS §4, §6; issue 11); GCPError naming why.

    ``gcps``: the GCP table (``lon, lat, h, sample, line``, GDAL convention). ``image_size`` (W, H): the image's
    (default: implied by the RPC's offsets and scales). Refused, in this order: measured points more than
    ``outside_margin`` x the size outside the image (25 % when the size is only implied by the RPC); heights outside the RPC's height range +/- ``height_margin_m``
    (named "feet" when /3.28 would fit); points whose RPC prediction lies more than ``predicted_margin_px``
    (default max(500 px, 10 % of the image diagonal)) from their measured position: "lon/lat swapped" when swapping
    brings them in, else "check the layer's CRS". A real bias of tens of px passes. Returns the margins used.
    """
    w, hgt = (float(x) for x in (image_size or rpc.image_size))
    implied = image_size is None                  # a standalone RPC: its size is a guess from offsets and scales
    if implied:
        outside_margin = max(outside_margin, IMPLIED_SIZE_MARGIN)
    n = len(gcps)
    if n == 0:
        return {}
    lon, lat, h, s, l = (np.asarray(gcps[c], float) for c in ("lon", "lat", "h", "sample", "line"))
    # 1. measured image points inside the image (+ margin)
    ms, ml = outside_margin * w, outside_margin * hgt
    out = ~((s >= -ms) & (s <= w + ms) & (l >= -ml) & (l <= hgt + ml))
    if out.any():
        i = int(np.flatnonzero(out)[0])
        what = "image implied by the RPC" if implied else "image"
        raise GCPError(f"{out.sum()} of {n} GCPs are measured outside the {w:.0f} x {hgt:.0f} px {what} (beyond "
                       f"{outside_margin:.0%} of its size; e.g. {_ids(gcps, out, 1)} at sample {s[i]:.1f}, line "
                       f"{l[i]:.1f}): they belong to another image or use other pixel units; remove or fix them")
    # 2. heights within the RPC's height range (+ margin)
    h0, h1 = rpc.height_range
    lo, hi = h0 - height_margin_m, h1 + height_margin_m
    bad = ~((h >= lo) & (h <= hi))
    if bad.any():
        feet = h * FEET
        in_feet = bool(np.all((feet[bad] >= lo) & (feet[bad] <= hi)))
        hint = ("they look like feet: give heights in metres (x 0.3048)" if in_feet else
                "give ellipsoidal heights in metres (or --dem) for points of this image")
        raise GCPError(f"{bad.sum()} of {n} GCP heights lie outside the RPC's height range {h0:.0f}..{h1:.0f} m "
                       f"+/- {height_margin_m:.0f} m (e.g. {_ids(gcps, bad, 1)}: {h[bad][0]:.6g} m): {hint}")
    # 3. predicted (RPC(ground)) vs measured
    margin = (max(PREDICTED_MARGIN_PX, PREDICTED_MARGIN_FRACTION * float(np.hypot(w, hgt)))
              if predicted_margin_px is None else float(predicted_margin_px))
    d = _distance(rpc, lon, lat, h, s, l)
    far = ~(d <= margin)
    if far.any():
        d_swap = _distance(rpc, lat, lon, h, s, l)
        if np.median(d_swap) <= margin and np.median(d_swap) < np.median(d):
            raise GCPError(f"the GCPs' lon/lat look swapped: as given the RPC projects {far.sum()} of {n} more than "
                           f"{margin:.0f} px from their measured position, swapped they agree (median "
                           f"{np.median(d_swap):.1f} px); swap the lon and lat columns")
        med = np.median(d)
        where = "outside the RPC's ground domain" if not np.isfinite(med) else f"median {med:.0f} px off"
        if far.sum() * 2 > n:
            raise GCPError(f"{far.sum()} of {n} GCPs project more than {margin:.0f} px from their measured position "
                           f"({where}): the ground coordinates do not belong to this image; check the layer's CRS "
                           "(or --gcp-crs), the lon/lat order and that the GCPs are for this image")
        raise GCPError(f"{far.sum()} of {n} GCPs ({_ids(gcps, far)}) project more than {margin:.0f} px from their "
                       "measured position: they cannot belong to this image; remove or fix them")
    return {"outside_margin": outside_margin, "predicted_margin_px": margin,
            "height_range_m": [lo, hi], "max_predicted_offset_px": float(np.max(d))}


def correction_precision(result, image_size: Tuple[int, int], *, grid: int = 21) -> Dict[str, float]:
    """Propagated 1-sigma uncertainty (px) of an estimated correction over the whole image (METHODS §4, §6).

    ``result``: a :class:`~gdal_gf4cal.compensation.CompensationResult` (covariance already scaled by the
    measured noise, ``correction_std``). Evaluated on a ``grid`` x ``grid`` lattice over ``image_size`` (W, H)
    including the corners; planar sigma = hypot(sample, line). Returns ``max``, ``rms``, ``max_sample``,
    ``max_line`` and where the maximum is (``at_sample``, ``at_line``).
    """
    w, h = (float(x) for x in image_size)
    ss, ll = np.meshgrid(np.linspace(0.0, w, grid), np.linspace(0.0, h, grid))
    sd_s, sd_l = (np.asarray(v, float) for v in result.correction_std(ss, ll))
    p = np.hypot(sd_s, sd_l)
    k = int(np.nanargmax(p)) if np.isfinite(p).any() else 0
    return {"max": float(np.nanmax(p)), "rms": float(np.sqrt(np.nanmean(p ** 2))),
            "max_sample": float(np.nanmax(sd_s)), "max_line": float(np.nanmax(sd_l)),
            "at_sample": float(ss.ravel()[k]), "at_line": float(ll.ravel()[k]), "grid": int(grid),
            "suspects": list(getattr(result, "suspects", []))}


def check_precision(precision: Dict[str, float], model_label: str, *,
                    max_uncertainty_px: float = MAX_UNCERTAINTY_PX) -> Sequence[str]:
    """Refuse a correction whose propagated uncertainty exceeds ``max_uncertainty_px`` (DegenerateGeometryError
    with a suggestion); returns the warnings (above 1 px). METHODS §4, §6."""
    if not max_uncertainty_px > 0:
        raise GCPError(f"max uncertainty {max_uncertainty_px} px makes no sense: give a positive number of pixels")
    mx, rms = precision["max"], precision["rms"]
    where = f"at sample {precision['at_sample']:.0f}, line {precision['at_line']:.0f}"
    if not mx <= max_uncertainty_px and precision.get("suspects"):
        # The check points fit worse after the correction: its sigma (hence the uncertainty) is inflated by
        # blunders, not by the layout.
        raise DegenerateGeometryError(
            f"the {model_label} correction is uncertain by up to {mx:.1f} px and the check points fit worse after it: "
            f"blunders are suspected among the GCPs, the worst: {describe_suspects(precision['suspects'])}; check or "
            "remove them, else use a simpler model (or raise --max-uncertainty)")
    if not mx <= max_uncertainty_px:
        raise DegenerateGeometryError(
            f"the GCP layout leaves the {model_label} correction uncertain by up to {mx:.1f} px (1 sigma, rms "
            f"{rms:.1f} px over the image, {where}) > {max_uncertainty_px:g} px: use a simpler model or GCPs spread "
            "over the whole image (or raise --max-uncertainty)")
    if mx > WARN_UNCERTAINTY_PX:
        return [f"the GCP layout leaves the correction uncertain by up to {mx:.2f} px (1 sigma, rms {rms:.2f} px "
                f"over the image, {where}): more spread GCPs or a simpler model would tighten it"]
    return []
