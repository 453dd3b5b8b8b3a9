"""register-pan-ms draws its plots after every other output, on the calling thread, one at a time, whatever the
thread count (issue 23): matplotlib holds the GIL throughout, so plots drawn beside the writes convoyed them (each
short GIL release of the writes' NumPy and GDAL calls waited a switch interval for the plotting thread: the
writes 0.1 s at 1 thread, 0.23-0.56 s at 2 on the GF7 bench crop), and two plots drawn at once only handed the
GIL to and fro.

The real Pleiades-1B Ventoux pan/MS crops (tests/panms/conftest.py), registered with 2 threads; every output
writer and plot is wrapped to note its thread and when it ran.
"""
from __future__ import annotations

import os
import threading
import time

from gdal_gf4cal import threads
from gdal_gf4cal.workflows import panms as wp

DATA = os.path.join(os.path.dirname(__file__), "..", "data")

WRITERS = ("_write_ms_rpc", "_write_cells")
PLOTS = ("plot_step_residual_maps", "plot_line_profiles", "plot_spectrum")


def _noted(fn, name, log):
    def run(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            log.append((name, threading.get_ident(), t0, time.perf_counter()))
    return run


def test_plots_are_drawn_after_the_writes_on_the_calling_thread(ventoux_pair, tmp_path, monkeypatch):
    log: list = []
    for name in WRITERS + PLOTS:
        monkeypatch.setattr(wp, name, _noted(getattr(wp, name), name, log))
    for name in ("write_correction", "resample_ms_on_pan"):
        monkeypatch.setattr(wp.panms, name, _noted(getattr(wp.panms, name), name, log))
    d = ventoux_pair
    with threads.limit(2):
        rep = wp.register_pan_ms(str(d / "left_image.tif"), str(d / "lowres_color_image.tif"),
                                 dem=os.path.join(DATA, "dem", "N44E005.hgt"), geoid="egm96",
                                 out=str(tmp_path / "out"))
    assert sorted(os.listdir(tmp_path / "out")) == sorted(wp.OUTPUT_NAMES.values())
    assert rep["steps"][-1]["rms_sample_px"] < 0.1
    writes = [e for e in log if e[0] not in PLOTS]
    plots = [e for e in log if e[0] in PLOTS]
    assert sorted(e[0] for e in writes) == sorted(WRITERS + ("write_correction", "resample_ms_on_pan"))
    assert sorted(e[0] for e in plots) == sorted(PLOTS)
    me = threading.get_ident()
    assert {e[1] for e in log} == {me}                          # everything on the calling thread
    assert min(e[2] for e in plots) >= max(e[3] for e in writes)     # the plots after every write
    spans = sorted((e[2], e[3]) for e in plots)
    assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:]))    # one plot at a time
