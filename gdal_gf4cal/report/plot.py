"""Residual vectors in image space, before and after, as a PNG (matplotlib Agg, no display)."""
from __future__ import annotations

import functools
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
#: zlib level of the PNGs: 1 encodes in ~2/3 of the default's (6) CPU, holding the GIL, for ~10 % larger files
#: (the same pixels: PNG is lossless).
PNG_COMPRESS_LEVEL = 1


def _save(fig, path: PathLike) -> Path:
    """Write ``fig`` as a PNG at ``path`` atomically (temporary file in the folder, then :func:`os.replace`)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    path = Path(path)
    FigureCanvasAgg(fig)
    tmp = _temp_path(path)
    try:
        fig.savefig(str(tmp), format="png", pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
        os.replace(tmp, path)
    finally:
        _cleanup(tmp)
    return path


def _few_ticks(ax, nbins: int = 5) -> None:
    """At most ``nbins`` intervals of round ticks on both axes, only those in view: matplotlib builds every tick as
    a set of artists (3 lines, 2 texts: ~0.5 ms each, holding the GIL), which made most of a small figure's drawing
    time, also for the locations beyond the view it then does not draw (a third of the pan-MS plots' ticks)."""
    locator = _in_view_locator()
    ax.xaxis.set_major_locator(locator(nbins, steps=[1, 2, 5, 10]))
    ax.yaxis.set_major_locator(locator(nbins, steps=[1, 2, 5, 10]))


@functools.lru_cache(maxsize=1)
def _in_view_locator():
    """matplotlib's MaxNLocator giving only the locations inside the view interval (within matplotlib's own 1e-10
    tolerance of its edges: the ticks it draws, the same pixels); a class made on first use (matplotlib is
    imported only when a plot is drawn)."""
    from matplotlib.ticker import MaxNLocator

    class InViewLocator(MaxNLocator):
        def tick_values(self, vmin, vmax):
            locs = super().tick_values(vmin, vmax)
            lo, hi = min(vmin, vmax), max(vmin, vmax)
            tol = 1e-10 * (hi - lo)
            return locs[(locs >= lo - tol) & (locs <= hi + tol)]

    return InViewLocator


def _nice_scale(v: float) -> float:
    """1, 2 or 5 x 10^k, not above v (the scale arrow's length in px)."""
    if not math.isfinite(v) or v <= 0:
        return 1.0
    e = 10 ** math.floor(math.log10(v))
    for m in (5, 2, 1):
        if m * e <= v:
            return m * e
    return e


#: At most this many arrows per panel (a seeded sample beyond; outliers always drawn) and id labels only up to
#: _MAX_LABELS points: a picture of 1e6 arrows takes minutes and shows nothing more (the statistics use every point).
_MAX_ARROWS = 5000
_MAX_LABELS = 200


def plot_residuals(gcps, path: PathLike, *, before: Optional[Tuple[str, str]] = STANDARD_BEFORE,
                   after: Optional[Tuple[str, str]] = STANDARD_AFTER, image_size: Optional[Tuple[int, int]] = None,
                   title: str = "GCP residuals", dpi: int = 110) -> Path:
    """Residual vectors in image space, before and after, side by side (a PNG, written atomically).

    Each panel draws every GCP's residual ``(res_sample, res_line)`` (measured - predicted, px) as an arrow at its
    image position (line axis pointing down, like the image), control and check points in different colours and
    outliers circled, GCP ids written next to each point, with a scale arrow and the per-axis RMS of control and
    check points (separately) in the panel title. ONE exaggeration for all panels (stated in the figure title), so
    the gain of the refinement shows as shorter arrows; the axes include the whole image and every GCP; the legend
    sits below the axes.

    Parameters
    ----------
    gcps : DataFrame
        With ``sample``, ``line`` (GDAL convention), the residual columns, optionally ``role`` and ``outlier``.
    path : path-like
        Output ``.png``.
    before, after : (str, str) or None
        (sample, line) residual columns; missing ones give no panel. At least one must exist.
    image_size : (width, height), optional
        The axes include the whole image (dashed frame) and every GCP; default: the GCPs' extent.
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
    ids = df["id"].astype(str).to_numpy() if "id" in df.columns else np.array([str(i) for i in range(len(df))])
    n_all = len(df)
    draw = np.ones(n_all, bool)
    if n_all > _MAX_ARROWS:
        draw[:] = False
        draw[np.random.default_rng(0).choice(n_all, _MAX_ARROWS, replace=False)] = True
        title = f"{title}; {_MAX_ARROWS:,} of {n_all:,} GCPs drawn"
    xlim, ylim = _residual_limits(s, l, image_size)
    factor, ref = _common_exaggeration(panels, s, l, outlier,
                                       max(abs(xlim[1] - xlim[0]), abs(ylim[1] - ylim[0])))
    fig = Figure(figsize=(5.2 * len(panels), 6.2), dpi=dpi)
    FigureCanvasAgg(fig)
    fig.suptitle(f"{title} (arrows exaggerated {factor:.3g}x in every panel)")
    points = dict(s=s, l=l, role=role, outlier=outlier, draw=draw, ids=ids if n_all <= _MAX_LABELS else None)
    with matplotlib.rc_context({"font.size": 9}):
        for k, (label, (rs, rl)) in enumerate(panels):
            ax = fig.add_subplot(1, len(panels), k + 1)
            _residual_panel(ax, label, rs, rl, points, image_size, xlim, ylim, factor, ref)
        fig.tight_layout()
    return _save(fig, path)


def _residual_limits(s, l, image_size):
    """(xlim, ylim) of the residual panels: the whole image AND every GCP (points outside the image are drawn too,
    never clipped away), line axis pointing down."""
    xs = [s[np.isfinite(s)]] + ([np.array([0.0, float(image_size[0])])] if image_size is not None else [])
    ys = [l[np.isfinite(l)]] + ([np.array([0.0, float(image_size[1])])] if image_size is not None else [])
    xa, ya = np.concatenate(xs), np.concatenate(ys)
    pad = 0.06 * max(float(np.ptp(xa)) if xa.size else 1.0, float(np.ptp(ya)) if ya.size else 1.0, 1.0)
    xlim = (float(xa.min()) - pad, float(xa.max()) + pad) if xa.size else (0.0, 1.0)
    ylim = (float(ya.max()) + pad, float(ya.min()) - pad) if ya.size else (1.0, 0.0)
    return xlim, ylim


def _common_exaggeration(panels, s, l, outlier, span):
    """ONE exaggeration for every panel (data units per px of residual), from the longest regular residual of any
    panel, so the gain shows; and the scale arrow's length (px)."""
    finite_all = np.isfinite(s) & np.isfinite(l)
    longest = 0.0
    for _, (rs, rl) in panels:
        mag = np.hypot(rs, rl)
        ok = finite_all & np.isfinite(mag) & (~outlier if (finite_all & np.isfinite(mag) & ~outlier).any() else True)
        if ok.any():
            longest = max(longest, float(np.max(mag[ok])))
    factor = 0.08 * span / longest if longest > 0 else 1.0
    return factor, (_nice_scale(longest) if longest > 0 else 1.0)


def _residual_panel(ax, label, rs, rl, points, image_size, xlim, ylim, factor, ref) -> None:
    """One panel of :func:`plot_residuals`: arrows by role, outliers circled, ids, the image frame, a scale arrow,
    the control and check RMS in the title, the legend below the axes."""
    from matplotlib.patches import Rectangle
    s, l, role, outlier, draw = (points[k] for k in ("s", "l", "role", "outlier", "draw"))
    mag = np.hypot(rs, rl)
    finite = np.isfinite(mag) & np.isfinite(s) & np.isfinite(l)
    quiver = dict(angles="xy", scale_units="xy", scale=1.0 / factor, width=0.004)
    for r, colour in (("control", _ROLE_COLOURS["control"]), ("check", _ROLE_COLOURS["check"])):
        m = finite & (role == r) & draw
        if m.any():    # y axis is inverted (line down): +res_line draws downwards, like the image
            ax.quiver(s[m], l[m], rs[m], rl[m], color=colour, label=f"{r} ({int(m.sum())})", **quiver)
    m = finite & ~np.isin(role, ["control", "check"]) & draw
    if m.any():
        ax.quiver(s[m], l[m], rs[m], rl[m], color="#888888", label=f"other ({int(m.sum())})", **quiver)
    if (outlier & finite).any():
        ax.scatter(s[outlier & finite], l[outlier & finite], s=60, facecolors="none", edgecolors=_OUTLIER_COLOUR,
                   linewidths=1.2, label=f"outlier ({int((outlier & finite).sum())})")
    for i in np.flatnonzero(np.isfinite(s) & np.isfinite(l)) if points["ids"] is not None else ():
        ax.annotate(points["ids"][i], (s[i], l[i]), xytext=(3, 3), textcoords="offset points", fontsize=6,
                    color="#333333")
    if image_size is not None:
        ax.add_patch(Rectangle((0, 0), float(image_size[0]), float(image_size[1]), fill=False,
                               edgecolor="#aaaaaa", linewidth=0.8, linestyle="--", label="image"))
    x0 = xlim[0] + 0.05 * (xlim[1] - xlim[0])          # scale arrow in the lower-left corner
    y0 = ylim[0] - 0.05 * (ylim[0] - ylim[1])
    ax.quiver([x0], [y0], [ref], [0.0], color="black", angles="xy", scale_units="xy", scale=1.0 / factor,
              width=0.006)
    ax.annotate(f"{ref:g} px", (x0, y0), xytext=(0, 6), textcoords="offset points", fontsize=8)
    lines = []
    for r in ("control", "check"):          # control and check never mixed in one number
        use = finite & ~outlier & (role == r)
        if use.any():
            lines.append(f"{r} (n={int(use.sum())}): RMS sample {np.sqrt(np.mean(rs[use] ** 2)):.3g} px, "
                         f"line {np.sqrt(np.mean(rl[use] ** 2)):.3g} px")
    ax.set_title(f"{label}\n" + "\n".join(lines), fontsize=8)
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal")
    ax.set_xlabel("sample (px)")
    ax.set_ylabel("line (px)")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=3, fontsize=7, frameon=False)  # never over an arrow


def plot_seams(seams, path: PathLike, *, residual_rms=None, title: str = "Seams between adjacent CCDs",
               dpi: int = 110) -> Path:
    """Seam offsets along track, before and after (METHODS §8 seam report), and residual RMS per image (a PNG).

    ``seams``: the list of :func:`gdal_gf4cal.block.seam_offsets` (each with ``pair`` and ``points``: ``line_b``,
    ``ds_before``, ``dl_before``, ``ds_after``, ``dl_after``, px). Left panels: sample and line offset of each
    overlap's tie points against their line (before faded, after solid), one colour per pair, the legend below
    the panels (never over the data). ``residual_rms``: ``{image: (before, after)}`` planar RMS px, drawn as bars
    on the right.
    """
    return _save(seams_figure(seams, residual_rms=residual_rms, title=title, dpi=dpi), path)


def pair_colours(n: int) -> list:
    """``n`` distinct colours (hex): matplotlib's tab10 / tab20 up to 20, else evenly spaced hues of a perceptual
    cyclic map; never a repeated colour."""
    from matplotlib import colormaps
    from matplotlib.colors import to_hex
    if n <= 10:
        return [to_hex(c) for c in colormaps["tab10"].colors[:n]]
    if n <= 20:
        return [to_hex(c) for c in colormaps["tab20"].colors[:n]]
    cmap = colormaps["twilight_shifted"] if n > 60 else colormaps["hsv"]
    return [to_hex(cmap(k / n)) for k in range(n)]


def seams_figure(seams, *, residual_rms=None, title: str = "Seams between adjacent CCDs", dpi: int = 110):
    """The figure of :func:`plot_seams` (a matplotlib ``Figure``, not saved)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    ncol = 3 if residual_rms else 2
    drawn = [s for s in seams if s.get("points")]
    legend_rows = -(-len(drawn) // 4) if drawn else 0
    fig = Figure(figsize=(5.0 * ncol, 4.6 + 0.22 * legend_rows), dpi=dpi)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, ncol, i + 1) for i in range(ncol)]
    handles = []
    for entry, c in zip(drawn, pair_colours(len(drawn))):
        p = entry["points"]
        for ax, key in zip(axes[:2], ("ds", "dl")):
            ax.plot(p["line_b"], p[f"{key}_before"], ".", color=c, alpha=0.25, ms=3)
            h, = ax.plot(p["line_b"], p[f"{key}_after"], "o", color=c, ms=3,
                         label=f"{entry['pair'][0]} | {entry['pair'][1]}")
        handles.append(h)
    for ax, name in zip(axes[:2], ("sample", "line")):
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_xlabel("line (right image of the pair)")
        ax.set_ylabel(f"{name} offset, px (faded: before)")
        ax.set_title(f"{name} seam offset")
    if residual_rms:
        _residual_bars(axes[2], residual_rms)
    fig.suptitle(title)
    bottom = 0.0
    if handles:          # below the panels, outside every axes: one entry (and colour) per pair
        bottom = min(0.45, (0.22 * legend_rows + 0.15) / fig.get_figheight())
        fig.legend(handles=handles, loc="lower center", ncol=min(4, len(handles)), fontsize=7, frameon=False,
                   title="overlap (left | right image): after; faded: before", title_fontsize=7)
    fig.tight_layout(rect=(0.0, bottom, 1.0, 1.0))
    return fig


def _residual_bars(ax, residual_rms) -> None:
    names = list(residual_rms)
    xs = np.arange(len(names))
    ax.bar(xs - 0.2, [residual_rms[n][0] for n in names], 0.4, color="#bbbbbb", label="before")
    ax.bar(xs + 0.2, [residual_rms[n][1] for n in names], 0.4, color="#1f4fd1", label="after")
    ax.set_xticks(xs)
    ax.set_xticklabels(names, rotation=90, fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("planar RMS residual, px (grey: before, blue: after)")
    ax.set_title("residuals per CCD and band")


def plot_tie_residuals(table, path: PathLike, *, sizes=None, title: str = "Tie residuals per view",
                       dpi: int = 100) -> Path:
    """Tie residual vectors in each view's image space, before (top row) and after (bottom row) a bundle
    adjustment (METHODS §11), ONE exaggeration for every panel (stated in the title), outliers in red, the RMS per
    component (``sqrt(mean(ds^2, dl^2))``, METHODS §6) of the rays kept in each panel's title (a PNG).

    ``table``: the long table with ``image_id, sample, line, res_sample_before, res_line_before, res_sample_after,
    res_line_after`` and optionally ``outlier``; ``sizes``: ``{view: (W, H)}`` (dashed frame; default the ties'
    extent). At most :data:`_MAX_ARROWS` arrows per panel (a seeded sample)."""
    from matplotlib.figure import Figure
    views = list(dict.fromkeys(table["image_id"].astype(str)))
    out_all = _as_bool_array(table["outlier"]) if "outlier" in table.columns else np.zeros(len(table), bool)
    mags = np.hypot(_column(table, "res_sample_before"), _column(table, "res_line_before"))
    longest = float(np.nanmax(mags[~out_all])) if np.isfinite(mags[~out_all]).any() else 1.0
    fig = Figure(figsize=(4.2 * len(views), 8.4), dpi=dpi)
    for j, v in enumerate(views):
        rows = (table["image_id"].astype(str) == v).to_numpy()
        s, l, out = _column(table, "sample")[rows], _column(table, "line")[rows], out_all[rows]
        W, H = (sizes or {}).get(v) or (float(np.nanmax(s)), float(np.nanmax(l)))
        factor = 0.08 * max(W, H) / max(longest, 1e-9)
        draw = np.random.default_rng(0).permutation(s.size)[:_MAX_ARROWS]
        for i, when in enumerate(("before", "after")):
            ax = fig.add_subplot(2, len(views), i * len(views) + j + 1)
            rs, rl = _column(table, f"res_sample_{when}")[rows], _column(table, f"res_line_{when}")[rows]
            keep = np.zeros(s.size, bool)
            keep[draw] = True
            for m, colour in ((keep & ~out, _ROLE_COLOURS["control"]), (keep & out, _OUTLIER_COLOUR)):
                if m.any():
                    ax.quiver(s[m], l[m], rs[m], rl[m], color=colour, angles="xy", scale_units="xy",
                              scale=1.0 / factor, width=0.004)
            use = ~out & np.isfinite(rs) & np.isfinite(rl)
            rms = float(np.sqrt(np.mean(rs[use] ** 2 + rl[use] ** 2) / 2)) if use.any() else float("nan")
            ax.set_title(f"{v} {when}: RMS {rms:.3g} px ({int(use.sum())} rays, {int(out.sum())} outliers)",
                         fontsize=8)
            ax.plot([0, W, W, 0, 0], [0, 0, H, H, 0], "--", color="#aaaaaa", lw=0.8)
            ax.set_xlim(-0.05 * W, 1.05 * W)
            ax.set_ylim(1.05 * H, -0.05 * H)
            ax.set_aspect("equal")
            ax.set_xlabel("sample (px)", fontsize=8)
            ax.set_ylabel("line (px)", fontsize=8)
    fig.suptitle(f"{title}\none exaggeration: a 1 px residual is drawn {8.0 / max(longest, 1e-9):.3g} % of the "
                 "image's side; red: outliers")
    fig.tight_layout()
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------------------
# pan-MS registration (METHODS §9): residual maps per step, the residual along the line, the spectrum
# ----------------------------------------------------------------------------------------------------------------
def _no_empty_labels(ax) -> None:
    """Keep matplotlib from placing the axes' empty labels by measuring every tick label at each draw (nothing is
    drawn there: the same pixels; with titles set at ``y=1.0``, which ends the same search for the title, ~30 %
    of a small panel's drawing time, all of it holding the GIL)."""
    for axis, xy in ((ax.xaxis, (0.5, -0.1)), (ax.yaxis, (-0.1, 0.5))):
        if not axis.label.get_text():
            axis.set_label_coords(*xy)


def plot_step_residual_maps(sample, line, steps, path: PathLike, *, image_size, used=None,
                            title: str = "residuals per step", dpi: int = 100) -> Path:
    """One panel per step: the cells' residual vectors ``(res_sample, res_line)`` (MS px, measured - predicted)
    at their centres, ONE exaggeration for all panels, colour = magnitude; ``steps`` is a list of
    ``(name, res_sample, res_line, rms_sample, rms_line, p_le)``; ``used`` marks the cells in the estimate."""
    from matplotlib.figure import Figure
    W, H = image_size
    s, l = np.asarray(sample, float), np.asarray(line, float)
    used = np.ones(s.size, bool) if used is None else np.asarray(used, bool)
    mags = [np.hypot(rs, rl)[used] for _, rs, rl, *_ in steps]
    top = max(float(np.nanpercentile(m, 99)) if m.size else 0.0 for m in mags) or 1.0
    spacing = math.sqrt(W * H / max(1, s.size))
    k = 0.9 * spacing / top
    fig = Figure(figsize=(4.2 * len(steps), 4.8), dpi=dpi)
    for i, (name, rs, rl, rms_s, rms_l, p_le) in enumerate(steps):
        ax = fig.add_subplot(1, len(steps), i + 1)
        m = np.hypot(rs, rl)
        ax.quiver(s[used], l[used], rs[used] * k, -rl[used] * k, m[used], angles="xy", scale_units="xy", scale=1,
                  cmap="viridis", clim=(0, top), width=0.004)
        if (~used).any():
            ax.plot(s[~used], l[~used], ".", color="0.75", ms=2)
        ax.set_xlim(0, W)
        ax.set_ylim(H, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{name}\nrms {rms_s:.3f} / {rms_l:.3f} px, P(<=0.25) {100 * p_le:.1f} %", fontsize=9, y=1.0)
        ax.tick_params(labelsize=7)
        _few_ticks(ax, 4)
        _no_empty_labels(ax)
    fig.suptitle(f"{title} (arrows x {k:.0f}; grey: cells left out)", fontsize=10)
    return _save(fig, path)


def plot_line_profiles(series, path: PathLike, *, title: str = "residual along the line",
                       dpi: int = 100) -> Path:
    """Residual row means along the MS line, per axis: ``series`` = ``{label: (lines, mean_sample, mean_line)}``
    (e.g. before and after the jitter term, METHODS §9)."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(9, 5), dpi=dpi)
    for k, axis in enumerate(("sample", "line")):
        ax = fig.add_subplot(2, 1, k + 1)
        for label, (lc, ys, yl) in series.items():
            ax.plot(lc, (ys, yl)[k], label=label, lw=1)
        ax.set_ylabel(f"{axis} (MS px)")
        _few_ticks(ax)
        ax.axhline(0, color="0.6", lw=0.5)
        ax.legend(fontsize=8)
        if k == 0:
            _no_empty_labels(ax)
    ax.set_xlabel("MS line")
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def plot_spectrum(amplitudes, path: PathLike, *, chosen=None, unit: str = "Hz",
                  title: str = "residual spectrum along the line", dpi: int = 100) -> Path:
    """Amplitude spectra per axis (``amplitudes = {axis: (freqs, amp)}``, px) with the accepted jitter
    frequencies marked (``chosen = {axis: [frequency]}``), frequencies in ``unit``."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(9, 5), dpi=dpi)
    for k, axis in enumerate(("sample", "line")):
        ax = fig.add_subplot(2, 1, k + 1)
        f, a = amplitudes.get(axis, (np.zeros(0), np.zeros(0)))
        ax.plot(f, a, lw=1)
        for c in (chosen or {}).get(axis, []):
            ax.axvline(c, color="tab:red", lw=0.8, ls="--")
        ax.set_ylabel(f"{axis} amplitude (px)")
        _few_ticks(ax)
        if k == 0:
            _no_empty_labels(ax)
    ax.set_xlabel(f"frequency ({unit}); dashed: accepted jitter components")
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)
