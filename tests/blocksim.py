"""Shared helpers of the block-calibration tests (METHODS §8): a seeded simulated Jilin-1 group written to disk once
per process, the ``gf4cal block-adjust`` arguments for it, and its accuracy against the simulator's truth."""
from __future__ import annotations

import functools
import json
import os

import numpy as np

SEED = 3
SIZE = (512, 256)
MS_BANDS = ("blue", "green", "red", "nir")
REF = [f"ccd{k}_blue" for k in range(1, 5)]
NAMES = REF + [f"ccd{k}" for k in range(1, 5)] + [f"ccd{k}_{b}" for k in range(1, 5) for b in MS_BANDS[1:]]


@functools.lru_cache(maxsize=4)
def block_scene(root: str, tie_outlier_fraction: float = 0.0, seed: int = SEED, size=SIZE, center=None,
                orbit_seed=None) -> str:
    """Write the group (30 GCPs per image at 0.2 px, 40 ties per overlap and per band pair at 0.1 px) once.
    ``center``: another group's place (e.g. the next group, 23 km across track); ``orbit_seed``: another orbit of
    the same camera and group (per-orbit attitude error)."""
    from gdal_gf4cal.simulate import write_scene
    d = os.path.join(root, f"jl1_{seed}_{size[0]}x{size[1]}_{tie_outlier_fraction:g}_{center}_{orbit_seed}")
    if not os.path.exists(os.path.join(d, "observations.csv")):
        write_scene("jl1", d, seed=seed, size=size, center=center, n_gcps=30, gcp_noise_px=0.2, check_grid_n=5,
                    reference_ortho=False, observation_options={"tie_outlier_fraction": tie_outlier_fraction},
                    options=None if orbit_seed is None else {"orbit_seed": orbit_seed})
    return d


def image_path(d: str, name: str) -> str:
    return os.path.join(d, name, "scene.tif")


def cli_args(d: str, names=NAMES, bands=True):
    """``block-adjust`` arguments: the blue CCDs in order, then the other bands tied to their CCD's blue image."""
    args = [image_path(d, n) for n in names]
    if bands:
        args += ["--bands-of"] + [f"{n}={n.split('_')[0]}_blue" for n in names if n not in REF]
    obs = os.path.join(d, "observations.csv")
    return args + ["--dem", os.path.join(d, "dem.tif"), "--gcps", obs, "--ties", obs]


@functools.lru_cache(maxsize=3)
def truth_scene(seed: int = SEED, size=SIZE, orbit_seed=None):  # positional: one cache key per scene
    from gdal_gf4cal.simulate import make_scene
    return make_scene("jl1", seed=seed, size=tuple(size), options=None if orbit_seed is None else
                      {"orbit_seed": orbit_seed})


def _grid(im, n=(15, 7), s_range=None):
    W, H = im.size
    s0, s1 = s_range if s_range is not None else (1.0, W - 1.0)
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(s0, s1, n[0]), np.linspace(1.0, H - 1.0, n[1])))
    return S, L


def errors_vs_truth(out: str, d: str, names=NAMES, orbit_seed=None):
    """Per image: (sample, line) error of the recalibrated RPC (``out/<name>.RPB``) against the true model at true
    ground points of a grid (px of the image), and the same for the original RPC (``before``)."""
    from gdal_gf4cal.rpc import RPCModel
    scene = truth_scene(SEED, SIZE, orbit_seed)
    res = {}
    for name in names:
        im = scene.image(name)
        S, L = _grid(im)
        lon, lat, h = im.true.localize_dem(S, L, scene.dem)
        new = RPCModel.from_file(os.path.join(out, f"{name}.RPB"))
        old = RPCModel.from_file(os.path.join(d, name, "scene.RPB"))
        res[name] = {"after": np.stack(new.project(lon, lat, h)) - np.stack([S, L]),
                     "before": np.stack(old.project(lon, lat, h)) - np.stack([S, L])}
    return res


def rms(e) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(e) ** 2, axis=0))))


def true_seams(out: str, d: str, orbit_seed=None, seed=SEED, size=SIZE, bands=("pan",) + MS_BANDS):
    """Per adjacent pair of one band: largest |seam| (px of the band) in the overlap after and before: the relative
    error of the two images' models at true ground points (what a mosaic shows)."""
    from gdal_gf4cal.rpc import RPCModel
    scene = truth_scene(seed, tuple(size), orbit_seed)
    out_seams = {}
    for band in bands:
        nm = [f"ccd{k}" if band == "pan" else f"ccd{k}_{band}" for k in range(1, 5)]
        for a, b in zip(nm[:-1], nm[1:]):
            ia, ib = scene.image(a), scene.image(b)
            ov = float(ib.info["overlap_pan_px"]) / (1 if band == "pan" else 4)
            S, L = _grid(ib, (7, 9), (0.5, 0.8 * ov))
            lon, lat, h = ib.true.localize_dem(S, L, scene.dem)
            ta, tb = np.stack(ia.true.project(lon, lat, h)), np.stack([S, L])
            ent = {}
            for tag, path in (("after", out), ("before", None)):
                ma = RPCModel.from_file(os.path.join(path, f"{a}.RPB") if path else os.path.join(d, a, "scene.RPB"))
                mb = RPCModel.from_file(os.path.join(path, f"{b}.RPB") if path else os.path.join(d, b, "scene.RPB"))
                ea = np.stack(ma.project(lon, lat, h)) - ta
                eb = np.stack(mb.project(lon, lat, h)) - tb
                ent[tag] = float(np.max(np.hypot(*(eb - ea))))
                ent[f"{tag}_mean"] = float(np.hypot(*np.mean(eb - ea, axis=1)))
            out_seams[f"{a}|{b}"] = ent
    return out_seams


def band_to_band(out: str, d: str, names=NAMES):
    """Per band image: RMS registration error against its CCD's blue image at true ground points of a grid, in px of
    the MS bands (3 m; pan errors x 0.25): ``(err_b - err_blue)`` after and before."""
    from gdal_gf4cal.rpc import RPCModel
    scene = truth_scene(SEED, SIZE, None)
    res = {}
    for b in names:
        if b in REF:
            continue
        r = b.split("_")[0] + "_blue"
        ib, ir = scene.image(b), scene.image(r)
        fb = 0.25 if "_" not in b else 1.0
        S, L = _grid(ib)
        lon, lat, h = ib.true.localize_dem(S, L, scene.dem)
        tb, tr = np.stack([S, L]), np.stack(ir.true.project(lon, lat, h))
        ent = {}
        for tag, path in (("after", out), ("before", None)):
            mb = RPCModel.from_file(os.path.join(path, f"{b}.RPB") if path else os.path.join(d, b, "scene.RPB"))
            mr = RPCModel.from_file(os.path.join(path, f"{r}.RPB") if path else os.path.join(d, r, "scene.RPB"))
            e = (np.stack(mb.project(lon, lat, h)) - tb) * fb - (np.stack(mr.project(lon, lat, h)) - tr)
            ent[tag] = rms(e)
        res[b] = ent
    return res


def read_report(out: str):
    with open(os.path.join(out, "report.json"), encoding="utf-8") as f:
        return json.load(f)


def orbit_seams(orbit_seed: int, pairs):
    """Largest seam (px of the band) that an orbit's own attitude error leaves between two CCD images even with a
    perfect calibration: the relative displacement of their true models with and without that error."""
    c, o = truth_scene(SEED, SIZE, None), truth_scene(SEED, SIZE, orbit_seed)
    out = {}
    for a, b in pairs:
        ib = o.image(b)
        ov = float(ib.info["overlap_pan_px"]) / (1 if "_" not in b else 4)
        S, L = _grid(ib, (7, 9), (0.5, 0.8 * ov))
        lon, lat, h = ib.true.localize_dem(S, L, o.dem)

        def shift(n):
            return np.stack(o.image(n).true.project(lon, lat, h)) - np.stack(c.image(n).true.project(lon, lat, h))
        out[f"{a}|{b}"] = float(np.max(np.hypot(*(shift(b) - shift(a)))))
    return out
