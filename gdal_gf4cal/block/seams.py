"""Seam offsets between overlapping images from their tie points, before and after (METHODS §8 seam report)."""
from __future__ import annotations

import math
from typing import Any, Dict, List, Mapping, Sequence, Tuple

import numpy as np

from ..estimation import weighted_lsq

def seam_offsets(table, models_before: Mapping[str, Any], models_after: Mapping[str, Any], dem,
                 pairs: Sequence[Tuple[str, str]]) -> List[Dict[str, Any]]:
    """Seam offset of each overlap (METHODS §8 seam report) from its tie points, before and after.

    For a tie point seen by ``a`` and ``b``: ``a``'s measurement is localised on the DEM with ``a``'s model and
    projected with ``b``'s; the offset is ``b``'s measurement minus that prediction (px of ``b``, sample and line;
    matching noise included: ``sqrt(2)`` x the tie sigma per axis). Rows flagged ``outlier`` are left out.
    Returns one dict per pair with ``n``, per epoch ``mean``/``rms``/``max`` per axis and planar (``max_px``: the
    largest single tie offset, noise included), ``seam_max_px`` (the seam itself, noise averaged: the offsets fitted
    by a straight line along the overlap's lines, its largest magnitude over them), and the per-point arrays under
    ``points`` (``point_id, lon, lat, line_b, ds/dl before/after``).
    """
    out = []
    ok = ~table["outlier"].to_numpy(bool) if "outlier" in table.columns else np.ones(len(table), bool)
    ties = table[(table["kind"] == "tie").to_numpy() & ok]
    for a, b in pairs:
        ta = ties[ties["image_id"] == a].set_index("point_id")
        tb = ties[ties["image_id"] == b].set_index("point_id")
        common = ta.index.intersection(tb.index)
        entry: Dict[str, Any] = {"pair": [a, b], "n": int(len(common))}
        if len(common) == 0:
            out.append(entry)
            continue
        sa, la = ta.loc[common, "sample"].to_numpy(float), ta.loc[common, "line"].to_numpy(float)
        sb, lb = tb.loc[common, "sample"].to_numpy(float), tb.loc[common, "line"].to_numpy(float)
        pts = {"point_id": np.asarray(common, dtype=object), "sample_b": sb, "line_b": lb}
        for tag, models in (("before", models_before), ("after", models_after)):
            lon, lat, h = models[a].localize_dem(sa, la, dem)
            ps, pl = models[b].project(lon, lat, h)
            ds, dl = sb - np.asarray(ps), lb - np.asarray(pl)
            pts[f"ds_{tag}"], pts[f"dl_{tag}"] = ds, dl
            if tag == "before":
                pts["lon"], pts["lat"], pts["h"] = np.asarray(lon), np.asarray(lat), np.asarray(h)
            rad = np.hypot(ds, dl)
            entry[tag] = {"mean_sample_px": float(np.nanmean(ds)), "mean_line_px": float(np.nanmean(dl)),
                          "mean_px": float(math.hypot(np.nanmean(ds), np.nanmean(dl))),
                          "rms_sample_px": float(np.sqrt(np.nanmean(ds ** 2))),
                          "rms_line_px": float(np.sqrt(np.nanmean(dl ** 2))),
                          "rms_px": float(np.sqrt(np.nanmean(rad ** 2))), "max_px": float(np.nanmax(rad)),
                          "seam_max_px": _systematic_seam(lb, ds, dl)}
        entry["points"] = pts
        out.append(entry)
    return out


def _systematic_seam(line, ds, dl) -> float:
    """Largest magnitude over ``line``'s range of the straight line (in ``line``) fitted to the offsets ``ds, dl``:
    a seam that drifts along track, without the matching noise of single ties."""
    ok = np.isfinite(line) & np.isfinite(ds) & np.isfinite(dl)
    if ok.sum() < 3:
        return float(np.nanmax(np.hypot(ds, dl))) if ok.any() else float("nan")
    lo, hi = float(line[ok].min()), float(line[ok].max())
    u = (line[ok] - 0.5 * (lo + hi)) / max(0.5 * (hi - lo), 1.0)
    a = np.column_stack([np.ones(u.size), u])
    fs = weighted_lsq(a, ds[ok]).x
    fl = weighted_lsq(a, dl[ok]).x
    ends = np.array([[1.0, -1.0], [1.0, 1.0]])
    return float(np.max(np.hypot(ends @ fs, ends @ fl)))


