"""Residual vectors in image space, before and after, as a PNG (matplotlib Agg, no display)."""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from ..errors import GCPError
from ._common import _as_bool_array, STANDARD_BEFORE, STANDARD_AFTER, _ROLE_COLOURS, _OUTLIER_COLOUR, PathLike, _temp_path, _cleanup, _column, _residual_pair


# ----------------------------------------------------------------------------------------------------------------
# plot
# ----------------------------------------------------------------------------------------------------------------
def _nice_scale(v: float) -> float:
    """1, 2 or 5 x 10^k, not above v (the scale arrow's length in px)."""
    if not math.isfinite(v) or v <= 0:
        return 1.0
    e = 10 ** math.floor(math.log10(v))
    for m in (5, 2, 1):
        if m * e <= v:
            return m * e
    return e


def plot_residuals(gcps, path: PathLike, *, before: Optional[Tuple[str, str]] = STANDARD_BEFORE,
                   after: Optional[Tuple[str, str]] = STANDARD_AFTER, image_size: Optional[Tuple[int, int]] = None,
                   title: str = "GCP residuals", dpi: int = 110) -> Path:
    """Residual vectors in image space, before and after, side by side (a PNG, written atomically).

    Each panel draws every GCP's residual ``(res_sample, res_line)`` (measured - predicted, px) as an arrow at its
    image position (line axis pointing down, like the image), control and check points in different colours and
    outliers circled, with a scale arrow and the per-axis RMS in the panel title. Each panel has its own
    exaggeration so both patterns are readable (like Fig. 5 of seed 000); the scale arrow gives it.

    Parameters
    ----------
    gcps : DataFrame
        With ``sample``, ``line`` (GDAL convention), the residual columns, optionally ``role`` and ``outlier``.
    path : path-like
        Output ``.png``.
    before, after : (str, str) or None
        (sample, line) residual columns; missing ones give no panel. At least one must exist.
    image_size : (width, height), optional
        Sets the axes to the whole image; default: the GCPs' extent.
    """
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    import pandas as pd

    path = Path(path)
    df = gcps if isinstance(gcps, pd.DataFrame) else pd.DataFrame(gcps)
    panels = [(lab, _residual_pair(df, names)) for lab, names in (("before", before), ("after", after))]
    panels = [(lab, r) for lab, r in panels if r is not None]
    if not panels:
        raise GCPError("no residual columns to plot; compute residuals first (res_sample_*/res_line_* columns)")
    for col in ("sample", "line"):
        if col not in df.columns:
            raise GCPError(f"the GCP table has no {col!r} column")
    s, l = _column(df, "sample"), _column(df, "line")
    role = df["role"].astype(str).to_numpy() if "role" in df.columns else np.full(len(df), "control", object)
    outlier = _as_bool_array(df["outlier"]) if "outlier" in df.columns else np.zeros(len(df), bool)
    if image_size is not None:
        xlim, ylim = (0, float(image_size[0])), (float(image_size[1]), 0)
    else:
        pad = 0.05 * max(np.nanmax(s) - np.nanmin(s), np.nanmax(l) - np.nanmin(l), 1.0)
        xlim, ylim = (np.nanmin(s) - pad, np.nanmax(s) + pad), (np.nanmax(l) + pad, np.nanmin(l) - pad)
    span = max(abs(xlim[1] - xlim[0]), abs(ylim[1] - ylim[0]))

    fig = Figure(figsize=(5.2 * len(panels), 5.6), dpi=dpi)
    FigureCanvasAgg(fig)
    fig.suptitle(title)
    with matplotlib.rc_context({"font.size": 9}):
        for k, (label, (rs, rl)) in enumerate(panels):
            ax = fig.add_subplot(1, len(panels), k + 1)
            mag = np.hypot(rs, rl)
            finite = np.isfinite(mag) & np.isfinite(s) & np.isfinite(l)
            longest = float(np.nanmax(mag[finite])) if finite.any() else 0.0
            # Data units per px of residual: the longest arrow spans ~8 % of the image.
            factor = 0.08 * span / longest if longest > 0 else 1.0
            for r, colour in (("control", _ROLE_COLOURS["control"]), ("check", _ROLE_COLOURS["check"])):
                m = finite & (role == r)
                if m.any():
                    # y axis is inverted (line down): +res_line draws downwards, like the image.
                    ax.quiver(s[m], l[m], rs[m], rl[m], color=colour, angles="xy", scale_units="xy",
                              scale=1.0 / factor, width=0.004, label=f"{r} ({int(m.sum())})")
            m = finite & ~np.isin(role, ["control", "check"])
            if m.any():
                ax.quiver(s[m], l[m], rs[m], rl[m], color="#888888", angles="xy", scale_units="xy",
                          scale=1.0 / factor, width=0.004, label=f"other ({int(m.sum())})")
            if (outlier & finite).any():
                ax.scatter(s[outlier & finite], l[outlier & finite], s=60, facecolors="none",
                           edgecolors=_OUTLIER_COLOUR, linewidths=1.2,
                           label=f"outlier ({int((outlier & finite).sum())})")
            ref = _nice_scale(longest) if longest > 0 else 1.0
            # Scale arrow in the lower-left corner.
            x0 = xlim[0] + 0.05 * (xlim[1] - xlim[0])
            y0 = ylim[0] - 0.05 * (ylim[0] - ylim[1])
            ax.quiver([x0], [y0], [ref], [0.0], color="black", angles="xy", scale_units="xy", scale=1.0 / factor,
                      width=0.006)
            ax.annotate(f"{ref:g} px", (x0, y0), xytext=(0, 6), textcoords="offset points", fontsize=8)
            use = finite & ~outlier
            rms_s = float(np.sqrt(np.mean(rs[use] ** 2))) if use.any() else float("nan")
            rms_l = float(np.sqrt(np.mean(rl[use] ** 2))) if use.any() else float("nan")
            ax.set_title(f"{label}: RMS sample {rms_s:.3g} px, line {rms_l:.3g} px", fontsize=9)
            ax.set_xlim(*xlim)
            ax.set_ylim(*ylim)
            ax.set_aspect("equal")
            ax.set_xlabel("sample (px)")
            ax.set_ylabel("line (px)")
            ax.legend(loc="upper right", fontsize=7)
        fig.tight_layout()
    tmp = _temp_path(path)
    try:
        fig.savefig(str(tmp), format="png")
        os.replace(tmp, path)
    finally:
        _cleanup(tmp)
    return path
