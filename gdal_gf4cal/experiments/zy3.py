"""Experiment of seed 001 (ZY-3 triplet over a GPS test field): bias compensation and stereo accuracy, Table 1.

A simulated ZY-3 three-line scene (METHODS §10: nadir 2.1 m 24576 px, forward/backward +-22 deg 3.5 m 16384 px;
platform attitude biases shared by the three cameras plus per-camera interior errors of a few pixels), each view
with its vendor-style RPC fitted from the *nominal* model. A test field of 24 GPS points (the paper's Chongming
scene) is measured in every view with ``gcp_noise_px`` noise. For each compensation model (translation,
shift-drift, affine; METHODS §4) and each number of control points 1..N (the best-spread ones, the remaining points
are checks), every view is compensated with the same control points and the check points are intersected
(METHODS §7) for the four view combinations (nadir+forward, nadir+backward, forward+backward, all three); planar
and height RMS errors against the GPS truth, in metres. ``0`` control points = the vendor RPCs as they are.

The paper's findings this reproduces: a single GCP with the translation model already removes most of the error
(the vendor RPCs' error is mostly a shift), shift-drift and affine add little; without GCPs forward+backward (the
largest intersection angle) gives the best height among the pairs and the triplet the best overall.

Built from the public API only: :func:`gdal_gf4cal.simulate.make_scene`, :func:`~gdal_gf4cal.simulate.simulate_gcps`,
:func:`gdal_gf4cal.rpc_fit.fit_rpc_from_model`, :mod:`gdal_gf4cal.compensation`, :mod:`gdal_gf4cal.intersection`.
"""
from __future__ import annotations

import os
import time
from typing import Any, Dict, Optional, Sequence

import numpy as np

from ..compensation import CompensatedRPC, fit_compensation
from ..errors import DegenerateGeometryError, GCPError
from ..gcp import write_gcps
from ..intersection import intersect, intersection_accuracy
from ..progress import report as _report
from ..report import write_report_json
from ..rpc_fit import fit_rpc_from_model
from ..simulate import make_scene, simulate_gcps

VIEWS = ("nadir", "fwd", "bwd")
COMBINATIONS = {"nadir+fwd": ("nadir", "fwd"), "nadir+bwd": ("nadir", "bwd"), "fwd+bwd": ("fwd", "bwd"),
                "nadir+fwd+bwd": ("nadir", "fwd", "bwd")}
MODELS = ("translation", "shift-drift", "affine")
N_FIELD = 24
MAX_CONTROL = 12
GCP_NOISE_PX = 0.5


def spread_order(x, y) -> np.ndarray:
    """Indices ordered for control-point selection: nearest the centroid first, then farthest-point sampling.

    The first k indices are a well-spread set of k points for every k (deterministic).
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    sx, sy = (x - x.mean()) / (x.std() or 1.0), (y - y.mean()) / (y.std() or 1.0)
    order = [int(np.argmin(sx ** 2 + sy ** 2))]
    d = np.hypot(sx - sx[order[0]], sy - sy[order[0]])
    for _ in range(x.size - 1):
        d[order] = -1.0
        k = int(np.argmax(d))
        order.append(k)
        d = np.minimum(d, np.hypot(sx - sx[k], sy - sy[k]))
    return np.array(order)


def _accuracy(models_by_view, pts_by_view, truth, combo, sel, sigma_px):
    models = [models_by_view[v] for v in combo]
    pts = np.stack([pts_by_view[v][sel] for v in combo])
    res = intersect(models, pts, sigma_px=sigma_px)
    acc = intersection_accuracy(res, *(t[sel] for t in truth))
    ok = res.converged
    return {"n_check": acc["n"], "planar_rms_m": acc["planar_rms_m"], "height_rms_m": acc["height_rms_m"],
            "ce90_m": acc.get("ce90_m"), "le90_m": acc.get("le90_m"),
            "predicted_planar_m": float(np.sqrt(np.mean(res.sigma_planar_m[ok] ** 2))) if ok.any() else None,
            "predicted_height_m": float(np.sqrt(np.mean(res.sigma_height_m[ok] ** 2))) if ok.any() else None}


def run(out_dir, *, seed: int = 0, progress=None, gcp_noise_px: float = GCP_NOISE_PX, n_field: int = N_FIELD,
        max_control: int = MAX_CONTROL, size=None, write_files: bool = True, verbose: bool = True
        ) -> Dict[str, Any]:
    """Run the ZY-3 experiment; print Table 1 and write ``out_dir/report.json`` (+ RPCs, test-field points).

    Returns the report: ``table -> model -> n_control ("0".."N") -> combination -> {planar_rms_m,
    height_rms_m, n_check, ...}``, ``no_gcp`` (= n_control 0), ``views`` (image-space bias of each RPC on the
    field), ``scene``.
    """
    t0 = time.perf_counter()
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    _report(progress, 0.0, "simulating the ZY-3 triplet")
    scene = make_scene("zy3", seed=seed, size=size)
    rpcs, fits = {}, {}
    for k, v in enumerate(VIEWS):
        _report(progress, 0.05 + 0.05 * k, f"fitting the {v} RPC")
        rpcs[v], fits[v] = fit_rpc_from_model(scene.image(v).current, size=scene.image(v).size)
    _report(progress, 0.2, "surveying the test field")
    ids, field = _test_field(scene, n_field, max_control, gcp_noise_px, seed)
    base = field["nadir"]
    truth = tuple(base[c].to_numpy(float) for c in ("lon", "lat", "h"))
    pts = {v: field[v][["sample", "line"]].to_numpy(float) for v in VIEWS}
    order = spread_order(base["sample"].to_numpy(float), base["line"].to_numpy(float))
    n_pts = len(ids)
    max_control = min(max_control, n_pts - 2)

    table: Dict[str, Dict[str, Any]] = {}
    all_sel = np.ones(n_pts, bool)
    no_gcp = {c: _accuracy(rpcs, pts, truth, combo, all_sel, gcp_noise_px) for c, combo in COMBINATIONS.items()}
    n_steps = len(MODELS) * max_control
    step = 0
    for model in MODELS:
        table[model] = {"0": no_gcp}
        for n_ctrl in range(1, max_control + 1):
            step += 1
            _report(progress, 0.25 + 0.7 * step / n_steps, f"{model}, {n_ctrl} GCPs")
            ctrl = np.zeros(n_pts, bool)
            ctrl[order[:n_ctrl]] = True
            try:
                comp = {v: CompensatedRPC(rpcs[v], fit_compensation(
                    rpcs[v], field[v].assign(role=np.where(ctrl, "control", "check")), model, robust=False))
                    for v in VIEWS}
            except (GCPError, DegenerateGeometryError) as exc:   # too few / degenerate GCPs for this model
                table[model][str(n_ctrl)] = {"skipped": str(exc).splitlines()[0]}
                continue
            table[model][str(n_ctrl)] = {c: _accuracy(comp, pts, truth, combo, ~ctrl, gcp_noise_px)
                                         for c, combo in COMBINATIONS.items()}

    views = {v: _view_bias(scene.image(v), rpcs[v], fits[v], pts[v], truth) for v in VIEWS}
    rep: Dict[str, Any] = {
        "experiment": "zy3", "seed": int(seed), "gcp_noise_px": float(gcp_noise_px), "n_field": n_pts,
        "combinations": {k: list(v) for k, v in COMBINATIONS.items()}, "models": list(MODELS),
        "no_gcp": no_gcp, "table": table, "views": views, "control_order": [ids[i] for i in order],
        "note": "planar/height RMS (m) of the check points (test-field points not used as control), intersected "
                "from the compensated RPCs of each view combination; n_control 0 = the RPCs as delivered",
    }
    if write_files:
        for v in VIEWS:
            rpcs[v].write_rpb(os.path.join(out_dir, f"zy3_{v}.RPB"), overwrite=True)
            write_gcps(field[v], os.path.join(out_dir, f"field_{v}.csv"), overwrite=True)
        rep["files"] = [f"zy3_{v}.RPB" for v in VIEWS] + [f"field_{v}.csv" for v in VIEWS] + ["report.json"]
    rep["elapsed_s"] = time.perf_counter() - t0
    if write_files:
        write_report_json(rep, os.path.join(out_dir, "report.json"))
    if verbose:
        print(format_table(rep))
    _report(progress, 1.0, "done")
    return rep


def _test_field(scene, n_field: int, max_control: int, gcp_noise_px: float, seed: int):
    """The test field: ``(ids, {view: GCP table})`` of up to ``n_field`` points seen by all three views (refused
    below ``max(4, max_control + 2)``)."""
    tables = simulate_gcps(scene, n_gcps=4 * n_field, gcp_noise_px=gcp_noise_px, check_fraction=0.0, seed=seed)
    common = set(tables[VIEWS[0]]["id"])
    for v in VIEWS[1:]:
        common &= set(tables[v]["id"])
    ids = [i for i in tables[VIEWS[0]]["id"] if i in common][:n_field]
    if len(ids) < max(4, max_control + 2):
        raise GCPError(f"only {len(ids)} test-field points are seen by all three views; use a larger scene (size) "
                       f"or fewer control points (max_control < {len(ids) - 1})")
    return ids, {v: tables[v].set_index("id").loc[ids].reset_index() for v in VIEWS}


def _view_bias(image, rpc, fit, pts, truth) -> Dict[str, Any]:
    """The delivered RPC's mean image bias on the field (px), the view's size, GSD and RPC fit error."""
    s, l = rpc.project(*truth)
    return {"mean_bias_px": {"sample": float(np.mean(pts[:, 0] - s)), "line": float(np.mean(pts[:, 1] - l))},
            "size": list(image.size), "gsd_m": float(image.gsd_m), "rpc_fit_max_px": float(fit.max_px)}


def format_table(rep: Dict[str, Any], counts: Optional[Sequence[int]] = None) -> str:
    """Table 1 layout: rows model x number of GCPs; per combination planar / height RMS (m)."""
    combos = list(rep["combinations"])
    head = f"{'model':12} {'GCPs':>4} " + " ".join(f"{c:>17}" for c in combos)
    lines = [f"ZY-3 triplet (simulated, seed {rep['seed']}): {rep['n_field']} test-field points, noise "
             f"{rep['gcp_noise_px']:g} px; planar / height RMS of check points (m)", head]
    max_n = max(int(k) for k in rep["table"][rep["models"][0]])
    counts = counts or [0] + list(range(1, max_n + 1))
    for model in rep["models"]:
        for n in counts:
            row = rep["table"][model].get(str(n))
            if row is None or "skipped" in row or (n == 0 and model != rep["models"][0]):
                continue
            cells = " ".join(f"{row[c]['planar_rms_m']:8.2f}/{row[c]['height_rms_m']:<8.2f}" for c in combos)
            lines.append(f"{(model if n else 'no GCP'):12} {n:>4} {cells}")
    return "\n".join(lines)
