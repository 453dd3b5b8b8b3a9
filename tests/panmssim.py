"""Cell tables synthesised from the GF7 simulator's truth (METHODS §9): what ``matching.pan_ms_cells`` measures,
with seeded Gaussian noise of a known floor, blunders and cloudy cells, so the model's own accuracy tests stay fast."""
from __future__ import annotations

import numpy as np
import pandas as pd

from gdal_gf4cal.simulate.gf7 import cover_class, true_misregistration


def synth_cells(scene, *, cell: int = 64, sigma: float = 0.03, seed: int = 1, n_bad: int = 0,
                bad_px: float = 2.0) -> pd.DataFrame:
    """Regular MS cells (centres, GDAL convention) with ``d_sample, d_line`` = true nabla + N(0, sigma) noise,
    ``n_bad`` blunders of ~``bad_px`` and ``usable`` False where the cell centre is cloud or water."""
    ms = scene.image("ms")
    W, H = ms.size
    s, l = np.meshgrid(np.arange(W // cell) * cell + cell / 2.0, np.arange(H // cell) * cell + cell / 2.0)
    s, l = s.ravel(), l.ravel()
    ds, dl = true_misregistration(scene, s, l)
    rng = np.random.default_rng(seed)
    ds = ds + rng.normal(0.0, sigma, s.size)
    dl = dl + rng.normal(0.0, sigma, s.size)
    if n_bad:
        bad = rng.choice(s.size, n_bad, replace=False)
        ds[bad] += rng.normal(0.0, bad_px, n_bad)
        dl[bad] += rng.normal(0.0, bad_px, n_bad)
    lon, lat, _ = ms.true.localize_dem(s, l, scene.dem)
    clear = cover_class(scene, lon, lat) == 0
    return pd.DataFrame({"sample": s, "line": l, "d_sample": ds, "d_line": dl, "sigma_sample": sigma,
                         "sigma_line": sigma, "n": 100, "n_windows": 1, "usable": clear,
                         "clear_fraction": clear.astype(float)})


def truth_grid(scene, n: int = 150):
    """An ``n x n`` grid of MS points and the true nabla on it."""
    W, H = scene.image("ms").size
    s, l = np.meshgrid((np.arange(n) + 0.5) * W / n, (np.arange(n) + 0.5) * H / n)
    ds, dl = true_misregistration(scene, s, l)
    return s, l, ds, dl
