"""Experiment of seed 000 (GF4 PMS look-angle calibration from the RPC alone): Tables 1-4 on simulated scenes.

Four scenes like the paper's Table 1 (PMS1-PMS4: centres, imaging times, 10240 x 10240 px, 134/142/139/215 GCPs,
GCP noise 0.6 px) are simulated with the rigorous geostationary frame model (METHODS §10). All share one camera:
the *current* camera (the camera file the RPCs were made with) and the *true* one (yaw ~10 px at the edge, scale,
translation, unmodelled radial distortion). Each scene also has its own exterior error relative to PMS1 (yaw,
pitch, roll: GF4's attitude drifts during the day), which eq. 8 removes from the internal accuracy.

* Table 2: every scene calibrated from its own GCPs, RPC-based (METHODS §5) vs the rigorous baseline (virtual points
  from the current rigorous model); look-angle difference over a 50 px grid, in pixels.
* Table 3: PMS1 (the calibration scene), its GCPs as checkpoints: initial RPC, after removing rotation +
  translation (eq. 8), recalibrated RPC from the rigorous calibration, recalibrated RPC from the RPC-based one.
* Table 4: PMS2-PMS4 recalibrated with PMS1's camera: internal accuracy (eq. 8) before, rigorous, RPC-based.

Everything is built from the public API: :func:`gdal_gf4cal.simulate.make_scene`, :func:`simulate_gcps`,
:func:`check_grid`, :func:`gdal_gf4cal.rpc_fit.fit_rpc_from_model`, :mod:`gdal_gf4cal.lookangle`,
:mod:`gdal_gf4cal.stats`, :mod:`gdal_gf4cal.report`.
"""
from __future__ import annotations

import math
import os
import time
from typing import Any, Dict, Optional

import numpy as np

from ..lookangle import calibrate_lookangle, calibrate_lookangle_rigorous, compare_lookangle, recalibrate_rpc
from ..progress import report
from ..report import plot_residuals, write_report_json, write_residuals_gpkg
from ..rpc_fit import fit_rpc_from_model
from ..simulate import make_scene
from ..simulate.models import FrameModel
from ..simulate.scene import check_grid, simulate_gcps
from ..stats import axis_stats, internal_accuracy, remove_low_order

#: The paper's Table 1: name -> (control points, imaging time, centre (lon, lat), GSD m).
TABLE1 = {
    "PMS1": (134, "14:09:52", (88.5, 32.5), 66.2),
    "PMS2": (142, "14:11:31", (92.8, 31.4), 63.4),
    "PMS3": (139, "14:13:09", (96.6, 31.3), 60.1),
    "PMS4": (215, "13:02:39", (88.9, 27.3), 62.2),
}
CALIBRATION_SCENE = "PMS1"
GCP_NOISE_PX = 0.6
DEFAULT_SEED = 2021      # the paper's images were taken on 2021-01-09


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m = np.eye(3)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _exterior_error(rng, ifov: float) -> Dict[str, float]:
    """Attitude change of a scene relative to PMS1: yaw 0.5-1.5 mrad (5-8 px at the edge), pitch/roll 1-5 px."""
    sign = lambda: rng.choice([-1.0, 1.0])  # noqa: E731
    return {"yaw_rad": float(sign() * rng.uniform(0.5e-3, 1.5e-3)),
            "pitch_rad": float(sign() * rng.uniform(1.0, 5.0) * ifov),
            "roll_rad": float(sign() * rng.uniform(1.0, 5.0) * ifov)}


def _true_model(current, camera_true, ext: Optional[Dict[str, float]]):
    """The scene's true rigorous model: the common true camera, the scene's attitude with its own error."""
    R = np.asarray(current.rotation, dtype=float)
    if ext:
        R = R @ _rot(2, ext["yaw_rad"]) @ _rot(0, ext["pitch_rad"]) @ _rot(1, ext["roll_rad"])
    return FrameModel(camera_true, current.position, R, height_range=current.height_range,
                      name=f"{getattr(current, 'name', 'gf4')} true")


def _pair(res_s, res_l, keys):
    sa, la = axis_stats(res_s), axis_stats(res_l)
    return {"line": {k: la[k] for k in keys}, "sample": {k: sa[k] for k in keys}}


def _internal(gcps, sample_pred, line_pred, keys=("mean", "rms")):
    ia = internal_accuracy(gcps["sample"].to_numpy(float), gcps["line"].to_numpy(float), sample_pred, line_pred)
    return ({"line": {k: ia["line"][k] for k in keys}, "sample": {k: ia["sample"][k] for k in keys}},
            {"theta_rad": ia["theta_rad"], "ds_px": ia["ds"], "dl_px": ia["dl"]})


def _sci(x: float) -> str:
    return f"{x: .1e}"


def format_tables(rep: Dict[str, Any]) -> str:
    """The paper's Tables 1-4 as text (pixels)."""
    out = ["Table 1  Simulated GF4 PMS scenes (paper's values in brackets)",
           f"{'Image':6} {'GCPs':>5} {'time':>9} {'centre':>16} {'GSD / m':>15} {'size / px':>13}"]
    for name, row in rep["table1"].items():
        out.append(f"{name:6} {row['gcps']:>5} {row['time']:>9} {row['center'][0]:6.1f}E {row['center'][1]:5.1f}N "
                   f"{row['gsd_m']:7.1f} ({row['paper_gsd_m']:.1f}) {row['size'][0]:>6}x{row['size'][1]}")
    out += ["", "Table 2  Look angles: RPC-based vs rigorous calibration, 50 px grid (pixel)",
            f"{'Image':6} {'Mean line':>10} {'Mean samp':>10} {'RMS line':>10} {'RMS samp':>10} {'Max line':>10} "
            f"{'Max samp':>10}"]
    for name, t in rep["table2"].items():
        out.append(f"{name:6} " + " ".join(_sci(t[a][k]).rjust(10) for k in ("mean", "rms", "max")
                                           for a in ("line", "sample")))
    labels = {"initial": "Initial RPC imaging model", "low_order_removed": "After correcting the low-order error",
              "rigorous": "Calibration based on physical model", "rpc": "Calibration based on RPC model"}
    out += ["", f"Table 3  {CALIBRATION_SCENE} geometric accuracy before and after calibration (pixel)",
            f"{'Processing stage':38} {'line: Mean':>10} {'RMS':>6} {'RMSE':>6}   {'sample: Mean':>12} {'RMS':>6} "
            f"{'RMSE':>6}"]
    for key, label in labels.items():
        t = rep["table3"][key]
        out.append(f"{label:38} {t['line']['mean']:10.2f} {t['line']['rms']:6.2f} {t['line']['std']:6.2f}   "
                   f"{t['sample']['mean']:12.2f} {t['sample']['rms']:6.2f} {t['sample']['std']:6.2f}")
    out += ["", "Table 4  Internal accuracy of the independent scenes with the calibration of " + CALIBRATION_SCENE
            + " (pixel)",
            f"{'':6} {'Before calibration':^27} | {'Physical-model calibration':^27} | {'RPC-model calibration':^27}",
            f"{'Image':6} " + " | ".join(f"{'Mean s':>6} {'l':>5} {'RMS s':>7} {'l':>5}" for _ in range(3))]
    for name, t in rep["table4"].items():
        out.append(f"{name:6} " + " | ".join(
            f"{t[c]['sample']['mean']:6.2f} {t[c]['line']['mean']:5.2f} {t[c]['sample']['rms']:7.2f} "
            f"{t[c]['line']['rms']:5.2f}" for c in ("before", "rigorous", "rpc")))
    cg = rep.get("check_grid")
    if cg:
        out += ["", "Dense check grid vs the true model, recalibrated RPCs from the calibration of "
                f"{CALIBRATION_SCENE} (pixel RMS; eq. 8 applied to the other scenes)"]
        for name, t in cg.items():
            out.append(f"{name:6} before {t['before']['sample']['rms']:6.2f} / {t['before']['line']['rms']:5.2f}   "
                       f"rpc {t['rpc']['sample']['rms']:6.3f} / {t['rpc']['line']['rms']:5.3f}   "
                       f"(least-squares floor {t['floor_px']:.3f})")
    return "\n".join(out)


def run(out_dir, *, seed: int = DEFAULT_SEED, progress=None, gcp_noise_px: float = GCP_NOISE_PX,
        n_gcps: Optional[Dict[str, int]] = None, size=None, write_files: bool = True, verbose: bool = True
        ) -> Dict[str, Any]:
    """Run the GF4 experiment; print Tables 1-4 and write ``out_dir/report.json`` (+ cameras, RPCs, Fig. 5 plots).

    Parameters
    ----------
    out_dir : output folder (created).
    seed : seeds every random draw (camera errors, terrain, attitude drift, GCPs).
    progress : ``progress(fraction, message)``.
    gcp_noise_px : GCP measurement noise per axis (paper: matching accuracy ~0.6 px).
    n_gcps : GCPs per scene (default: the paper's Table 1 counts).
    size : optional (W, H) crop of the detector array (tests); default the full 10240 x 10240.
    write_files, verbose : write the side files / print the tables.

    Returns
    -------
    dict : the report (``table1`` ... ``table4``, ``check_grid``, ``calibration``, ``truth``).
    """
    t0 = time.perf_counter()
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    counts = {k: v[0] for k, v in TABLE1.items()}
    counts.update(n_gcps or {})
    names = list(TABLE1)
    scenes, camera_current, camera_true, truth_camera = _simulate_scenes(names, counts, seed=seed, size=size,
                                                                         gcp_noise_px=gcp_noise_px,
                                                                         progress=progress)
    table1 = {name: {"gcps": int(len(s["gcps"])), "time": s["time"], "center": list(s["center"]),
                     "gsd_m": float(s["image"].gsd_m), "paper_gsd_m": TABLE1[name][3],
                     "size": list(s["image"].size)} for name, s in scenes.items()}

    table2, calib = _table2(scenes, camera_current, progress)

    # ---- Table 3: the calibration scene.
    report(progress, 0.68, f"recalibrating {CALIBRATION_SCENE}")
    cal_rpc, cal_rig = calib[CALIBRATION_SCENE]["rpc"], calib[CALIBRATION_SCENE]["rigorous"]
    new_rpcs: Dict[str, Dict[str, Any]] = {}
    new_rpcs[CALIBRATION_SCENE] = _recalibrated(scenes[CALIBRATION_SCENE], camera_current, cal_rpc, cal_rig)
    table3 = _table3(scenes[CALIBRATION_SCENE], new_rpcs[CALIBRATION_SCENE])

    # ---- Table 4: the other scenes with the calibration scene's camera; internal accuracy (eq. 8).
    table4, eq8, check = {}, {}, {}
    for i, name in enumerate(names):
        report(progress, 0.72 + 0.2 * i / len(names), f"recalibrating {name}")
        s = scenes[name]
        if name != CALIBRATION_SCENE:
            new_rpcs[name] = _recalibrated(s, camera_current, cal_rpc, cal_rig)
            g = s["gcps"]
            glon, glat, gh = (g[c].to_numpy(float) for c in ("lon", "lat", "h"))
            cols = {"before": _internal(g, *s["rpc"].project(glon, glat, gh)),
                    "rigorous": _internal(g, *new_rpcs[name]["rigorous"].project(glon, glat, gh)),
                    "rpc": _internal(g, *new_rpcs[name]["rpc"].project(glon, glat, gh))}
            table4[name] = {k: v[0] for k, v in cols.items()}
            eq8[name] = {k: v[1] for k, v in cols.items()}
        check[name] = _check_grid_entry(name, s, new_rpcs[name]["rpc"], new_rpcs[name]["rigorous"])
        n_used = int(cal_rpc.n_control - cal_rpc.n_outliers)
        check[name]["floor_px"] = gcp_noise_px * math.sqrt(10.0 / n_used)

    rep = _report_dict(seed=seed, gcp_noise_px=gcp_noise_px, scenes=scenes, calib=calib, new_rpcs=new_rpcs,
                       tables=(table1, table2, table3, table4, eq8, check), truth_camera=truth_camera,
                       camera_true=camera_true, camera_current=camera_current)
    report(progress, 0.94, "writing outputs")
    outputs = {"report": os.path.join(out_dir, "report.json")}
    if write_files:
        outputs.update(_write_side_files(out_dir, scenes, new_rpcs, calib, camera_current, camera_true,
                                         plot_residuals, write_residuals_gpkg))
    rep["outputs"] = outputs
    rep["elapsed_s"] = time.perf_counter() - t0
    write_report_json(rep, outputs["report"])
    if verbose:
        print(format_tables(rep))
        print(f"\nwrote {outputs['report']} ({rep['elapsed_s']:.1f} s)")
    report(progress, 1.0, "done")
    return rep


def _simulate_scenes(names, counts, *, seed, size, gcp_noise_px, progress):
    """Scenes: one camera (current + true), per-scene attitude drift, RPC from the current model, GCPs, check grid.

    Returns ``(scenes, camera_current, camera_true, truth_camera)``."""
    rng = np.random.default_rng(seed)
    scenes: Dict[str, Dict[str, Any]] = {}
    camera_true = camera_current = None
    for i, name in enumerate(names):
        report(progress, 0.02 + 0.4 * i / len(names), f"simulating {name}")
        n, t_img, center, _ = TABLE1[name]
        sc = make_scene("gf4", seed=seed + i, center=center, size=size)
        im = sc.image("")
        if camera_true is None:
            camera_current, camera_true = im.current.camera, im.true.camera
            truth_camera = im.errors
        elif not (np.array_equal(im.current.camera.x, camera_current.x)
                  and np.array_equal(im.current.camera.y, camera_current.y)):
            raise RuntimeError("the simulator's current GF4 camera differs between scenes")
        ext = None if name == CALIBRATION_SCENE else _exterior_error(rng, im.errors["ifov_rad"])
        im.true = _true_model(im.current, camera_true, ext)      # the GCPs and the check grid see this truth
        rpc, fit_rep = fit_rpc_from_model(im.current, progress=None)
        gcps = simulate_gcps(sc, n_gcps=counts[name], gcp_noise_px=gcp_noise_px, check_fraction=0.0,
                             seed=seed * 31 + i)[""]
        grid = check_grid(im, sc.dem, n=41)
        scenes[name] = {"scene": sc, "image": im, "rpc": rpc, "rpc_fit": fit_rep, "gcps": gcps, "grid": grid,
                        "exterior_error": ext, "time": t_img, "center": center}
    return scenes, camera_current, camera_true, truth_camera


def _table2(scenes, camera_current, progress):
    """Table 2: each scene calibrated from its own GCPs, RPC-based vs rigorous; ``(table2, calibrations)``."""
    table2, calib = {}, {}
    for i, (name, s) in enumerate(scenes.items()):
        report(progress, 0.45 + 0.2 * i / len(scenes), f"calibrating {name}")
        res_rpc = calibrate_lookangle(s["rpc"], s["gcps"], camera_current)
        res_rig = calibrate_lookangle_rigorous(s["image"].current, s["gcps"])
        d = compare_lookangle(res_rpc.camera, res_rig.camera, grid_px=50)
        table2[name] = {"line": d["line"], "sample": d["sample"]}
        calib[name] = {"rpc": res_rpc, "rigorous": res_rig}
    return table2, calib


def _recalibrated(s, camera_current, cal_rpc, cal_rig) -> Dict[str, Any]:
    """The scene's RPC recalibrated for the RPC-calibrated camera, and refitted from the rigorous model with the
    rigorously calibrated camera (and their fit reports)."""
    rpc_new, rep_new = recalibrate_rpc(s["rpc"], camera_current, cal_rpc.camera)
    rpc_rig, rep_rig = fit_rpc_from_model(s["image"].current.with_camera(cal_rig.camera))
    return {"rpc": rpc_new, "rpc_fit": rep_new, "rigorous": rpc_rig, "rigorous_fit": rep_rig}


def _table3(s1, new1) -> Dict[str, Any]:
    """Table 3: the calibration scene's GCP residuals: initial, low order removed, rigorous, RPC-based."""
    g1 = s1["gcps"]
    lon, lat, h = (g1[c].to_numpy(float) for c in ("lon", "lat", "h"))
    ms, ml = g1["sample"].to_numpy(float), g1["line"].to_numpy(float)
    keys3 = ("mean", "rms", "std")
    s0, l0 = s1["rpc"].project(lon, lat, h)
    lo = internal_accuracy(ms, ml, s0, l0)
    sr, lr = new1["rigorous"].project(lon, lat, h)
    sn, ln = new1["rpc"].project(lon, lat, h)
    return {"initial": _pair(ms - s0, ml - l0, keys3),
            "low_order_removed": {"line": {k: lo["line"][k] for k in keys3},
                                  "sample": {k: lo["sample"][k] for k in keys3}},
            "rigorous": _pair(ms - sr, ml - lr, keys3),
            "rpc": _pair(ms - sn, ml - ln, keys3)}


def _check_grid_entry(name: str, s, rpc_new, rpc_rig) -> Dict[str, Any]:
    """Dense check grid against the true model (absolute for the calibration scene, eq. 8 for scenes with
    attitude drift): before, rigorous, RPC-based."""
    grid = s["grid"]
    gl, ga, gh = (grid[c].to_numpy(float) for c in ("lon", "lat", "h"))
    st, lt = grid["sample_true"].to_numpy(float), grid["line_true"].to_numpy(float)
    entry = {}
    for key, model in (("before", s["rpc"]), ("rigorous", rpc_rig), ("rpc", rpc_new)):
        ps, pl = model.project(gl, ga, gh)
        if name == CALIBRATION_SCENE:
            entry[key] = _pair(st - ps, lt - pl, ("mean", "rms", "max"))
        else:
            ia = internal_accuracy(st, lt, ps, pl)
            entry[key] = {"line": {k: ia["line"][k] for k in ("mean", "rms", "max")},
                          "sample": {k: ia["sample"][k] for k in ("mean", "rms", "max")}}
    return entry


def _report_dict(*, seed, gcp_noise_px, scenes, calib, new_rpcs, tables, truth_camera, camera_true,
                 camera_current) -> Dict[str, Any]:
    """The experiment's report: Tables 1-4, the check grid, the calibrations, the RPC fits and the truth."""
    table1, table2, table3, table4, eq8, check = tables
    cal_rpc = calib[CALIBRATION_SCENE]["rpc"]
    return {
        "experiment": "gf4 look-angle calibration from the RPC alone (seed 000, METHODS §5)",
        "seed": seed, "gcp_noise_px": gcp_noise_px, "calibration_scene": CALIBRATION_SCENE,
        "units": "pixels", "table1": table1, "table2": table2, "table3": table3, "table4": table4,
        "table4_removed_rotation_translation": eq8,
        "check_grid": check,
        "calibration": {name: {"rpc": {"iterations": c["rpc"].iterations, "sigma0": c["rpc"].sigma0,
                                       "n_outliers": c["rpc"].n_outliers, "history": c["rpc"].history,
                                       "condition_number": c["rpc"].condition_number},
                               "rigorous": {"iterations": c["rigorous"].iterations,
                                            "n_outliers": c["rigorous"].n_outliers}}
                        for name, c in calib.items()},
        "rpc_fit_max_px": {name: {"current": s["rpc_fit"].max_px, "recalibrated": new_rpcs[name]["rpc_fit"].max_px}
                           for name, s in scenes.items()},
        "truth": {"camera_errors": truth_camera,
                  "exterior_error_vs_" + CALIBRATION_SCENE: {n: s["exterior_error"] for n, s in scenes.items()}},
        "camera_change_px": {"true_vs_current": {k: v for k, v in compare_lookangle(camera_true, camera_current).items()
                                                 if k in ("line", "sample")},
                             "rpc_calibrated_vs_true": {k: v for k, v in
                                                        compare_lookangle(cal_rpc.camera, camera_true).items()
                                                        if k in ("line", "sample")}},
    }


def _write_side_files(out_dir, scenes, new_rpcs, calib, camera_current, camera_true, plot_residuals,
                      write_residuals_gpkg) -> Dict[str, str]:
    """Cameras, current and recalibrated RPCs of every scene, the calibration scene's residuals (Fig. 5)."""
    out = {}
    for key, cam in (("camera_current", camera_current), ("camera_true", camera_true),
                     ("camera_new", calib[CALIBRATION_SCENE]["rpc"].camera),
                     ("camera_new_rigorous", calib[CALIBRATION_SCENE]["rigorous"].camera)):
        out[key] = cam.to_json(os.path.join(out_dir, f"{key}.json"), overwrite=True)
    for name, s in scenes.items():
        out[f"{name}_rpb"] = str(s["rpc"].write_rpb(os.path.join(out_dir, f"{name}.RPB"), overwrite=True))
        out[f"{name}_recalibrated_rpb"] = str(new_rpcs[name]["rpc"].write_rpb(
            os.path.join(out_dir, f"{name}_recalibrated.RPB"), overwrite=True))
    res = calib[CALIBRATION_SCENE]["rpc"]
    g = res.gcps.copy()
    s = scenes[CALIBRATION_SCENE]
    # Fig. 5 (c, d): relative residuals after removing rotation + translation, before / after calibration.
    for tag, (cs, cl) in (("before", ("res_sample_before", "res_line_before")),
                          ("after", ("res_sample_after", "res_line_after"))):
        g[f"rel_sample_{tag}"], g[f"rel_line_{tag}"] = _remove_low_order(g, cs, cl)
    size = tuple(s["image"].size)
    out["residuals_png"] = str(plot_residuals(g, os.path.join(out_dir, "residuals.png"), image_size=size,
                                              title=f"{CALIBRATION_SCENE}: absolute residuals (Fig. 5 a, b)"))
    out["residuals_internal_png"] = str(plot_residuals(
        g, os.path.join(out_dir, "residuals_internal.png"), before=("rel_sample_before", "rel_line_before"),
        after=("rel_sample_after", "rel_line_after"), image_size=size,
        title=f"{CALIBRATION_SCENE}: relative residuals, rotation + translation removed (Fig. 5 c, d)"))
    out["residuals_gpkg"] = str(write_residuals_gpkg(g, os.path.join(out_dir, "residuals.gpkg"), overwrite=True,
                                                     title=f"{CALIBRATION_SCENE} look-angle calibration"))
    return out


def _remove_low_order(g, cs, cl):
    meas_s, meas_l = g["sample"].to_numpy(float), g["line"].to_numpy(float)
    return remove_low_order(meas_s, meas_l, meas_s - g[cs].to_numpy(float), meas_l - g[cl].to_numpy(float))
