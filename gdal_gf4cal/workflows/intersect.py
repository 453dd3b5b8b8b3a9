"""``gf4cal intersect``: read RPCs and tie points, intersect (METHODS §7), write points and a report.

Moved from :mod:`gdal_gf4cal.intersection` (which keeps :func:`intersect`); all outputs together or none.
"""
from __future__ import annotations

import os
from typing import Any, Dict, Optional, Sequence

import numpy as np
import pandas as pd

from ..crop import image_and_rpc, image_rpc
from ..errors import DegenerateGeometryError, GCPError
from ..gcp import write_gcps
from ..intersection import ground_errors_m, intersect, intersection_accuracy
from ..outputs import OutputSet, check_vector
from ..report import write_report_json
from ..threads import blas_serial
from ._common import cancel_check, collect_warnings, finish_report


def read_tie_points(path, n_images: int, names: Sequence[str] = ()):
    """Read image points of ``n_images`` images from a CSV (GDAL pixel convention).

    Two layouts (header required):

    * wide: ``id, sample_1, line_1, sample_2, line_2, ...`` (1-based image numbers in the order of the RPCs);
      an empty cell means the image does not see the point;
    * long: ``id, image, sample, line`` with ``image`` = 1-based number or the RPC file's name/stem.

    Optional ``lon, lat, h`` columns are ground truth (reported as errors). Returns ``(ids, points, truth)`` with
    ``points`` of shape (n_images, N, 2) and ``truth`` a (3, N) array or None.
    """
    try:
        df = pd.read_csv(path, skipinitialspace=True, comment="#")
    except Exception as exc:  # pandas raises several types
        raise GCPError(f"cannot read tie points from {path}: {str(exc).splitlines()[0]}") from None
    df.columns = [str(c).strip().lower() for c in df.columns]
    if "id" not in df.columns:
        df["id"] = [str(i + 1) for i in range(len(df))]
    truth_cols = ("lon", "lat", "h")
    if {"image", "sample", "line"} <= set(df.columns):

        keys = {}
        for k, nm in enumerate(names):
            base = os.path.basename(str(nm))
            for key in (str(k + 1), base, os.path.splitext(base)[0]):
                keys[key.lower()] = k
        img = df["image"].astype(str).str.strip().str.lower()
        bad = sorted(set(img) - set(keys) - {str(k + 1) for k in range(n_images)})
        if bad:
            raise GCPError(f"{path}: unknown image {bad[0]!r}; use 1..{n_images} or the RPC file names")
        idx = np.array([keys.get(v, int(v) - 1 if v.isdigit() else -1) for v in img])
        ids = list(dict.fromkeys(df["id"].astype(str)))
        pos = {v: i for i, v in enumerate(ids)}
        pts = np.full((n_images, len(ids), 2), np.nan)
        col = np.array([pos[v] for v in df["id"].astype(str)])
        pts[idx, col, 0] = df["sample"].to_numpy(float)
        pts[idx, col, 1] = df["line"].to_numpy(float)
        truth = None
        if all(c in df.columns for c in truth_cols):
            first = df.groupby(df["id"].astype(str), sort=False)[list(truth_cols)].first().loc[ids]
            truth = first.to_numpy(float).T
        return ids, pts, truth
    pts = np.full((n_images, len(df), 2), np.nan)
    for k in range(n_images):
        cs, cl = f"sample_{k + 1}", f"line_{k + 1}"
        if cs not in df.columns or cl not in df.columns:
            raise GCPError(f"{path}: columns {cs}, {cl} missing; expected id,sample_1,line_1,sample_2,line_2,... "
                           "or id,image,sample,line")
        pts[k, :, 0] = pd.to_numeric(df[cs], errors="coerce").to_numpy(float)
        pts[k, :, 1] = pd.to_numeric(df[cl], errors="coerce").to_numpy(float)
    truth = df[list(truth_cols)].to_numpy(float).T if all(c in df.columns for c in truth_cols) else None
    return list(df["id"].astype(str)), pts, truth


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def intersect_files(rpc_paths: Sequence[str], points_path: str, *, out: Optional[str] = None, sigma_px: float = 1.0,
                    report: Optional[str] = None, overwrite: bool = False, progress=None) -> Dict[str, Any]:
    """``gf4cal intersect``: read RPCs and tie points, intersect (METHODS §7), write points and a report.

    Each of ``rpc_paths`` is an image with its RPC, an RPC file, or ``IMAGE=RPC``: the RPC of the image's own pixel
    grid through :func:`gdal_gf4cal.crop.image_rpc` (a crop with its product's RPC: shifted by the crop's origin, the
    report's ``notes`` say so).

    ``out`` (``.csv``, ``.gpkg`` or ``.geojson``) gets one row per point: ``id, lon, lat, h, n_images,
    sigma_planar_m, sigma_height_m, sigma0`` and, with ground truth, ``err_east_m, err_north_m, err_h_m``.
    Outputs are written together after the intersection, or none is.
    """
    paths = [os.fspath(p) for p in rpc_paths]
    if len(paths) < 2:
        raise DegenerateGeometryError("forward intersection needs at least 2 RPCs (--rpc A B [C ...])")
    out = os.fspath(out) if out else None
    if out and not out.lower().endswith((".csv", ".gpkg", ".geojson")):
        raise GCPError(f"output {out!r}: use a name ending in .csv, .gpkg or .geojson")
    pairs = [image_and_rpc(p) for p in paths]
    inputs = [p for pair in pairs for p in pair if p] + [os.fspath(points_path)]
    outs = OutputSet(inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    if out:
        outs.declare("points", out, check=check_vector() if not out.lower().endswith(".csv") else None)
    if report:
        outs.declare("report", report)
    warns: list = []
    with outs, collect_warnings(warns):
        loaded = [image_rpc(image, rpc) for image, rpc in pairs]
        models = [m for m, _ in loaded]
        ids, pts, truth = read_tie_points(points_path, len(models), paths)
        res = intersect(models, pts, sigma_px=sigma_px, progress=progress)
        table = pd.DataFrame({"id": ids, "lon": res.lon, "lat": res.lat, "h": res.h, "n_images": res.n_images,
                              "sigma_planar_m": res.sigma_planar_m,
                              "sigma_height_m": res.sigma_height_m, "sigma0": res.sigma0})
        rep: Dict[str, Any] = {"rpcs": paths, "points": os.fspath(points_path), "n_points": len(ids),
                               "n_intersected": int(np.isfinite(res.lon).sum()), "sigma_px": float(sigma_px),
                               "predicted": {"sigma_planar_m_median": float(np.nanmedian(res.sigma_planar_m))
                                             if np.isfinite(res.sigma_planar_m).any() else None,
                                             "sigma_height_m_median": float(np.nanmedian(res.sigma_height_m))
                                             if np.isfinite(res.sigma_height_m).any() else None}}
        if any(note for _, note in loaded):
            rep["notes"] = [note for _, note in loaded if note]
        if truth is not None:
            e, n, u = ground_errors_m(res.lon, res.lat, res.h, *truth)
            table["err_east_m"], table["err_north_m"], table["err_h_m"] = e, n, u
            rep["accuracy"] = intersection_accuracy(res, *truth)
        if out:
            write_gcps(table, outs.tmp("points"))        # a point layer (EPSG:4326) for .gpkg/.geojson
            if out.lower().endswith(".gpkg"):
                outs.set_check("points", check_vector({"gcps": len(table)}))
            rep["output"] = out
        rep["outputs"] = outs.paths
        finish_report(rep, warns)
        if report:
            write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    rep["table"] = table
    return rep
