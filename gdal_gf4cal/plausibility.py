"""Plausibility of GCPs against an RPC and an image, and the layout strength of a correction in pixels (issue 11).

:func:`check_gcps_against` refuses GCPs that cannot belong to the image (METHODS §4, §6): measured points outside
the image beyond the RPC's own domain (points outside the image but inside it are used, with a warning: field GCPs
just outside a crop), heights outside the RPC's height range (metres expected; feet named) or, with a DEM, in feet
or on another vertical datum than the DEM's, ground points the RPC projects far from where they were measured
(lon/lat swapped is detected and named; otherwise the layer's CRS is suspected). Every refusal names the override
(``--no-plausibility-check``). :func:`check_measured_inside` alone judges image points (block-adjust's ties).
:func:`correction_precision` is the propagated 1-sigma uncertainty of an estimated correction over the whole image
(parameter covariance x measured noise, METHODS §4, §6), on a grid: what the GCP layout leaves unknown.
All vectorised; the workflows call them, the estimators stay pure.
"""
from __future__ import annotations

import warnings
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from .compensation import describe_suspects
from .errors import DegenerateGeometryError, GCPError

#: Measured points may lie this share of the image size outside it (edge GCPs, sloppy clicks).
OUTSIDE_MARGIN = 0.05
#: Farther out, measured points are used (with a warning naming them) while inside the RPC's own validity box
#: (normalised image and ground coordinates within RPC_DOMAIN) and within OUTSIDE_USE_MARGIN x the image size.
RPC_DOMAIN = 1.1
OUTSIDE_USE_MARGIN = 0.5
#: Tie measurements (block-adjust): a few stray ones beyond that (at most STRAY_FRACTION of an image's, within
#: STRAY_MARGIN x its size) are blunders for the robust adjustment to flag, with a warning; more are refused.
STRAY_FRACTION = 0.1
STRAY_MARGIN = 1.0
#: How refusals name their override; the QGIS provider words ``(--no-plausibility-check)`` as its parameter.
OVERRIDE_WORDS = "switch the plausibility check off (--no-plausibility-check)"
#: Heights against a DEM: at least this many compared points; feet when the median |h - DEM| exceeds
#: FEET_MIN_OFFSET_M and h x 0.3048 agrees FEET_AGREEMENT x better; another vertical datum when the median
#: offset is of a geoid's size (DATUM_MIN..MAX_OFFSET_M), DATUM_SAME_SIGN of the points on its side and their
#: spread (median absolute deviation) within DATUM_MAX_SPREAD x the offset.
MIN_HEIGHT_POINTS = 3
FEET_MIN_OFFSET_M = 30.0
FEET_AGREEMENT = 0.25
DATUM_MIN_OFFSET_M = 10.0
DATUM_MAX_OFFSET_M = 120.0
DATUM_SAME_SIGN = 0.8
DATUM_MAX_SPREAD = 0.5
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


def _id_array(gcps) -> np.ndarray:
    return (gcps["id"].astype(str).to_numpy() if "id" in gcps.columns else np.arange(len(gcps)).astype(str))


def _ids(gcps, mask, k: int = 3) -> str:
    ids = _id_array(gcps)[mask]
    more = f" and {mask.sum() - k} more" if mask.sum() > k else ""
    return ", ".join(ids[:k]) + more


def _distance(rpc, lon, lat, h, s, l):
    """|measured - RPC(ground)| in px; inf outside the RPC's ground domain or where the projection fails."""
    with np.errstate(all="ignore"):
        nl, np_ = _ground_normalised(rpc, lon, lat)
        inside = (nl <= GROUND_DOMAIN) & (np_ <= GROUND_DOMAIN) & np.isfinite(h)
        ps, pl = (np.asarray(v, float) for v in rpc.project(np.where(inside, lon, float(rpc.long_off)),
                                                            np.where(inside, lat, float(rpc.lat_off)),
                                                            np.where(inside, h, float(rpc.height_off))))
        d = np.hypot(s - ps, l - pl)
    return np.where(inside & np.isfinite(d), d, np.inf)


def _ground_normalised(rpc, lon, lat):
    """|normalised lon|, |normalised lat| of ground points in the RPC's own ground box."""
    with np.errstate(all="ignore"):
        return (np.abs((lon - float(rpc.long_off)) / (abs(float(rpc.long_scale)) or 1.0)),
                np.abs((lat - float(rpc.lat_off)) / (abs(float(rpc.lat_scale)) or 1.0)))


def _image_normalised(rpc, s, l):
    """|normalised sample|, |normalised line| of GDAL-convention image points in the RPC's own image box (a crop's
    RPC keeps the product's scales and shifts its offsets: its box is the product's, not the crop's)."""
    with np.errstate(all="ignore"):
        return (np.abs((s - 0.5 - float(rpc.samp_off)) / (abs(float(rpc.samp_scale)) or 1.0)),
                np.abs((l - 0.5 - float(rpc.line_off)) / (abs(float(rpc.line_scale)) or 1.0)))


def _outside_words(s, l, w, h) -> str:
    """'36 px above, 282 px right' for one point outside a w x h image."""
    parts = []
    for d, side in ((-l, "above"), (l - h, "below"), (-s, "left"), (s - w, "right")):
        if d > 0:
            parts.append(f"{d:.0f} px {side}")
    return ", ".join(parts)


def check_measured_inside(rpc, gcps, image_size: Optional[Tuple[int, int]] = None, *,
                          outside_margin: float = OUTSIDE_MARGIN, what: str = "GCPs", lon=None, lat=None,
                          stray_fraction: float = 0.0) -> int:
    """Measured image points against the image and the RPC's own domain (METHODS §4, §6; issue 19).

    ``gcps``: a table with ``sample, line`` (GDAL convention) and ``id``; ``lon``/``lat`` (when known) are checked
    against the RPC's ground box too. Points within ``outside_margin`` x the image size of it pass; points farther
    out but inside the RPC's validity box (normalised image and ground coordinates within :data:`RPC_DOMAIN`) and
    within :data:`OUTSIDE_USE_MARGIN` x the image size are used, with a warning naming them and how far out they
    are (field GCPs just outside a crop whose RPC is the product's); the rest are refused (:class:`GCPError`
    naming the override), unless they are at most ``stray_fraction`` of the points and within
    :data:`STRAY_MARGIN` x the image size (stray tie measurements: blunders left to the robust adjustment, with a
    warning). Returns the number of points used outside the image.
    """
    w, hgt = (float(x) for x in (image_size or rpc.image_size))
    implied = image_size is None                  # a standalone RPC: its size is a guess from offsets and scales
    if implied:
        outside_margin = max(outside_margin, IMPLIED_SIZE_MARGIN)
    s, l = (np.asarray(gcps[c], float) for c in ("sample", "line"))
    n = s.size
    if n == 0:
        return 0
    out = ~((s >= -outside_margin * w) & (s <= w * (1 + outside_margin)) & (l >= -outside_margin * hgt)
            & (l <= hgt * (1 + outside_margin)))
    if not out.any():
        return 0
    ns, nl = _image_normalised(rpc, s, l)
    usable = (ns <= RPC_DOMAIN) & (nl <= RPC_DOMAIN)
    usable &= ((s >= -OUTSIDE_USE_MARGIN * w) & (s <= w * (1 + OUTSIDE_USE_MARGIN))
               & (l >= -OUTSIDE_USE_MARGIN * hgt) & (l <= hgt * (1 + OUTSIDE_USE_MARGIN)))
    if lon is not None and lat is not None:
        glon, glat = _ground_normalised(rpc, np.asarray(lon, float), np.asarray(lat, float))
        usable &= (glon <= RPC_DOMAIN) & (glat <= RPC_DOMAIN)
    bad = out & ~usable
    stray = bad & (s >= -STRAY_MARGIN * w) & (s <= w * (1 + STRAY_MARGIN)) & (l >= -STRAY_MARGIN * hgt) & \
        (l <= hgt * (1 + STRAY_MARGIN))
    if bad.any() and stray.sum() == bad.sum() and bad.sum() <= stray_fraction * n:
        warnings.warn(f"{bad.sum()} of {n} {what} are measured outside the {w:.0f} x {hgt:.0f} px image, beyond its "
                      f"RPC's domain ({_ids(gcps, bad)}): blunders, left to the robust adjustment to flag")
        out &= ~bad
        bad[:] = False
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        what_img = "image implied by the RPC" if implied else "image"
        away = max(max(-s[i], s[i] - w, 0.0) / w, max(-l[i], l[i] - hgt, 0.0) / hgt)
        raise GCPError(f"{bad.sum()} of {n} {what} are measured outside the {w:.0f} x {hgt:.0f} px {what_img}, "
                       f"beyond {OUTSIDE_USE_MARGIN:.0%} of its size or its RPC's domain ({_ids(gcps, bad)}; e.g. "
                       f"{_id_array(gcps)[i]} at sample {s[i]:.1f}, line {l[i]:.1f}, {away:.1f} image sizes out): "
                       "they belong to another "
                       f"image or use other pixel units; remove or fix them, or {OVERRIDE_WORDS}")
    if not out.any():
        return 0
    ids = _id_array(gcps)[out]
    k = 6
    named = "; ".join(f"{i} ({_outside_words(a, b, w, hgt)})" for i, a, b in zip(ids[:k], s[out][:k], l[out][:k]))
    more = f"; and {out.sum() - k} more" if out.sum() > k else ""
    warnings.warn(f"{out.sum()} of {n} {what} are measured outside the {w:.0f} x {hgt:.0f} px image but inside its "
                  f"RPC's domain, and used: {named}{more}; check them if this image is not a crop of its product")
    return int(out.sum())


def check_heights_against_dem(gcps, dem) -> None:
    """GCP heights against the DEM under them (METHODS §2, §6; issue 19): a consistent ratio of 3.28 (feet) or a
    consistent offset of a geoid's size (orthometric vs ellipsoidal heights) is refused (:class:`GCPError` naming
    the override). Heights taken from the DEM itself, points off the DEM and fewer than
    :data:`MIN_HEIGHT_POINTS` compared points are not judged."""
    if dem is None:
        return
    lon, lat, h = (np.asarray(gcps[c], float) for c in ("lon", "lat", "h"))
    try:
        with np.errstate(all="ignore"):
            hd = np.asarray(dem.sample(lon, lat, nodata="nan"), float).ravel()
    except Exception:  # noqa: BLE001 - a DEM that cannot be sampled here is judged elsewhere (reading, coverage)
        return
    d = h - hd
    ok = np.isfinite(d) & (np.abs(d) > 1e-3)      # heights filled from the DEM agree with it exactly
    if ok.sum() < MIN_HEIGHT_POINTS:
        return
    d, h, hd = d[ok], h[ok], hd[ok]
    off = float(np.median(np.abs(d)))
    off_feet = float(np.median(np.abs(h * FEET - hd)))
    if off > FEET_MIN_OFFSET_M and off_feet < FEET_AGREEMENT * off:
        raise GCPError(f"the GCP heights are {float(np.median(h / hd)):.2f} x the DEM under them (median of "
                       f"{ok.sum()} points; in metres x 0.3048 they agree within {off_feet:.1f} m): they look like "
                       f"feet; give heights in metres, or {OVERRIDE_WORDS}")
    med = float(np.median(d))
    same_sign = float(np.mean(np.sign(d) == np.sign(med)))
    spread = float(np.median(np.abs(d - med)))
    if DATUM_MIN_OFFSET_M <= abs(med) <= DATUM_MAX_OFFSET_M and same_sign >= DATUM_SAME_SIGN and \
            spread <= DATUM_MAX_SPREAD * abs(med):
        raise GCPError(f"the GCP heights lie a consistent {med:+.1f} m from the DEM under them (median of {ok.sum()} "
                       f"points, {same_sign:.0%} on that side; a geoid's size): GCPs and DEM use different vertical "
                       "datums (orthometric vs ellipsoidal); give ellipsoidal GCP heights or the DEM's geoid "
                       f"(--geoid), or {OVERRIDE_WORDS}")


def check_gcps_against(rpc, gcps, image_size: Optional[Tuple[int, int]] = None, *,
                       outside_margin: float = OUTSIDE_MARGIN, predicted_margin_px: Optional[float] = None,
                       height_margin_m: float = HEIGHT_MARGIN_M, dem=None, what: str = "GCPs") -> Dict[str, Any]:
    """Refuse GCPs that cannot belong to the image of ``rpc`` (METHODS §4, §6; issues 11, 19); GCPError naming why
    and the override (``--no-plausibility-check``).

    ``gcps``: the GCP table (``lon, lat, h, sample, line``, GDAL convention). ``image_size`` (W, H): the image's
    (default: implied by the RPC's offsets and scales). In this order: measured points outside the image
    (:func:`check_measured_inside`: used with a warning inside the RPC's own domain, refused beyond it); heights
    outside the RPC's height range +/- ``height_margin_m`` (named "feet" when /3.28 would fit) and, with a ``dem``,
    heights in feet or on another vertical datum than the DEM's (:func:`check_heights_against_dem`); points whose
    RPC prediction lies more than ``predicted_margin_px`` (default max(500 px, 10 % of the image diagonal)) from
    their measured position: "lon/lat swapped" when swapping brings them in, else "check the layer's CRS". A real
    bias of tens of px passes. ``what`` names the points in messages. Returns the margins used and
    ``n_outside_used``.
    """
    w, hgt = (float(x) for x in (image_size or rpc.image_size))
    if image_size is None:
        outside_margin = max(outside_margin, IMPLIED_SIZE_MARGIN)
    n = len(gcps)
    if n == 0:
        return {}
    lon, lat, h, s, l = (np.asarray(gcps[c], float) for c in ("lon", "lat", "h", "sample", "line"))
    # 1. measured image points inside the image, or inside the RPC's domain (used, with a warning)
    n_out = check_measured_inside(rpc, gcps, image_size, outside_margin=outside_margin, lon=lon, lat=lat, what=what)
    # 2. heights within the RPC's height range (+ margin); against the DEM under them when there is one
    h0, h1 = rpc.height_range
    lo, hi = h0 - height_margin_m, h1 + height_margin_m
    bad = ~((h >= lo) & (h <= hi))
    if bad.any():
        feet = h * FEET
        in_feet = bool(np.all((feet[bad] >= lo) & (feet[bad] <= hi)))
        hint = ("they look like feet: give heights in metres (x 0.3048)" if in_feet else
                "give ellipsoidal heights in metres (or --dem) for points of this image")
        raise GCPError(f"{bad.sum()} of {n} GCP heights lie outside the RPC's height range {h0:.0f}..{h1:.0f} m "
                       f"+/- {height_margin_m:.0f} m (e.g. {_ids(gcps, bad, 1)}: {h[bad][0]:.6g} m): {hint}, or "
                       f"{OVERRIDE_WORDS}")
    check_heights_against_dem(gcps, dem)
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
                           f"{np.median(d_swap):.1f} px); swap the lon and lat columns, or {OVERRIDE_WORDS}")
        med = np.median(d)
        where = "outside the RPC's ground domain" if not np.isfinite(med) else f"median {med:.0f} px off"
        if far.sum() * 2 > n:
            raise GCPError(f"{far.sum()} of {n} GCPs project more than {margin:.0f} px from their measured position "
                           f"({where}): the ground coordinates do not belong to this image; check the layer's CRS "
                           "(or --gcp-crs), the lon/lat order and that the GCPs are for this image, or "
                           f"{OVERRIDE_WORDS}")
        raise GCPError(f"{far.sum()} of {n} GCPs ({_ids(gcps, far)}) project more than {margin:.0f} px from their "
                       f"measured position: they cannot belong to this image; remove or fix them, or {OVERRIDE_WORDS}")
    return {"outside_margin": outside_margin, "predicted_margin_px": margin, "n_outside_used": n_out,
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
