"""Experiment of seed 003 (Jilin1-KF01A wide-field camera): block calibration of one group and its validation,
Tables 3-6 (METHODS §8; the paper's tables are lost, these follow its prose).

A simulated Jilin-1 group (METHODS §10: 4 staggered CCDs x pan + 4 MS bands, crops of ``size`` pan px per CCD;
interior truth per CCD and band, exterior truth per group) is calibrated with ``gf4cal block-adjust`` (GCPs
``gcp_noise_px``, tie points 0.1 px, blue the reference band). Then:

* **Table 3** calibration accuracy per CCD and band: check-GCP residuals across (sample) and along (line) track
  after the calibration, and the error of the recalibrated RPC against the true model on a grid (px of the image);
* **Table 4** band-to-band registration against the blue image of each CCD (true ground points, MS px), before and
  after;
* **Table 5** ``n_orbits`` other orbits of the same camera and group (their own attitude error, N(0, 3.6") per axis)
  recalibrated with ``calibration.json`` and no control: CE90 of the ground error (m) of every GCP's true image
  point, against the CE90 the orbits' attitude errors alone imply (their true models with and without the error);
  band-to-band from their tie points (largest mean offset and RMS, MS px, matching noise included);
* **Table 6** ``n_scenes`` other scenes with 5 control GCPs each (the group's exterior re-estimated, interiors
  calibrated) and every other GCP as a check point: planar RMS (m).

Paper: calibration < 0.3 px, band-to-band < 0.3 px, seams removed, 10 orbits without control CE90 < 20 m, 5 GCPs per
scene < 2 m. Built from the public API: :func:`gdal_gf4cal.simulate.write_scene`,
:func:`gdal_gf4cal.workflows.block_adjust`, :func:`gdal_gf4cal.workflows.apply_block_calibration`,
:func:`gdal_gf4cal.block.adjust_block`.
"""
from __future__ import annotations

import os
from typing import Any, Dict, List

import numpy as np

from ..progress import report as _report

MS_BANDS = ("blue", "green", "red", "nir")
REF = tuple(f"ccd{k}_blue" for k in range(1, 5))
NAMES = REF + tuple(f"ccd{k}" for k in range(1, 5)) + tuple(f"ccd{k}_{b}" for k in range(1, 5) for b in MS_BANDS[1:])
BANDS_OF = {n: n.split("_")[0] + "_blue" for n in NAMES if n not in REF}


def _scene(out_dir, tag, seed, size, orbit_seed=None, n_gcps=30, gcp_noise_px=0.2):
    from ..simulate import write_scene
    d = os.path.join(out_dir, "scenes", tag)
    write_scene("jl1", d, seed=seed, size=size, n_gcps=n_gcps, gcp_noise_px=gcp_noise_px, check_grid_n=5,
                reference_ortho=False, options=None if orbit_seed is None else {"orbit_seed": orbit_seed})
    return d


def _images(d):
    return [os.path.join(d, n, "scene.tif") for n in NAMES]


def _grid(size, n=(15, 7)):
    W, H = size
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(1, W - 1, n[0]), np.linspace(1, H - 1, n[1])))
    return S, L


def _rms(e) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(e) ** 2, axis=0))))


def _ground_errors_m(models, table, columns=("sample", "line")):
    """Planar ground error (m) of each GCP row: its image point (``columns``: measured, or ``truth_sample,
    truth_line`` for the model's error alone) localised at its height with the image's model, against its ground
    coordinates."""
    from ..geodesy import metres_per_degree
    out = []
    for n, g in table.groupby("image_id"):
        lon, lat = models[n].localize(g[columns[0]].to_numpy(float), g[columns[1]].to_numpy(float),
                                      g["h"].to_numpy(float))
        mx, my = metres_per_degree(g["lat"].to_numpy(float))
        out.append(np.hypot((np.asarray(lon) - g["lon"].to_numpy(float)) * mx,
                            (np.asarray(lat) - g["lat"].to_numpy(float)) * my))
    return np.concatenate(out)


def _implied_errors_m(truth_cal, truth_orbit, table):
    """Ground error (m) the orbit's attitude error alone implies at each GCP: its true image point in the orbit
    scene localised with the calibration scene's true model (a perfect calibration)."""
    from ..geodesy import metres_per_degree
    out = []
    for n, g in table.groupby("image_id"):
        lon, lat, h = (g[c].to_numpy(float) for c in ("lon", "lat", "h"))
        s, l = truth_orbit.image(n).true.project(lon, lat, h)
        lo, la = truth_cal.image(n).true.localize(s, l, h)
        mx, my = metres_per_degree(lat)
        out.append(np.hypot((np.asarray(lo) - lon) * mx, (np.asarray(la) - lat) * my))
    return np.concatenate(out)


def run(out_dir, *, seed: int = 3, size=(512, 256), n_orbits: int = 10, n_scenes: int = 5,
        gcp_noise_px: float = 0.2, progress=None) -> Dict[str, Any]:
    """Run the Jilin-1 experiment; print Tables 3-6 and write ``out_dir/report.json`` (module docstring)."""
    import pandas as pd
    from ..block import adjust_block, read_calibration, seam_offsets
    from ..dem import DEM
    from ..report import write_report_json
    from ..rpc import RPCModel
    from ..simulate import make_scene
    from ..stats import ce90
    from ..workflows import apply_block_calibration, block_adjust

    size = tuple(int(v) for v in size)
    steps = 2 + n_orbits + n_scenes
    _report(progress, 0.0, "calibration scene")
    cal_dir = _scene(out_dir, "calibration", seed, size, gcp_noise_px=gcp_noise_px)
    obs = os.path.join(cal_dir, "observations.csv")
    blk = os.path.join(out_dir, "block")
    rep_b = block_adjust(_images(cal_dir), dem=os.path.join(cal_dir, "dem.tif"), gcps=obs, ties=obs,
                         bands_of=BANDS_OF, out=blk, overwrite=True)
    cal = read_calibration(os.path.join(blk, "calibration.json"))
    truth = make_scene("jl1", seed=seed, size=size)
    new = {n: RPCModel.from_file(os.path.join(blk, f"{n}.RPB")) for n in NAMES}
    old = {n: RPCModel.from_file(os.path.join(cal_dir, n, "scene.RPB")) for n in NAMES}
    # Table 3
    t3 = {}
    for n in NAMES:
        im = truth.image(n)
        S, L = _grid(im.size)
        lon, lat, h = im.true.localize_dem(S, L, truth.dem)
        chk = (rep_b["images"][n]["gcps"] or {}).get("check", {}).get("after", {})
        t3[n] = {"check_sample_rms_px": chk.get("sample", {}).get("rms"), "check_line_rms_px": chk.get("line", {}).get("rms"),
                 "check_sample_max_px": chk.get("sample", {}).get("max"), "check_line_max_px": chk.get("line", {}).get("max"),
                 "truth_rms_px_before": _rms(np.stack(old[n].project(lon, lat, h)) - np.stack([S, L])),
                 "truth_rms_px_after": _rms(np.stack(new[n].project(lon, lat, h)) - np.stack([S, L]))}
    # Table 4
    t4 = {}
    for b, r in BANDS_OF.items():
        ib, ir = truth.image(b), truth.image(r)
        fb = 0.25 if "_" not in b else 1.0
        S, L = _grid(ib.size)
        lon, lat, h = ib.true.localize_dem(S, L, truth.dem)
        tb, tr = np.stack([S, L]), np.stack(ir.true.project(lon, lat, h))
        t4[b] = {tag: _rms((np.stack(m[b].project(lon, lat, h)) - tb) * fb - (np.stack(m[r].project(lon, lat, h)) - tr))
                 for tag, m in (("before_ms_px", old), ("after_ms_px", new))}
    # Table 5
    t5: List[Dict[str, Any]] = []
    meas_all, impl_all = [], []
    for k in range(n_orbits):
        _report(progress, (1 + k) / steps, f"orbit {k + 1} of {n_orbits}")
        d = _scene(out_dir, f"orbit{k + 1:02d}", seed, size, orbit_seed=k + 1, gcp_noise_px=gcp_noise_px)
        app = os.path.join(out_dir, "applied", f"orbit{k + 1:02d}")
        apply_block_calibration(cal, _images(d), app, overwrite=True)
        models = {n: RPCModel.from_file(os.path.join(app, f"{n}.RPB")) for n in NAMES}
        orig = {n: RPCModel.from_file(os.path.join(d, n, "scene.RPB")) for n in NAMES}
        tab = pd.read_csv(os.path.join(d, "observations.csv"), dtype={"point_id": str})
        g = tab[tab["kind"] == "gcp"]
        meas = _ground_errors_m(models, g, ("truth_sample", "truth_line"))     # the models' error, no GCP noise
        impl = _implied_errors_m(truth, make_scene("jl1", seed=seed, size=size, options={"orbit_seed": k + 1}), g)
        meas_all.append(meas)
        impl_all.append(impl)
        dem = DEM.from_file(os.path.join(d, "dem.tif"))
        ties = tab[tab["kind"] == "tie"].assign(outlier=False)
        b2b = seam_offsets(ties, orig, models, dem, list((r, b) for b, r in BANDS_OF.items()))
        after = [dict(s["after"], scale=0.25 if "_" not in s["pair"][1] else 1.0) for s in b2b if s.get("n")]
        t5.append({"orbit": k + 1, "ce90_m": ce90(meas), "implied_ce90_m": ce90(impl),
                   "band_to_band_mean_px": float(np.max([a["mean_px"] * a["scale"] for a in after])) if after else None,
                   "band_to_band_rms_px": float(np.sqrt(np.mean([(a["rms_px"] * a["scale"]) ** 2 for a in after])))
                   if after else None})
    # Table 6
    t6: List[Dict[str, Any]] = []
    for k in range(n_scenes):
        _report(progress, (1 + n_orbits + k) / steps, f"scene {k + 1} of {n_scenes} with 5 GCPs")
        d = _scene(out_dir, f"scene{k + 1}", seed, size, orbit_seed=101 + k, n_gcps=15, gcp_noise_px=0.1 / 0.75)
        tab = pd.read_csv(os.path.join(d, "observations.csv"), dtype={"point_id": str})
        g = tab[tab["kind"] == "gcp"].copy()
        pts = g.groupby("point_id")[["lon", "lat"]].first()
        order = np.argsort(np.hypot(pts["lon"] - pts["lon"].mean(), pts["lat"] - pts["lat"].mean()).to_numpy())[::-1]
        control = set(pts.index[order[:4]]) | {pts.index[order[-1]]}          # 4 far apart + the central one
        g["role"] = np.where(g["point_id"].isin(control), "control", "check")
        models = {n: RPCModel.from_file(os.path.join(d, n, "scene.RPB")) for n in NAMES}
        est = adjust_block(g, models, DEM.from_file(os.path.join(d, "dem.tif")), calibration=cal)
        from ..block import corrected_model
        corr = {n: corrected_model(est, n, models[n]) for n in NAMES}
        chk = g[g["role"] == "check"]
        e = _ground_errors_m(corr, chk)
        t6.append({"scene": k + 1, "n_control": len(control), "n_check": int(chk["point_id"].nunique()),
                   "check_planar_rms_m": float(np.sqrt(np.mean(e ** 2))), "check_max_m": float(np.max(e))})
    meas_all = np.concatenate(meas_all) if meas_all else np.zeros(0)
    impl_all = np.concatenate(impl_all) if impl_all else np.zeros(0)
    rep = {"experiment": "jl1", "seed": seed, "size": list(size), "gcp_noise_px": gcp_noise_px,
           "table3_calibration": t3, "table4_band_to_band": t4,
           "seams": rep_b["seams"], "stages": rep_b["stages"],
           "table5_orbits": {"orbits": t5, "ce90_m": ce90(meas_all) if meas_all.size else None,
                             "implied_ce90_m": ce90(impl_all) if impl_all.size else None},
           "table6_scenes": t6, "paper": {"calibration_px": 0.3, "band_to_band_px": 0.3, "ce90_m": 20.0,
                                          "check_rms_m": 2.0}}
    write_report_json(rep, os.path.join(out_dir, "report.json"))
    print(format_tables(rep))
    _report(progress, 1.0, "done")
    return rep


def format_tables(rep: Dict[str, Any]) -> str:
    def f(v, fmt=".3f"):
        return "-" if v is None else format(v, fmt)
    lines = ["Table 3 - calibration accuracy per CCD and band (px of the image)",
             f"{'image':<12} {'check across rms':>16} {'check along rms':>15} {'truth before':>12} {'truth after':>11}"]
    for n, v in rep["table3_calibration"].items():
        lines.append(f"{n:<12} {f(v['check_sample_rms_px']):>16} {f(v['check_line_rms_px']):>15} "
                     f"{f(v['truth_rms_px_before']):>12} {f(v['truth_rms_px_after']):>11}")
    lines += ["", "Table 4 - band-to-band registration against blue (MS px, true ground points)",
              f"{'image':<12} {'before':>8} {'after':>8}"]
    for n, v in rep["table4_band_to_band"].items():
        lines.append(f"{n:<12} {f(v['before_ms_px']):>8} {f(v['after_ms_px']):>8}")
    t5 = rep["table5_orbits"]
    lines += ["", "Table 5 - other orbits, calibration applied, no control",
              f"{'orbit':>5} {'CE90 m':>8} {'implied':>8} {'b2b mean px':>12} {'b2b rms px':>11}"]
    for o in t5["orbits"]:
        lines.append(f"{o['orbit']:>5} {f(o['ce90_m'], '.2f'):>8} {f(o['implied_ce90_m'], '.2f'):>8} "
                     f"{f(o['band_to_band_mean_px']):>12} {f(o['band_to_band_rms_px']):>11}")
    lines.append(f"{'all':>5} {f(t5['ce90_m'], '.2f'):>8} {f(t5['implied_ce90_m'], '.2f'):>8}")
    lines += ["", "Table 6 - scenes with 5 GCPs (exterior re-estimated), check points",
              f"{'scene':>5} {'checks':>6} {'planar rms m':>12} {'max m':>7}"]
    for s in rep["table6_scenes"]:
        lines.append(f"{s['scene']:>5} {s['n_check']:>6} {f(s['check_planar_rms_m'], '.2f'):>12} "
                     f"{f(s['check_max_m'], '.2f'):>7}")
    return "\n".join(lines)
