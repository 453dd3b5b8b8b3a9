"""Batch forms of the file-to-file jobs (issue 14): many scenes, one output per scene, a resumable summary.

A *scene function* is a plain top-level function ``fn(scene, outputs, **params) -> dict`` of file paths and
parameters (nothing holding an open GDAL dataset), so :func:`run_batch` runs it serially, on threads or on a Dask
cluster unchanged (:mod:`gdal_gf4cal.executors`). It writes the files named in ``outputs`` (atomically, through
:class:`gdal_gf4cal.outputs.OutputSet`) and returns its accuracy figures (plain numbers).

:func:`run_batch` writes ``batch_summary.csv`` and ``batch_summary.json`` in the output folder: one row per scene
with ``status`` (``ok``, ``failed``, ``skipped`` = complete outputs from an earlier run), ``seconds``, the figures
and the one-line ``error``. One failing scene never stops the others; a rerun skips scenes whose outputs all exist
(they are renamed into place only when complete) unless ``overwrite``.
"""
from __future__ import annotations

import concurrent.futures as cf
import csv
import glob
import inspect
import json
import math
import os
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np

from . import threads
from .camera import LookAngleModel
from .errors import CancelledError, GCPError, Gf4calError
from .executors import SerialExecutor, dask_client, map_ordered
from .lookangle import recalibrate_rpc
from .outputs import OutputSet, atomic_output
from .outputs import scene_stem  # noqa: F401  (batch.scene_stem: the name of a scene's outputs)
from .progress import cancel_check, report
from .report.json import report_text     # strict JSON: no NaN, absent values left out (as report.json)
from .rpc import RPCModel
from .rpc_io import rpc_file_format, write_rpb, write_rpc_vrt
from .workflows.collect import collect_gcps_file
from .workflows.refine import check_refine_options, refine_rpc

SUMMARY_CSV = "batch_summary.csv"
SUMMARY_JSON = "batch_summary.json"
#: row statuses: done now, failed (the error says why), done by an earlier run, not run (the batch was cancelled)
STATUSES = ("ok", "failed", "skipped", "cancelled")
_FIRST = ["scene", "status", "seconds", "outputs", "error"]


def expand_scenes(items: Sequence) -> List[str]:
    """Scene list from paths, globs (``*.tif``) and list files (``@list.txt``: one path or glob a line, ``#``
    comments; relative paths are relative to the list file). Order is kept, duplicates dropped; a path that
    does not exist is kept (the batch reports it); a glob that matches nothing is an error."""
    out: List[str] = []

    def add(item: str, base: str = "") -> None:
        item = os.path.expanduser(item.strip())
        if not item:
            return
        if base and not os.path.isabs(item):
            item = os.path.join(base, item)
        if any(ch in item for ch in "*?["):
            hits = sorted(glob.glob(item))
            if not hits:
                raise Gf4calError(f"no scene matches {item!r}; check the pattern (quote it for the shell)")
            out.extend(hits)
        else:
            out.append(item)

    for it in items:
        it = os.fspath(it)
        if it.startswith("@"):
            lst = it[1:]
            try:
                with open(lst, encoding="utf-8") as fh:
                    lines = fh.read().splitlines()
            except OSError as exc:
                raise Gf4calError(f"cannot read the scene list {lst}: {exc.strerror}") from None
            for line in lines:
                if line.strip() and not line.lstrip().startswith("#"):
                    add(line, os.path.dirname(os.path.abspath(lst)))
        else:
            add(it)
    seen = set()
    return [s for s in out if not (s in seen or seen.add(s))]


@dataclass(frozen=True)
class SceneTask:
    """One scene of a batch: plain picklable data (a dataclass, not a tuple: Dask would run a tuple that starts
    with a callable as a task of its own). ``progress`` is the scene's own progress/cancel callback
    (:class:`_LocalSceneProgress` on threads, :class:`_DaskSceneProgress` on a cluster)."""

    fn: Callable[..., Dict[str, Any]]
    scene: str
    outputs: Dict[str, str]
    params: Dict[str, Any]
    progress: Any = None
    threads: Optional[int] = None         # the scene's thread budget on a thread pool (None: unchanged)


class _Tracker:
    """Driver side of a batch's progress: the fraction done of each running scene and the cancel flag."""

    def __init__(self, outer_cancelled: Optional[Callable[[], bool]] = None):
        self.fractions: Dict[int, float] = {}
        self.cancel = threading.Event()
        self.outer_cancelled = outer_cancelled      # the caller's own cancel flag (QGIS feedback), thread-safe
        self.notify: Optional[Callable[[int, float], None]] = None   # serial: report from the scene itself

    def cancelled(self) -> bool:
        if not self.cancel.is_set() and self.outer_cancelled is not None and self.outer_cancelled():
            self.cancel.set()
        return self.cancel.is_set()

    def partial(self) -> float:
        return sum(f for f in list(self.fractions.values()) if f < 1.0)

    def on_event(self, event) -> None:          # distributed topic handler: (timestamp, (index, fraction))
        try:
            i, f = event[1]
            self.fractions[int(i)] = float(f)
        except (TypeError, ValueError, IndexError):
            pass


class _LocalSceneProgress:
    """A scene's progress on threads (or serially): its fraction into the tracker; raises
    :class:`CancelledError` once the batch is cancelled, so the scene stops and its OutputSet removes what it
    wrote (the finished scenes stay)."""

    def __init__(self, tracker: _Tracker, index: int):
        self.tracker, self.index = tracker, index

    def __call__(self, fraction: float, message: str = "") -> None:
        self.tracker.fractions[self.index] = float(fraction)
        if self.tracker.notify is not None:
            self.tracker.notify(self.index, float(fraction))
        if self.tracker.cancelled():
            raise CancelledError("batch cancelled")

    def is_cancelled(self) -> bool:
        return self.tracker.cancelled()


class _DaskSceneProgress:
    """A scene's progress on a Dask worker (picklable): fractions go to the driver as worker events on
    ``topic`` (at most every 0.5 s), and the task stops when the driver cancelled its future.

    ``distributed`` is an optional dependency (Dask clusters only), hence imported where it is used."""

    def __init__(self, topic: str, index: int):
        self.topic, self.index = topic, index
        self._t = 0.0

    def __call__(self, fraction: float, message: str = "") -> None:
        now = time.monotonic()
        if fraction >= 1.0 or now - self._t >= 0.5:
            self._t = now
            try:
                from distributed import get_worker
                get_worker().log_event(self.topic, (self.index, float(fraction)))
            except (ImportError, ValueError):     # not on a worker: nothing to tell
                pass
        if self.is_cancelled():
            raise CancelledError("batch cancelled")

    def is_cancelled(self) -> bool:
        try:
            from distributed import get_worker
            w = get_worker()
            ts = w.state.tasks.get(w.get_current_task())
        except Exception:  # noqa: BLE001 - not on a worker, or another distributed version: no remote cancel
            return False
        return ts is not None and ts.state in ("cancelled", "released", "forgotten")


def _takes_progress(fn) -> bool:
    """Whether a scene function takes ``progress=`` (ours do; a user's may not)."""
    try:
        ps = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return "progress" in ps or any(p.kind is p.VAR_KEYWORD for p in ps.values())


def _run_scene(task: SceneTask) -> Dict[str, Any]:
    """Worker side: run one scene function, catch its error into the row (never raises but for cancel)."""
    fn, scene, outputs, params = task.fn, task.scene, task.outputs, dict(task.params)
    if task.progress is not None and _takes_progress(fn):
        params["progress"] = task.progress
    t0 = time.perf_counter()
    with threads.limit(task.threads):
        return _scene_row(fn, scene, outputs, params, t0)


def _scene_row(fn, scene, outputs, params, t0) -> Dict[str, Any]:
    """:func:`_run_scene`'s row, under the scene's thread budget."""
    row: Dict[str, Any] = {"scene": scene, "status": "ok", "seconds": 0.0,
                           "outputs": ";".join(outputs.values()), "error": ""}
    try:
        if not os.path.exists(scene):
            raise Gf4calError(f"scene not found: {scene}")
        figures = fn(scene, outputs, **params) or {}
        row.update({k: v for k, v in figures.items() if k not in row})
    except CancelledError:
        raise
    except Exception as exc:  # noqa: BLE001 - one failing scene is reported, the others go on
        row["status"] = "failed"
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        row["error"] = msg if isinstance(exc, Gf4calError) else f"{type(exc).__name__}: {msg}"
        if os.environ.get("GF4CAL_DEBUG", "").strip().lower() in ("1", "yes", "true", "on"):
            row["traceback"] = traceback.format_exc()
    row["seconds"] = round(time.perf_counter() - t0, 3)
    return row


def _previous_rows(out_dir: str) -> Dict[str, Dict[str, Any]]:
    try:
        with open(os.path.join(out_dir, SUMMARY_JSON), encoding="utf-8") as fh:
            return {r["scene"]: r for r in json.load(fh).get("scenes", [])}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def write_summary(rows: List[Dict[str, Any]], out_dir: str, meta: Optional[Dict[str, Any]] = None) -> Dict[str, str]:
    """Write ``batch_summary.csv`` and ``.json`` in ``out_dir`` (atomically); returns their paths."""
    cols = list(_FIRST)
    for r in rows:
        cols += [k for k in r if k not in cols and k != "traceback"]
    csv_path, json_path = os.path.join(out_dir, SUMMARY_CSV), os.path.join(out_dir, SUMMARY_JSON)
    with atomic_output(csv_path) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
    counts = {s: sum(r["status"] == s for r in rows) for s in STATUSES}
    with atomic_output(json_path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(report_text({**(meta or {}), "counts": counts, "scenes": rows}, indent=1))
    return {"csv": csv_path, "json": json_path}


def run_batch(fn: Callable[..., Dict[str, Any]], scenes: Sequence, out_dir, outputs_for: Callable[[str], Dict[str, str]],
              *, params: Optional[Dict[str, Any]] = None, executor=None, overwrite: bool = False, progress=None,
              command: str = "") -> Dict[str, Any]:
    """Run the scene function ``fn`` on every scene and write the batch summary in ``out_dir``.

    Parameters
    ----------
    fn : top-level scene function ``fn(scene, outputs, **params) -> dict of figures`` (picklable); when it takes
        ``progress=``, it gets the scene's own progress/cancel callback (its fraction joins the batch's, on
        threads and on Dask; it raises :class:`CancelledError` once the batch is cancelled).
    scenes : scene paths, globs or ``@list.txt`` (see :func:`expand_scenes`).
    out_dir : output folder (created).
    outputs_for : ``scene -> {role: output path}``; all existing = the scene is complete (skipped on rerun).
    executor : a :class:`concurrent.futures.Executor` (``None``: serial); see :func:`gdal_gf4cal.executors.get_executor`.
    overwrite : rerun complete scenes too (their outputs replaced; never an input).
    progress : ``callable(fraction, message)`` over scenes (and the running scenes' own progress, e.g. tiles);
        raising :class:`CancelledError` cancels: finished scenes stay, running ones stop and remove their
        partial outputs, the summary (``status`` ``cancelled``, ``"cancelled": true``) is written, and
        :class:`CancelledError` propagates.

    Returns
    -------
    dict ``{"command", "scenes" (rows), "counts", "summary": {"csv", "json"}}``.
    """
    out_dir = os.fspath(out_dir)
    plans = _plan_scenes(scenes, out_dir, outputs_for)
    rows, todo = _skip_complete(plans, out_dir, overwrite)
    report(progress, 0.0, f"{len(todo)} of {len(plans)} scenes to run")
    t0 = time.perf_counter()
    tracker = _Tracker(cancel_check(progress))
    client = dask_client(executor)
    topic = f"gf4cal-batch-{os.getpid()}-{id(tracker)}"

    def batch_progress(fraction, message):
        try:
            report(progress, fraction, message)
        except BaseException:
            tracker.cancel.set()          # running scenes on threads stop at their next progress call
            raise

    prog = _scene_progress(executor, client, tracker, topic, len(todo), batch_progress)
    budget = _scene_threads(executor, len(todo))
    tasks = [SceneTask(fn, plans[i][0], plans[i][1], dict(params or {}, overwrite=overwrite), prog[k], budget)
             for k, i in enumerate(todo)]
    meta: Dict[str, Any] = {"command": command}
    done = [False] * len(tasks)
    res: List[Any] = [None] * len(tasks)
    try:
        res = map_ordered(_run_scene, tasks, executor, progress=batch_progress, label="scene",
                          return_exceptions=True, partial=tracker.partial, done=done, out=res)
    except BaseException:
        tracker.cancel.set()
        # Cancelled: the finished scenes stay (their outputs are complete); the others are said cancelled.
        for k, i in enumerate(todo):
            rows[i] = res[k] if done[k] and isinstance(res[k], dict) else _row(plans[i], "cancelled",
                                                                               "cancelled by the user")
        meta.update(cancelled=True, wall_seconds=round(time.perf_counter() - t0, 3))
        write_summary(rows, out_dir, meta)  # type: ignore[arg-type]
        raise
    finally:
        if client is not None:
            try:
                client.unsubscribe_topic(topic)
            except Exception:  # noqa: BLE001 - the cluster may be gone already
                pass
    for i, r in zip(todo, res):
        if isinstance(r, BaseException):   # the task itself was lost (e.g. KilledWorker after retries)
            msg = str(r).strip().splitlines()[0] if str(r).strip() else ""
            r = _row(plans[i], "failed", f"{type(r).__name__}: {msg}")
        rows[i] = r
    meta["wall_seconds"] = round(time.perf_counter() - t0, 3)
    paths = write_summary(rows, out_dir, meta)  # type: ignore[arg-type]
    counts = {s: sum(r["status"] == s for r in rows) for s in STATUSES}  # type: ignore[index]
    report(progress, 1.0, f"{counts['ok']} ok, {counts['failed']} failed, {counts['skipped']} skipped")
    return {"command": command, "scenes": rows, "counts": counts, "summary": paths,
            "wall_seconds": meta["wall_seconds"]}


def _plan_scenes(scenes: Sequence, out_dir: str, outputs_for: Callable[[str], Dict[str, str]]):
    """``[(scene, {role: output path})]``, the output folder created; refuses a file as folder, no scene, and
    two scenes writing the same path."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise Gf4calError(f"--out {out_dir} is a file; with several scenes give a folder")
    scenes = expand_scenes(scenes)
    if not scenes:
        raise Gf4calError("no scene given; name scenes, globs or @list.txt")
    os.makedirs(out_dir, exist_ok=True)
    plans = [(s, outputs_for(s)) for s in scenes]
    seen: Dict[str, str] = {}
    for s, outs in plans:
        for p in outs.values():
            if p in seen:
                raise Gf4calError(f"scenes {seen[p]} and {s} would both write {p}; rename one or run them "
                                  "into different folders")
            seen[p] = s
    return plans


def _skip_complete(plans, out_dir: str, overwrite: bool):
    """Rows of the complete scenes (all outputs exist; the previous summary's row, status ``skipped``) and the
    indices of the scenes to run."""
    prev = _previous_rows(out_dir)
    rows: List[Optional[Dict[str, Any]]] = [None] * len(plans)
    todo = []
    for i, (s, outs) in enumerate(plans):
        if not overwrite and outs and all(os.path.exists(p) for p in outs.values()):
            old = dict(prev.get(s) or {"scene": s, "outputs": ";".join(outs.values()), "error": ""})
            old.update(status="skipped", seconds=0.0)
            rows[i] = old
        else:
            todo.append(i)
    return rows, todo


def _row(plan, status: str, error: str) -> Dict[str, Any]:
    """The summary row of a scene that did not run to its end (cancelled, or its task lost)."""
    return {"scene": plan[0], "status": status, "seconds": 0.0, "outputs": ";".join(plan[1].values()),
            "error": error}


def _scene_threads(executor, n: int) -> Optional[int]:
    """Threads each scene may use (its tiles, point kernels): on a thread pool the process's
    :func:`gdal_gf4cal.threads.num_threads` shared among the scenes running at once (1 at least), so scenes x
    tiles never exceed it; on Dask or another executor 1 (the executor parallelises); serially None (all)."""
    if executor is None or isinstance(executor, SerialExecutor):
        return None
    if not isinstance(executor, cf.ThreadPoolExecutor):
        return 1
    running = max(1, min(int(getattr(executor, "_max_workers", 1)), n))
    return max(1, threads.num_threads() // running)


def _scene_progress(executor, client, tracker: _Tracker, topic: str, n: int, batch_progress) -> List[Any]:
    """Each scene's own progress callback: Dask worker events on ``topic``, the tracker on threads (serially
    straight to the batch's bar), none on another executor (a process pool)."""
    if client is not None:
        client.subscribe_topic(topic, tracker.on_event)
        return [_DaskSceneProgress(topic, k) for k in range(n)]
    if executor is None or isinstance(executor, (SerialExecutor, cf.ThreadPoolExecutor)):
        if executor is None or isinstance(executor, SerialExecutor):
            # Serially the scene runs in this thread: its progress (e.g. over tiles) goes straight to the bar.
            tracker.notify = lambda k, f: batch_progress((k + min(f, 1.0)) / n, f"scene {k + 1}/{n}")
        return [_LocalSceneProgress(tracker, k) for k in range(n)]
    return [None] * n                     # another executor (a process pool): scenes report no sub-progress


# --------------------------------------------------------------------------------------------- scene functions
def apply_calibration_scene(scene: str, outputs: Dict[str, str], *, current, new, overwrite: bool = False,
                            progress=None) -> Dict[str, Any]:
    """Scene function of batch ``apply-calibration`` (METHODS §5 step 4): recalibrate one scene's RPC for the
    ``new`` camera and write ``outputs['rpb']`` (+ ``outputs['vrt']`` over the untouched image for rasters).

    Returns the figures ``image_shift_mean_px, image_shift_max_px`` (how far the new RPC moves the image) and
    ``rpc_fit_max_px`` (the refit's worst residual)."""
    cur = current if hasattr(current, "tan_angles") else LookAngleModel.from_json(current)
    nw = new if hasattr(new, "tan_angles") else LookAngleModel.from_json(new)
    outs = OutputSet([scene] + [c for c in (current, new) if isinstance(c, (str, os.PathLike))],
                     overwrite=overwrite, cancelled=cancel_check(progress))
    for role, p in outputs.items():
        outs.declare(role, p)
    with outs:
        rpc = RPCModel.from_file(scene)
        report(progress, 0.1, "refitting the RPC")
        new_rpc, fit = recalibrate_rpc(rpc, cur, nw)
        report(progress, 0.9, "writing")
        write_rpb(new_rpc, outs.tmp("rpb"), overwrite=True)
        if "vrt" in outputs:
            write_rpc_vrt(scene, new_rpc, outs.tmp("vrt"), overwrite=True)
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, cur.size[0], 11), np.linspace(0, cur.size[1], 11)))
    lon, lat = rpc.localize(S, L, np.full(S.shape, rpc.height_off))
    ns, nl = new_rpc.project(lon, lat, rpc.height_off)
    shift = np.hypot(ns - S, nl - L)
    f = fit.to_dict()
    chk = f.get("check") or f.get("fit") or {}
    return {"image_shift_mean_px": float(np.nanmean(shift)), "image_shift_max_px": float(np.nanmax(shift)),
            "rpc_fit_max_px": float(chk.get("max_px", np.nan))}


def apply_calibration_batch(current, new, scenes: Sequence, out_dir, *, executor=None, overwrite: bool = False,
                            progress=None) -> Dict[str, Any]:
    """Batch ``apply-calibration``: ``out_dir/<stem>.RPB`` (+ ``<stem>.vrt`` for rasters) per scene and the
    batch summary; see :func:`run_batch` and :func:`apply_calibration_scene`."""
    out = os.fspath(out_dir)
    cur = current if hasattr(current, "tan_angles") else LookAngleModel.from_json(current)
    nw = new if hasattr(new, "tan_angles") else LookAngleModel.from_json(new)
    if tuple(cur.size) != tuple(nw.size):
        raise GCPError(f"the cameras have different sizes {tuple(cur.size)} and {tuple(nw.size)}; give the "
                       "current camera the new one was calibrated from")

    def outputs_for(s):
        stem = scene_stem(s)
        o = {"rpb": os.path.join(out, f"{stem}.RPB")}
        try:
            if os.path.exists(s) and rpc_file_format(s) == "gdal":
                o["vrt"] = os.path.join(out, f"{stem}.vrt")
        except Exception:  # noqa: BLE001 - an unreadable scene: the scene function reports it
            pass
        return o
    return run_batch(apply_calibration_scene, scenes, out, outputs_for, params={"current": cur, "new": nw},
                     executor=executor, overwrite=overwrite, progress=progress, command="apply-calibration")


def collect_gcps_scene(scene: str, outputs: Dict[str, str], *, reference, dem, overwrite: bool = False,
                       progress=None, **options) -> Dict[str, Any]:
    """Scene function of batch ``collect-gcps`` (issue 7): match ``scene`` against ``reference`` + ``dem`` and
    write ``outputs['gcps']``; its tiles on the scene's share of the threads (:func:`run_batch`: all of them
    serially, 1 on Dask, the process's threads over the scenes running at once on a thread pool).

    Returns ``n_gcps, n_outliers, windows, median_precision_px, offset_sample_px, offset_line_px``."""
    rep = collect_gcps_file(scene, reference, dem, outputs["gcps"], overwrite=overwrite, progress=progress,
                            **options)
    g = rep["gcps"]
    inl = ~g["outlier"].to_numpy(bool)
    return {"n_gcps": rep["n_gcps"], "n_outliers": rep["n_outliers"], "windows": rep["windows"]["total"],
            "median_precision_px": float(np.median(g["precision_px"].to_numpy()[inl])) if inl.any() else np.nan,
            "offset_sample_px": float(np.mean(g["dsample"].to_numpy()[inl])) if inl.any() else np.nan,
            "offset_line_px": float(np.mean(g["dline"].to_numpy()[inl])) if inl.any() else np.nan}


def collect_gcps_batch(scenes: Sequence, reference, dem, out_dir, *, ext: str = ".gpkg", executor=None,
                       overwrite: bool = False, progress=None, **options) -> Dict[str, Any]:
    """Batch ``collect-gcps``: ``out_dir/<stem>.gpkg`` per scene and the batch summary (:func:`run_batch`)."""
    out = os.fspath(out_dir)
    return run_batch(collect_gcps_scene, scenes, out, lambda s: {"gcps": os.path.join(out, scene_stem(s) + ext)},
                     params=dict(options, reference=os.fspath(reference),
                                 dem=dem if not isinstance(dem, os.PathLike) else os.fspath(dem)),
                     executor=executor, overwrite=overwrite, progress=progress, command="collect-gcps")


def _scene_gcps(gcps_dir: str, scene: str, gcps_ext: str) -> str:
    """The scene's GCP file: ``gcps_dir/<stem><gcps_ext>``, else the one ``gcps_dir/<stem>.*`` there is (a CSV,
    header-less with ``--columns``, a QGIS .points, ...)."""
    stem = scene_stem(scene)
    path = os.path.join(gcps_dir, stem + gcps_ext)
    if os.path.exists(path):
        return path
    found = sorted(p for p in glob.glob(os.path.join(glob.escape(gcps_dir), glob.escape(stem) + ".*"))
                   if os.path.isfile(p) and not p.endswith((".aux.xml", ".report.json")))
    if len(found) == 1:
        return found[0]
    if found:
        raise Gf4calError(f"several GCP files for this scene ({', '.join(os.path.basename(p) for p in found)}); "
                          f"keep one {stem}.* in {gcps_dir}")
    raise Gf4calError(f"no GCP table for this scene: {path} (run collect-gcps on it first)")


def refine_scene(scene: str, outputs: Dict[str, str], *, gcps_dir: str, gcps_ext: str = ".gpkg",
                 model: str = "affine", overwrite: bool = False, progress=None, **options) -> Dict[str, Any]:
    """Scene function of batch ``refine`` (METHODS §4): refine ``scene``'s RPC with its own GCP table
    ``gcps_dir/<stem><gcps_ext>`` (what batch collect-gcps writes; else the one ``<stem>.*`` file there) and write
    ``outputs['rpc']`` (+ ``report``); ``options`` are :func:`~gdal_gf4cal.workflows.refine_rpc`'s (the GCP
    reader's ``gcp_columns`` and ``gcp_pixel_convention``, ``max_uncertainty_px``, ``check_plausibility``...).

    Returns ``n_control, n_check, control_rms_after_px, check_rms_after_px, check_ce90_after_m, n_outliers``."""
    gcps = _scene_gcps(gcps_dir, scene, gcps_ext)
    rep = refine_rpc(scene, gcps, model, out=outputs["rpc"], report=outputs.get("report"), overwrite=overwrite,
                     progress=progress, **options)

    def rms(role):
        a = rep[role]["after"]
        return math.hypot(a["sample"]["rms"], a["line"]["rms"]) if a["n"] else math.nan
    return {"n_control": rep["control"]["after"]["n"], "n_check": rep["check"]["after"]["n"],
            "control_rms_after_px": rms("control"), "check_rms_after_px": rms("check"),
            "check_ce90_after_m": rep["check"]["after"].get("ce90_m", math.nan) if rep["check"]["after"]["n"]
            else math.nan, "n_outliers": len(rep.get("outliers", []))}


def refine_batch(scenes: Sequence, gcps_dir, model: str, out_dir, *, out_ext: str = ".RPB", gcps_ext: str = ".gpkg",
                 executor=None, overwrite: bool = False, progress=None, **options) -> Dict[str, Any]:
    """Batch ``refine``: ``out_dir/<stem><out_ext>`` (``.RPB``, ``_RPC.TXT`` or ``.vrt``) and
    ``out_dir/<stem>.report.json`` per scene, from ``gcps_dir/<stem><gcps_ext>``; see :func:`run_batch`."""
    check_refine_options(**options)       # a value that makes no sense fails once, not once per scene
    out = os.fspath(out_dir)
    return run_batch(refine_scene, scenes, out,
                     lambda s: {"rpc": os.path.join(out, scene_stem(s) + out_ext),
                                "report": os.path.join(out, scene_stem(s) + ".report.json")},
                     params=dict(options, gcps_dir=os.fspath(gcps_dir), gcps_ext=gcps_ext, model=model),
                     executor=executor, overwrite=overwrite, progress=progress, command="refine")
