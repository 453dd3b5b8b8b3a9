"""The one seeded GCP simulator of the tests (issue 10: instead of one copy per test module).

Import it as ``from gcpsim import gcps_from_truth`` (tests/ is on sys.path through its conftest.py), or use the
``simulate_gcps`` fixture. ``tests/frozen/scenes.py`` keeps its own copies on purpose: the frozen numbers must not
move when this one changes.
"""
from __future__ import annotations

import numpy as np
import pandas as pd


def gcps_from_truth(truth, n, *, size, heights, sigma_px=0.5, seed=0, n_control=None, blunder_fraction=0.0,
                    blunder_px=(10.0, 50.0), layout=None, id_prefix="g", with_sigma=True):
    """The one GCP simulator of the tests: ``n`` true image points spread over ``size`` (W, H) (uniformly, or
    ``layout(rng, n) -> (s, l)``), heights uniform in ``heights``, ground = ``truth.localize`` (any sensor model
    with the contract of gdal_gf4cal.sensor), measured with Gaussian noise ``sigma_px`` per axis; the first
    ``n_control`` are control, the rest check (default: all control); a seeded share ``blunder_fraction`` of the
    points is moved by ``blunder_px`` (uniform magnitude range, random direction). Returns ``(table, blunder)``:
    a DataFrame of the GCP schema with ``truth_sample, truth_line`` (and ``sigma`` unless ``with_sigma=False``:
    then the estimators' default of 1 px applies), and the boolean blunder mask. ``seed`` may be a Generator."""
    rng = np.random.default_rng(seed)
    if layout is None:
        s, l = rng.uniform(0, size[0], n), rng.uniform(0, size[1], n)
    else:
        s, l = layout(rng, n)
    h = rng.uniform(heights[0], heights[1], n)
    lon, lat = truth.localize(s, l, h)
    assert np.all(np.isfinite(lon)) and np.all(np.isfinite(lat)), "the truth model does not localise every GCP"
    ms, ml = s + rng.normal(0, sigma_px, n), l + rng.normal(0, sigma_px, n)
    blunder = np.zeros(n, bool)
    if blunder_fraction:
        idx = rng.choice(n, int(round(blunder_fraction * n)), replace=False)
        mag, ang = rng.uniform(*blunder_px, idx.size), rng.uniform(0, 2 * np.pi, idx.size)
        ms[idx] += mag * np.cos(ang)
        ml[idx] += mag * np.sin(ang)
        blunder[idx] = True
    n_control = n if n_control is None else n_control
    table = pd.DataFrame({"id": [f"{id_prefix}{i}" for i in range(n)], "lon": lon, "lat": lat, "h": h,
                          "sample": ms, "line": ml, "role": np.where(np.arange(n) < n_control, "control", "check"),
                          "truth_sample": s, "truth_line": l})
    if with_sigma:
        table.insert(8, "sigma", max(float(sigma_px), 1e-3))
    return table, blunder
