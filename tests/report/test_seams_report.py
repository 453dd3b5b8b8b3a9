"""Issue 24: the seams plot's legend lies outside every panel and each of 15 pairs has its own colour; the seams
layer's QGIS style is graduated by the after-offset and draws arrows with the one factor its title states."""
from __future__ import annotations

import re

import numpy as np
import pytest


def _seams(n_pairs=15, n=32, seed=7):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_pairs):
        line = np.sort(rng.uniform(0, 5000, n))
        before = rng.normal(1.5, 0.4, (2, n))
        after = rng.normal(0.0, 0.05, (2, n))
        out.append({"pair": (f"ccd{k + 1}", f"ccd{k + 2}"), "points": {
            "point_id": np.arange(n), "line_b": line, "lon": np.full(n, 100.0 + 0.2 * k),
            "lat": 40.0 - line * 1e-5, "ds_before": before[0], "dl_before": before[1], "ds_after": after[0],
            "dl_after": after[1]}})
    return out


def test_seams_plot_legend_outside_the_data_one_colour_per_pair(tmp_path):
    from gdal_gf4cal.report.plot import pair_colours, plot_seams, seams_figure
    seams = _seams()
    rms = {f"ccd{k}": (2.0, 0.1) for k in range(1, 17)}
    fig = seams_figure(seams, residual_rms=rms)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    (legend,) = fig.legends
    box = legend.get_window_extent(renderer)
    for ax in fig.axes:                       # the legend covers no panel (nor its tick labels)
        assert not box.overlaps(ax.get_tightbbox(renderer)), ax.get_title()
    colours = [h.get_color() for h in legend.legend_handles] if hasattr(legend, "legend_handles") else \
        [h.get_color() for h in legend.legendHandles]
    assert len(colours) == 15 and len(set(colours)) == 15
    assert len(set(pair_colours(40))) == 40 and len(set(pair_colours(90))) == 90
    assert plot_seams(seams, tmp_path / "seams.png", residual_rms=rms).stat().st_size > 10_000


def test_seams_style_graduated_by_after_offset_with_one_stated_factor():
    from gdal_gf4cal.report.styles import seams_style
    seams = _seams()
    cols = {c: np.concatenate([s["points"][c] for s in seams]) for c in ("line_b", "ds_after", "dl_after")}
    cols["pair"] = np.concatenate([[f"{s['pair'][0]}|{s['pair'][1]}"] * 32 for s in seams]).astype(object)
    cols["offset_px_after"] = np.hypot(cols["ds_after"], cols["dl_after"])
    lon = np.concatenate([s["points"]["lon"] for s in seams])
    lat = np.concatenate([s["points"]["lat"] for s in seams])
    qml, sld, title, factor = seams_style(cols, lon, lat)
    assert 'type="graduatedSymbol"' in qml and 'attr="offset_px_after"' in qml
    assert title == f"seams after (x{factor:g})"
    assert qml.count('class="GeometryGenerator"') == qml.count("<range ") >= 4
    # the arrows are drawn with the factor the title states: k degrees of latitude per px of offset = factor x GSD
    from gdal_gf4cal.geodesy import metres_per_degree
    from gdal_gf4cal.report.styles import seams_ground_scale
    gsd, spacing = seams_ground_scale(cols, lon, lat)
    my = float(metres_per_degree(40.0)[1])
    assert gsd == pytest.approx(1e-5 * my, rel=0.01)         # the synthetic seams: 1e-5 degree of latitude per line
    k = {float(v) for v in re.findall(r'(?:"|&quot;)dl_after(?:"|&quot;) \* ([0-9.e+-]+)', qml)}
    assert len(k) == 1 and k.pop() * float(metres_per_degree(lat.mean())[1]) == pytest.approx(factor * gsd, rel=1e-6)
    longest = np.percentile(cols["offset_px_after"], 99) * factor * gsd
    assert 0.7 * spacing <= longest <= 3 * spacing           # the longest arrow about 1.5 tie-point spacings
    assert "offset_px_after" in sld
