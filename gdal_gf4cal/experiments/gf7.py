"""Experiment of seed 004 (Gaofen-7 backward camera): pan-to-MS registration, the paper's Tables 2-3 (METHODS §9).

Simulated GF7 scenes (METHODS §10: pan 30720² at 0.65 m, MS 7680² at 2.6 m, 0.117 s apart, three sub-CCDs per band
with quartic truth drawn from ``camera_seed`` = 4, a linear attitude truth and differential jitter drawn per scene).
The cell observations are the true misregistration field (``simulate.gf7.true_misregistration``, METHODS §9's
nabla) at the centres of 64-px MS cells plus Gaussian noise of ``cell_noise_px`` per axis (the precision of a
dense-matching cell mean; ``gf4cal register-pan-ms`` measures them on rendered images), so the experiment runs on
the full scene geometry in seconds. Every model is solved by :func:`gdal_gf4cal.panms.estimate`:

* **Table 2** (solve mode, three scenes): RMS per axis about zero and P(<= 0.25 px) before, after the linear term
  and after linear + piecewise (paper: 0.60 / 0.30 px, P < 1 %; < 0.12 / ~0.20, P ~ 70 %; 0.06-0.08 px, P > 97 %);
* **jitter step**: after the piecewise term and after the jitter term (paper: 0.07 -> 0.06, 0.08 -> 0.07), with
  the components found (frequency, amplitude, implied attitude jitter) against the simulated ones;
* **Table 3** (reuse mode, three more scenes of the same camera): the first scene's piecewise term, the linear term
  from 200 sparse cells; RMS and P on the scene's dense cells next to its own solve mode (paper: ~0.07 px, 98 %);
* **cloudy scene** (``clouds`` share): cells under cloud measure nothing (their nabla is noise of
  ``cloud_noise_px``); solved with every cell, and with the cloudy cells left out (paper: P 83.8 %, > 90 %).

Built from the public API only: :mod:`gdal_gf4cal.simulate.gf7`, :mod:`gdal_gf4cal.panms`, :mod:`gdal_gf4cal.report`.
"""
from __future__ import annotations

import os
import time
from typing import Any, Dict

import numpy as np
import pandas as pd

from .. import panms
from ..progress import report as _report
from ..report import write_report_json
from ..simulate.gf7 import cover_class, make_gf7_scene, true_misregistration
from ..stats import share_within

#: The paper's numbers (METHODS §9): before, after linear, after piecewise; jitter; reuse; cloudy scene.
PAPER = {"before": {"rms_sample_px": 0.60, "rms_line_px": 0.30, "p_le_0.25": "< 0.01"},
         "linear": {"rms_sample_px": "< 0.12", "rms_line_px": 0.20, "p_le_0.25": 0.70},
         "piecewise": {"rms_px": "0.06-0.08", "p_le_0.25": "> 0.97"},
         "jitter": {"rms_px": "0.07 -> 0.06, 0.08 -> 0.07", "components": 8, "amplitude_px": "< 0.1"},
         "reuse": {"rms_px": 0.07, "p_le_0.25": 0.98},
         "cloudy": {"p_le_0.25_all_cells": 0.838, "p_le_0.25_clear_cells": "> 0.90"}}
SOLVE_SEEDS, REUSE_SEEDS, CLOUDY_SEED = (0, 1, 2), (3, 4, 5), 6
CELL_PX = 64
CELL_NOISE_PX = 0.03
CLOUD_NOISE_PX = 0.5
N_SPARSE = 200


def _cells(scene, cell_px, noise_px, rng, cloud_noise_px=None):
    ms = scene.image("ms")
    W, H = ms.size
    s, l = np.meshgrid(np.arange(W // cell_px) * cell_px + cell_px / 2.0,
                       np.arange(H // cell_px) * cell_px + cell_px / 2.0)
    s, l = s.ravel(), l.ravel()
    ds, dl = true_misregistration(scene, s, l)
    lon, lat, _ = ms.true.localize_dem(s, l, scene.dem)
    clear = cover_class(scene, lon, lat) == 0
    noise = np.where(clear, noise_px, cloud_noise_px if cloud_noise_px else noise_px)
    return pd.DataFrame({"sample": s, "line": l, "d_sample": ds + rng.normal(0, 1, s.size) * noise,
                         "d_line": dl + rng.normal(0, 1, s.size) * noise, "sigma_sample": noise_px,
                         "sigma_line": noise_px, "usable": clear, "clear": clear})


def _row(step: dict) -> Dict[str, float]:
    return {"rms_sample_px": step["rms_sample_px"], "rms_line_px": step["rms_line_px"],
            "p_le_0.25": step["p_le_0.25"]}


def _evaluate(model, cells, mask) -> Dict[str, float]:
    ps, pl = model.predict(cells["sample"], cells["line"])
    rs, rl = (cells["d_sample"] - ps).to_numpy()[mask], (cells["d_line"] - pl).to_numpy()[mask]
    return {"rms_sample_px": float(np.sqrt(np.mean(rs ** 2))), "rms_line_px": float(np.sqrt(np.mean(rl ** 2))),
            "p_le_0.25": share_within(rs, rl, 0.25)}


def _fmt(r):
    return f"{r['rms_sample_px']:7.3f} {r['rms_line_px']:7.3f} {100 * r['p_le_0.25']:7.1f}%"


def run(out_dir, *, seed: int = 0, progress=None, cell_px: int = CELL_PX, cell_noise_px: float = CELL_NOISE_PX,
        clouds: float = 0.3, verbose: bool = True, write_files: bool = True) -> Dict[str, Any]:
    """Run the GF7 experiment; print the tables and write ``out_dir/report.json`` (and the first scene's
    ``model.json``). ``seed`` offsets every scene seed. Returns the report: ``table2`` (per scene: ``before``,
    ``linear``, ``piecewise``), ``jitter`` (per scene: ``piecewise``, ``jitter``, components vs truth),
    ``table3`` (per scene: ``reuse``, ``solve``), ``cloudy`` (``all_cells``, ``clear_cells``), ``paper``."""

    t0 = time.perf_counter()
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    rep: Dict[str, Any] = {"experiment": "gf7", "paper": PAPER, "cell_px": cell_px, "cell_noise_px": cell_noise_px,
                           "table2": {}, "jitter": {}, "table3": {}}
    n_steps = len(SOLVE_SEEDS) + len(REUSE_SEEDS) + 1
    first = None
    for i, sd in enumerate(SOLVE_SEEDS):
        _report(progress, i / n_steps, f"Table 2: scene {sd + seed}")
        scene = make_gf7_scene(seed=sd + seed)
        cells = _cells(scene, cell_px, cell_noise_px, np.random.default_rng(1000 + sd + seed))
        model = panms.estimate(cells, ms_size=scene.image("ms").size)
        steps = {st["step"]: st for st in model.steps}
        rep["table2"][f"scene{sd + seed}"] = {k: _row(steps[k]) for k in ("before", "linear", "piecewise")}
        truth = scene.image("ms").errors
        rep["jitter"][f"scene{sd + seed}"] = {
            "piecewise": _row(steps["piecewise"]), "jitter": _row(steps["jitter"]),
            "components": {ax: [{k: c.get(k) for k in ("frequency_hz", "amplitude_px", "attitude_amplitude_urad")}
                                for c in model.jitter[ax]["components"]] for ax in ("sample", "line")},
            "simulated": [{"axis": "sample" if a == "roll" else "line", "frequency_hz": f, "amplitude_px": d}
                          for (a, _, f, _), d in zip(truth["jitter"], truth["jitter_differential_px"])]}
        if first is None:
            first = model
            model.info["source"] = f"simulated GF7 scene seed {sd + seed}"
            if write_files:
                model.to_json(os.path.join(out_dir, "model.json"), overwrite=True)
    for i, sd in enumerate(REUSE_SEEDS):
        _report(progress, (len(SOLVE_SEEDS) + i) / n_steps, f"Table 3: scene {sd + seed}")
        scene = make_gf7_scene(seed=sd + seed)
        rng = np.random.default_rng(2000 + sd + seed)
        dense = _cells(scene, cell_px, cell_noise_px, rng)
        sparse = dense.iloc[rng.choice(len(dense), N_SPARSE, replace=False)].reset_index(drop=True)
        reused = panms.estimate(sparse, ms_size=scene.image("ms").size, reuse=first)
        solve = panms.estimate(dense, ms_size=scene.image("ms").size, jitter="none")
        allc = np.ones(len(dense), bool)
        rep["table3"][f"scene{sd + seed}"] = {"reuse": _evaluate(reused, dense, allc),
                                              "solve": _evaluate(solve, dense, allc), "n_sparse": N_SPARSE}
    _report(progress, (n_steps - 1) / n_steps, "cloudy scene")
    scene = make_gf7_scene(seed=CLOUDY_SEED + seed, clouds=clouds)
    cells = _cells(scene, cell_px, cell_noise_px, np.random.default_rng(3000 + seed), CLOUD_NOISE_PX)
    clear = cells["clear"].to_numpy()
    with_all = panms.estimate(cells.assign(usable=True), ms_size=scene.image("ms").size)
    without = panms.estimate(cells, ms_size=scene.image("ms").size)
    rep["cloudy"] = {"clouds": clouds, "cloudy_share": float(1 - clear.mean()),
                     "all_cells": _evaluate(with_all, cells, np.ones(len(cells), bool)),
                     "clear_cells": _evaluate(without, cells, clear)}
    rep["elapsed_s"] = round(time.perf_counter() - t0, 1)
    if verbose:
        print("Table 2 (solve mode): RMS sample / line (MS px), P(<=0.25)")
        for sc, rows in rep["table2"].items():
            for k, r in rows.items():
                print(f"  {sc:8} {k:10} {_fmt(r)}")
        print("Jitter step")
        for sc, r in rep["jitter"].items():
            n = sum(len(v) for v in r["components"].values())
            print(f"  {sc:8} piecewise {_fmt(r['piecewise'])} -> jitter {_fmt(r['jitter'])} ({n} components)")
        print("Table 3 (reuse mode, 200 sparse cells, first scene's piecewise term)")
        for sc, r in rep["table3"].items():
            print(f"  {sc:8} reuse {_fmt(r['reuse'])}   solve {_fmt(r['solve'])}")
        c = rep["cloudy"]
        print(f"Cloudy scene ({100 * c['cloudy_share']:.0f} % cloudy cells): all cells {_fmt(c['all_cells'])}, "
              f"cloudy cells left out {_fmt(c['clear_cells'])}")
    if write_files:
        write_report_json(rep, os.path.join(out_dir, "report.json"))
    _report(progress, 1.0, "done")
    return rep
