"""choose_cell (register-pan-ms's automatic cell size, issue 23) measures only the sizes whose cell grid could
pass (enough cell columns in every sub-CCD piece and rows): on a crop the large sizes cannot, and each cost a
full robust averaging of every band's window matches, on one thread. The size and cells chosen are those of
measuring every size in turn (the rule as written before), also when no size passes."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal.workflows import panms as wp


def _matches(W, H, spacing=4, seed=0, clear=1.0):
    """A window table as match_raw_bands gives it: windows every ``spacing`` px, an offset field with a jump at the
    sub-CCD edges, noise, a share ``1 - clear`` of the image flat (cloud: not accepted)."""
    rng = np.random.default_rng(seed)
    s, l = np.meshgrid(np.arange(20.0, W - 19, spacing), np.arange(20.0, H - 19, spacing))
    s, l = s.ravel(), l.ravel()
    flat = (l > clear * H).astype(float)
    st = np.where(flat > 0.5, 2, 0).astype(np.int8)
    d_s = 0.2 + 0.1 * (s > W / 3) + rng.normal(0, 0.03, s.size)
    d_l = -0.1 + rng.normal(0, 0.03, s.size)
    t = pd.DataFrame({"pred_sample": s, "pred_line": l, "d_sample": np.where(st == 0, d_s, np.nan),
                      "d_line": np.where(st == 0, d_l, np.nan), "sigma": np.full(s.size, 0.05), "status": st,
                      "flat": flat, "outlier": np.zeros(s.size, bool)})
    t.attrs.update(window_px=wp.WINDOW_PX, spacing_px=spacing)
    return t


def _every_size(matches, ms_size, spacing, breaks):
    """choose_cell as it was: every size measured in turn."""
    best = None
    for cell in [c for c in wp.AUTO_CELLS if c >= spacing] or [spacing]:
        cells = wp._cells(matches, ms_size, cell, spacing, breaks)
        u = np.asarray(cells["usable"], bool)
        s = np.asarray(cells["sample"], float)[u]
        piece = np.searchsorted(np.asarray(breaks, float), s, side="right")
        cols = min(np.unique(s[piece == k]).size for k in range(len(breaks) + 1))
        rows = np.unique(np.asarray(cells["line"], float)[u]).size
        if cols >= wp.MIN_CELL_COLUMNS and rows >= wp.MIN_CELL_ROWS:
            return cell, cells
        if best is None or (cols, rows) > best[0]:
            best = ((cols, rows), cell, cells)
    return best[1], best[2]


@pytest.mark.parametrize("size, breaks, clear, measured", [
    ((256, 256), [85.0, 171.0], 1.0, [8, 6]),    # a crop over two sub-CCD edges: 64..12 px skipped (were measured)
    ((1024, 512), [512.0], 1.0, [64]),           # the largest passes at once
    ((1024, 512), [512.0], 0.3, [64, 48, 32, 24]),   # mostly cloud: the grids could pass, the usable cells not
    ((256, 48), [128.0], 1.0, [8, 6, 4, 64, 48, 32, 24, 16, 12]),   # none passes: every size, the fullest chosen
])
def test_the_size_of_measuring_every_size(size, breaks, clear, measured, monkeypatch):
    t = _matches(*size, clear=clear)
    want_cell, want_cells = _every_size(t, size, 4, breaks)
    calls = []
    cells_fn = wp._cells
    monkeypatch.setattr(wp, "_cells", lambda *a: calls.append(a[2]) or cells_fn(*a))
    cell, cells = wp.choose_cell(t, size, 4, breaks)
    assert cell == want_cell
    pd.testing.assert_frame_equal(cells, want_cells)
    assert calls == measured
