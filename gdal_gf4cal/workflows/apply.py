"""``gf4cal apply-calibration`` / QGIS "Apply calibration": recalibrate other scenes' RPCs for a calibrated camera
(METHODS §5 step 4). Moved from :mod:`gdal_gf4cal.lookangle`; all outputs together or none."""
from __future__ import annotations

import os
from typing import Any, Dict, Sequence

import numpy as np

from .. import progress as _progress
from ..block import calibrated_model, read_calibration
from ..camera import LookAngleModel
from ..crop import image_rpc, paired_rpc_files, product_rpc
from ..errors import GCPError, InputOverwriteError
from ..lookangle import recalibrate_rpc
from ..outputs import OutputSet, scene_stem
from ..report import write_report_json
from ..rpc_fit import fit_rpc_from_model
from ..rpc_io import rpc_file_format, write_rpb, write_rpc_vrt
from ..threads import blas_serial
from ._common import _open_image, cancel_check, collect_warnings, finish_report
from .block import image_keys


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def apply_calibration(current, new, scenes: Sequence, out_dir, *, overwrite: bool = False,
                      progress=None, rpcs=None) -> Dict[str, Any]:
    """Recalibrate the RPCs of other scenes made with camera ``current`` for camera ``new`` (METHODS §5 step 4).

    ``current``/``new`` are LookAngleModels or camera-file paths; ``scenes`` images or RPC files. Writes
    ``out_dir/<scene>.RPB`` for each (plus ``out_dir/<scene>.vrt`` over the untouched image when the scene is a
    raster) and ``out_dir/report.json`` with each fit report. Every RPC is refitted before anything is written,
    and all files are renamed into place together (none on failure or cancel).

    ``rpcs`` (``["IMAGE=RPC", ...]``, CLI ``--rpc``): the RPC file of a scene that carries none. A crop that states
    its origin in the product with the product's RPC (paired, or beside it): the product's RPC (the camera's pixels)
    is recalibrated, then shifted to the crop (:func:`gdal_gf4cal.crop.product_rpc`; the report's ``notes`` say so).
    """

    cur = current if hasattr(current, "tan_angles") else LookAngleModel.from_json(current)
    nw = new if hasattr(new, "tan_angles") else LookAngleModel.from_json(new)
    if tuple(cur.size) != tuple(nw.size):
        raise GCPError(f"the cameras have different sizes {tuple(cur.size)} and {tuple(nw.size)}; give the "
                       "current camera the new one was calibrated from")
    scenes = [os.fspath(s) for s in scenes]
    if not scenes:
        raise GCPError("no scene given; name the scenes (images or RPC files) to recalibrate")
    out = os.fspath(out_dir)
    stems = [scene_stem(s) for s in scenes]
    if len(set(stems)) != len(stems):
        raise InputOverwriteError("two scenes have the same name; recalibrate them into different folders")
    rpc_files = paired_rpc_files(scenes, rpcs)
    inputs = scenes + [current if isinstance(current, (str, os.PathLike)) else None,
                       new if isinstance(new, (str, os.PathLike)) else None] + [r for r in rpc_files if r]
    outs = OutputSet(inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    plans = []
    for s, stem, pr in zip(scenes, stems, rpc_files):
        is_image = (_open_image(s)[0] is not None) if pr else rpc_file_format(s) == "gdal"
        rpb = os.path.join(out, f"{stem}.RPB")
        vrt = os.path.join(out, f"{stem}.vrt") if is_image else None
        outs.declare(f"rpb:{stem}", rpb)
        if vrt:
            outs.declare(f"vrt:{stem}", vrt)
        plans.append((s, stem, rpb, vrt))
    outs.declare("report", os.path.join(out, "report.json"))
    warns: list = []
    with outs, collect_warnings(warns):
        entries, notes = [], []
        for i, ((s, stem, rpb, vrt), pr) in enumerate(zip(plans, rpc_files)):
            rpc, origin, note = product_rpc(s, pr)           # in the product's pixels: the camera's
            new_rpc, fit_report = recalibrate_rpc(rpc, cur, nw, progress=_progress.scaled(
                progress, i / len(plans), (i + 0.9) / len(plans)))
            written = new_rpc.with_image_affine(-origin[0], -origin[1]) if origin != (0.0, 0.0) else new_rpc
            notes += [note] if note else []
            write_rpb(written, outs.tmp(f"rpb:{stem}"), overwrite=True)
            if vrt:
                write_rpc_vrt(s, written, outs.tmp(f"vrt:{stem}"), overwrite=True)
            S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, cur.size[0], 11), np.linspace(0, cur.size[1], 11)))
            lon, lat = rpc.localize(S, L, np.full(S.shape, rpc.height_off))
            ns, nl = new_rpc.project(lon, lat, rpc.height_off)
            shift = np.hypot(ns - S, nl - L)
            entries.append({"scene": s, "rpb": rpb, "vrt": vrt, "fit": fit_report.to_dict(),
                            "image_shift_px": {"mean": float(np.nanmean(shift)), "max": float(np.nanmax(shift))}})
        rep = {"command": "apply-calibration",
               "current": current if isinstance(current, str) else getattr(cur, "name", ""),
               "new": new if isinstance(new, str) else getattr(nw, "name", ""),
               "scenes": entries, "outputs": {"report": outs.path("report")}}
        if notes:
            rep["notes"] = notes
        finish_report(rep, warns)
        write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def apply_block_calibration(calibration, scenes: Sequence, out_dir, *, overwrite: bool = False,
                            progress=None, rpcs=None) -> Dict[str, Any]:
    """Recalibrate other scenes of a block-calibrated camera group (METHODS §8 outputs, as §5 step 4).

    ``calibration``: the ``calibration.json`` of ``block-adjust`` (or its dict); ``scenes``: the images of another
    scene of the same camera and group, named as the calibrated ones (file stem, else folder name: see
    :func:`gdal_gf4cal.workflows.block.image_keys`). Each image's RPC is composed with the group's exterior and its
    interior and refitted (METHODS §3, error reported); writes ``out_dir/<key>.RPB`` (+ ``<key>.vrt`` over the
    untouched image) and ``out_dir/report.json``; all files or none. ``rpcs`` (``["IMAGE=RPC", ...]``, CLI
    ``--rpc``): the RPC file of an image that carries none (a crop with its product's RPC: shifted by its origin as
    ``block-adjust --rpc`` does, :func:`gdal_gf4cal.crop.image_rpc`; the report's ``notes`` say so).
    """

    cal = calibration if isinstance(calibration, dict) else read_calibration(calibration)
    scenes = [os.fspath(s) for s in scenes]
    if not scenes:
        raise GCPError("no scene given; name the images (with their RPCs) to recalibrate")
    keys = image_keys(scenes)
    out = os.fspath(out_dir)
    rpc_files = paired_rpc_files(scenes, rpcs)
    inputs = list(scenes) + ([calibration] if isinstance(calibration, (str, os.PathLike)) else []) + \
        [r for r in rpc_files if r]
    outs = OutputSet(inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    plans = []
    for s, k, pr in zip(scenes, keys, rpc_files):
        is_image = (_open_image(s)[0] is not None) if pr else rpc_file_format(s) == "gdal"
        outs.declare(f"rpb:{k}", os.path.join(out, f"{k}.RPB"))
        if is_image:
            outs.declare(f"vrt:{k}", os.path.join(out, f"{k}.vrt"))
        plans.append((s, k, is_image))
    outs.declare("report", os.path.join(out, "report.json"))
    warns: list = []
    with outs, collect_warnings(warns):
        entries, notes = [], []
        for i, ((s, k, is_image), pr) in enumerate(zip(plans, rpc_files)):
            rpc, note = image_rpc(s, pr)
            notes += [f"{k}: {note}"] if note else []
            size, _ = _open_image(s)
            model = calibrated_model(cal, k, rpc, size)
            new_rpc, fit = fit_rpc_from_model(model, size=model.size, height_range=tuple(rpc.height_range),
                                              progress=_progress.scaled(progress, i / len(plans),
                                                                        (i + 0.9) / len(plans)))
            write_rpb(new_rpc, outs.tmp(f"rpb:{k}"), overwrite=True)
            if is_image:
                write_rpc_vrt(s, new_rpc, outs.tmp(f"vrt:{k}"), overwrite=True)
            W, H = model.size
            S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, W, 11), np.linspace(0, H, 11)))
            lon, lat = rpc.localize(S, L, np.full(S.shape, rpc.height_off))
            ns, nl = new_rpc.project(lon, lat, rpc.height_off)
            shift = np.hypot(ns - S, nl - L)
            entries.append({"scene": s, "image": k, "rpb": outs.path(f"rpb:{k}"),
                            "vrt": outs.path(f"vrt:{k}") if is_image else None, "fit": fit.to_dict(),
                            "image_shift_px": {"mean": float(np.nanmean(shift)), "max": float(np.nanmax(shift))}})
        rep = {"command": "apply-calibration", "calibration": calibration if isinstance(calibration, str) else "",
               "model": cal.get("model"), "scenes": entries, "outputs": {"report": outs.path("report")}}
        if notes:
            rep["notes"] = notes
        finish_report(rep, warns)
        write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep
