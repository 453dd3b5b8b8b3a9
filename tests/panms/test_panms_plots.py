"""The pan-MS plots skip matplotlib's placement of empty axis labels and of the panel titles (measuring every tick
label at each draw, GIL-bound: issue 23) without moving a pixel: each PNG is the same bytes as with matplotlib's
automatic placement restored."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.report import plot


def _automatic(ax):
    """matplotlib's own placement of the axis labels and the title (what the plots did before)."""
    ax.xaxis._autolabelpos = ax.yaxis._autolabelpos = True
    ax._autotitlepos = True


def _draw_all(folder):
    rng = np.random.default_rng(3)
    s, l = np.meshgrid(np.arange(8, 256, 16.0), np.arange(8, 256, 16.0))
    s, l = s.ravel(), l.ravel()
    steps = [(name, rng.normal(0, sd, s.size), rng.normal(0, sd, s.size), sd, sd, 0.5)
             for name, sd in (("before", 0.7), ("linear", 0.1), ("piecewise", 0.03))]
    used = rng.random(s.size) > 0.1
    plot.plot_step_residual_maps(s, l, steps, folder / "maps.png", image_size=(256, 256), used=used)
    lc = np.arange(16, 256, 16.0)
    plot.plot_line_profiles({"after piecewise": (lc, 0.01 * np.sin(lc / 20), 0.01 * np.cos(lc / 30)),
                             "after jitter": (lc, 0.005 * np.sin(lc / 20), 0.01 * np.cos(lc / 30))},
                            folder / "line.png")
    f = np.linspace(10, 100, 80)
    plot.plot_spectrum({"sample": (f, np.abs(np.sin(f / 7))), "line": (f, np.abs(np.cos(f / 9)))},
                       folder / "spectrum.png", chosen={"sample": [38.0], "line": []})
    return {p.name: p.read_bytes() for p in folder.glob("*.png")}


def test_pan_ms_plots_are_the_pixels_of_automatic_placement(tmp_path, monkeypatch):
    (tmp_path / "fast").mkdir()
    (tmp_path / "auto").mkdir()
    fast = _draw_all(tmp_path / "fast")
    placed = []
    monkeypatch.setattr(plot, "_no_empty_labels", lambda ax: placed.append(ax) or _automatic(ax))
    auto = _draw_all(tmp_path / "auto")
    assert len(placed) == 5                     # 3 maps, the upper panel of each 2-panel figure
    assert sorted(fast) == ["line.png", "maps.png", "spectrum.png"]
    for name in fast:
        assert fast[name] == auto[name], name


@pytest.mark.parametrize("text", ["", "line (px)"])
def test_no_empty_labels_leaves_labelled_axes_to_matplotlib(text):
    from matplotlib.figure import Figure
    ax = Figure().add_subplot()
    ax.set_ylabel(text)
    plot._no_empty_labels(ax)
    assert ax.yaxis._autolabelpos is bool(text)
    assert ax.xaxis._autolabelpos is False
