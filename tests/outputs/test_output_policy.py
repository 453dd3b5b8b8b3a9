"""The one output policy (gdal_gf4cal.outputs), per command: every output of every command refuses to replace an
existing file without --overwrite, outputs never collide with inputs or each other, and a failed, cancelled or
terminated run leaves no file it created (issue 10 "Must show", issue 11 "All-or-nothing outputs").

Real files throughout: seeded simulated scenes written by the simulator, the real CLI, real GDAL/OGR.
"""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal import CancelledError, InputOverwriteError, RPCModel, threads
from gdal_gf4cal.cli import main
from gdal_gf4cal.outputs import OutputSet


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def gf4(tmp_path_factory):
    """A rendered 512 x 512 GF4 scene (seed 3) with reference ortho, DEM, GCPs and cameras."""
    d = tmp_path_factory.mktemp("gf4") / "scene"
    assert main(["simulate", "--sensor", "gf4", "--out", str(d), "--size", "512", "512", "--n-gcps", "40",
                 "--seed", "3", "--render"]) == 0
    return d


@pytest.fixture(scope="module")
def zy3(tmp_path_factory):
    """A ZY3 triplet (seed 2) and a wide tie-point CSV projected from known ground points (nadir, fwd)."""
    d = tmp_path_factory.mktemp("zy3") / "scene"
    assert main(["simulate", "--sensor", "zy3", "--out", str(d), "--size", "400", "400", "--n-gcps", "20",
                 "--seed", "2"]) == 0
    truth = pd.read_csv(d / "nadir" / "gcps.csv").head(12)
    cols = {"id": truth["id"].astype(str)}
    for k, name in enumerate(("nadir", "fwd")):
        s, l = RPCModel.from_file(d / name / "scene.RPB").project(truth["lon"].to_numpy(), truth["lat"].to_numpy(),
                                                                  truth["h"].to_numpy())
        cols[f"sample_{k + 1}"], cols[f"line_{k + 1}"] = s, l
    pd.DataFrame(cols).to_csv(d / "ties.csv", index=False)
    return d


def _commands(gf4, zy3):
    """name -> (argv without output options, {output option or None: file names}) for every writing command."""
    return {
        "refine": (["refine", gf4 / "scene.tif", "--gcps", gf4 / "gcps.csv", "--model", "affine"],
                   {"--out": "refined.vrt", "--report": "report.json", "--residuals": "res.gpkg",
                    "--plot": "res.png"}),
        "calibrate-lookangle": (["calibrate-lookangle", "--rpc", gf4 / "scene.RPB", "--gcps", gf4 / "gcps.csv",
                                 "--camera", gf4 / "camera_current.json", "--image", gf4 / "scene.tif"],
                                {None: ["camera_new.json", "scene.RPB", "scene.vrt", "residuals.gpkg",
                                        "residuals.png", "report.json"]}),
        "apply-calibration": (["apply-calibration", gf4 / "scene.tif", "--current", gf4 / "camera_current.json",
                               "--new", gf4 / "camera_true.json"],
                              {None: ["scene.RPB", "scene.vrt", "report.json"]}),
        "intersect": (["intersect", "--rpc", zy3 / "nadir" / "scene.RPB", zy3 / "fwd" / "scene.RPB",
                       "--points", zy3 / "ties.csv"], {"--out": "points.gpkg", "--report": "report.json"}),
        "collect-gcps": (["collect-gcps", gf4 / "scene.tif", "--reference", gf4 / "reference.tif", "--dem",
                          gf4 / "dem.tif", "--spacing", "128", "--workers", "1"], {"--out": "collected.gpkg"}),
    }


def _argv(base, outputs, out_dir: Path):
    argv = [str(a) for a in base]
    for opt, name in outputs.items():
        if opt is None:
            argv += ["--out", str(out_dir)]
        else:
            argv += [opt, str(out_dir / name)]
    return argv


def _files(outputs):
    names = []
    for name in outputs.values():
        names += name if isinstance(name, list) else [name]
    return names


def _snapshot(folder: Path):
    """{relative path: sha256} of every file under ``folder`` (hidden temporaries included)."""
    if not folder.exists():
        return None
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            out[str(p.relative_to(folder))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


COMMANDS = ["refine", "calibrate-lookangle", "apply-calibration", "intersect", "collect-gcps"]


# ------------------------------------------------------------------------------------------------ per command
@pytest.mark.parametrize("command", COMMANDS)
def test_every_output_refuses_an_existing_file_without_overwrite(gf4, zy3, tmp_path, capsys, command):
    base, outputs = _commands(gf4, zy3)[command]
    out_dir = tmp_path / "out"
    inputs_before = _snapshot(gf4), _snapshot(zy3)
    assert main(_argv(base, outputs, out_dir)) == 0, capsys.readouterr().err
    names = _files(outputs)
    assert sorted(os.listdir(out_dir)) == sorted(names)          # every output, no temporary left
    full = _snapshot(out_dir)
    # Each output alone: refused before any work, that file unchanged, nothing else created.
    for name in names:
        for other in names:
            if other != name:
                (out_dir / other).unlink()
        capsys.readouterr()
        assert main(_argv(base, outputs, out_dir)) == 2
        err = capsys.readouterr().err
        assert "exists" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1, err
        assert _snapshot(out_dir) == {name: full[name]}
        assert main(_argv(base, outputs, out_dir) + ["--overwrite"]) == 0
        assert sorted(os.listdir(out_dir)) == sorted(names)
        full = _snapshot(out_dir)
    assert (_snapshot(gf4), _snapshot(zy3)) == inputs_before       # inputs never modified


class _CancelAtCommit:
    """A progress callback whose user cancels once every output is written to its temporary (the worst moment)."""

    def __call__(self, fraction, message=""):
        pass

    def is_cancelled(self):
        return True


def _workflow_calls(gf4, zy3, out: Path):
    from gdal_gf4cal import workflows as wf
    return {
        "refine": lambda p: wf.refine_rpc(gf4 / "scene.tif", gf4 / "gcps.csv", "affine", out=out / "r.vrt",
                                          report=out / "r.json", residuals=out / "r.gpkg", plot=out / "r.png",
                                          progress=p),
        "calibrate-lookangle": lambda p: wf.calibrate_lookangle_files(gf4 / "scene.RPB", gf4 / "gcps.csv",
                                                                      gf4 / "camera_current.json", out,
                                                                      image=gf4 / "scene.tif", progress=p),
        "apply-calibration": lambda p: wf.apply_calibration(gf4 / "camera_current.json", gf4 / "camera_true.json",
                                                            [gf4 / "scene.tif"], out, progress=p),
        "intersect": lambda p: wf.intersect_files([zy3 / "nadir" / "scene.RPB", zy3 / "fwd" / "scene.RPB"],
                                                  zy3 / "ties.csv", out=out / "p.gpkg", report=out / "p.json",
                                                  progress=p),
        "collect-gcps": lambda p: wf.collect_gcps_file(gf4 / "scene.tif", gf4 / "reference.tif", gf4 / "dem.tif",
                                                       out / "c.gpkg", spacing_px=128, workers=1, progress=p),
        "assess": lambda p: wf.assess_accuracy(gf4 / "scene.tif", gf4 / "gcps.csv", residuals=out / "a.gpkg",
                                               plot=out / "a.png", report=out / "a.json", progress=p),
    }


@pytest.mark.parametrize("command", COMMANDS + ["assess"])
def test_cancel_after_all_outputs_were_written_leaves_no_file(gf4, zy3, tmp_path, command):
    out = tmp_path / "new" / "out"                  # two folders the run creates, removed again
    before = _snapshot(tmp_path)
    with pytest.raises(CancelledError):
        _workflow_calls(gf4, zy3, out)[command](_CancelAtCommit())
    assert _snapshot(tmp_path) == before == {}
    assert not (tmp_path / "new").exists()


@pytest.mark.skipif(threads.blas_threads() is None, reason="NumPy's BLAS is not OpenBLAS")
@pytest.mark.parametrize("command", COMMANDS + ["assess", "ortho"])
def test_workflows_compute_blas_on_the_calling_thread(gf4, zy3, tmp_path, command):
    """Every workflow called from Python (no ``gf4cal`` command, no ``threads.limit``) holds BLAS on the calling
    thread from start to end, as its command does: the same numbers as the command, and no OpenBLAS thread left
    spinning on another core after a product. Every progress report comes from inside that scope, closed after."""
    from gdal_gf4cal import workflows as wf
    calls = dict(_workflow_calls(gf4, zy3, tmp_path / "out"),
                 ortho=lambda p: wf.orthorectify(gf4 / "scene.tif", dem=gf4 / "dem.tif", out=tmp_path / "o.tif",
                                                 progress=p))
    assert not threads.blas_is_serial()
    seen = []
    calls[command](lambda f, m="": seen.append(threads.blas_is_serial()))
    assert len(seen) >= 2 and all(seen)
    assert not threads.blas_is_serial()


@pytest.mark.parametrize("command", ["refine", "calibrate-lookangle", "assess"])
def test_bad_gcp_file_leaves_no_file(gf4, zy3, tmp_path, command):
    bad = tmp_path / "bad" / "gcps.csv"
    bad.parent.mkdir()
    bad.write_text("id,lon,lat,h,sample,line\n1,88.0,31.0,4000,abc,100\n2,88.1,31.0,4000,200,100\n")
    g = {"refine": lambda o: main(["refine", str(gf4 / "scene.tif"), "--gcps", str(bad), "--model", "affine",
                                   "--out", str(o / "r.RPB"), "--report", str(o / "r.json"),
                                   "--residuals", str(o / "r.gpkg"), "--plot", str(o / "r.png")]),
         "calibrate-lookangle": lambda o: main(["calibrate-lookangle", "--rpc", str(gf4 / "scene.RPB"), "--gcps",
                                                str(bad), "--camera", str(gf4 / "camera_current.json"), "--out",
                                                str(o)]),
         "assess": None}[command]
    out = tmp_path / "out"
    if g is None:
        from gdal_gf4cal import Gf4calError
        from gdal_gf4cal.workflows import assess_accuracy
        with pytest.raises(Gf4calError):
            assess_accuracy(gf4 / "scene.tif", bad, residuals=out / "a.gpkg", report=out / "a.json")
    else:
        assert g(out) == 2
    assert not out.exists()
    assert sorted(os.listdir(tmp_path / "bad")) == ["gcps.csv"]


# ------------------------------------------------------------------------------------------------ collisions
def test_two_outputs_that_are_one_file_are_refused_before_any_work(gf4, tmp_path, capsys):
    target = tmp_path / "X.RPB"
    assert main(["refine", str(gf4 / "scene.tif"), "--gcps", str(gf4 / "gcps.csv"), "--model", "affine",
                 "--out", str(target), "--report", str(target)]) == 2
    assert "same file" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


def test_output_through_a_symlink_or_hard_link_to_an_input_is_refused(gf4, tmp_path):
    link = tmp_path / "link.csv"
    os.symlink(gf4 / "gcps.csv", link)
    hard = tmp_path / "hard.json"
    os.link(gf4 / "camera_current.json", hard)
    outs = OutputSet([gf4 / "gcps.csv", gf4 / "camera_current.json", gf4 / "scene.tif"], overwrite=True)
    for path in (link, hard, gf4 / "scene.RPB", tmp_path / ".." / tmp_path.name / "link.csv"):
        with pytest.raises(InputOverwriteError):
            outs.declare(str(path), path)


def test_overwrite_replaces_all_outputs_together_and_restores_them_on_failure(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    b.write_text("old b")
    outs = OutputSet([], overwrite=True)
    ta, tb = outs.declare("a", a), outs.declare("b", b)
    with pytest.raises(KeyboardInterrupt):
        with outs:
            Path(ta).write_text("new a")
            raise KeyboardInterrupt
    assert (a.read_text(), b.read_text()) == ("old a", "old b")
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "b.txt"]
    outs = OutputSet([], overwrite=True)
    ta, tb = outs.declare("a", a), outs.declare("b", b)
    with outs:
        Path(ta).write_text("new a")
        Path(tb).write_text("new b")
    assert (a.read_text(), b.read_text()) == ("new a", "new b")
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "b.txt"]


def test_an_output_that_was_not_written_fails_the_whole_set(tmp_path):
    outs = OutputSet([])
    ta = outs.declare("a", tmp_path / "sub" / "a.txt")
    outs.declare("b", tmp_path / "sub" / "b.txt")
    with pytest.raises(Exception, match="was not written"):
        with outs:
            Path(ta).write_text("a")
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------------------------------------ folder outputs
@pytest.mark.parametrize("command", [["simulate", "--sensor", "gf4", "--size", "256", "256", "--n-gcps", "20"],
                                     ["experiment", "hj1", "--quiet"]])
def test_folder_commands_refuse_a_non_empty_folder_without_overwrite(tmp_path, capsys, command):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(command + ["--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "not empty" in err and "--overwrite" in err
    assert os.listdir(out) == ["keep.txt"]


def test_simulate_cancelled_removes_the_folder_it_created(tmp_path):
    from gdal_gf4cal.workflows import simulate_scene

    def cancel(fraction, message=""):
        if fraction > 0.5:
            raise CancelledError("cancelled by the test")

    with pytest.raises(CancelledError):
        simulate_scene("gf4", tmp_path / "made" / "scene", size=(256, 256), n_gcps=20, render=True,
                       progress=cancel)
    assert os.listdir(tmp_path) == []


def test_simulate_overwrite_keeps_the_users_files_when_cancelled(tmp_path):
    from gdal_gf4cal.workflows import simulate_scene
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(CancelledError):
        simulate_scene("gf4", tmp_path, overwrite=True, size=(256, 256), n_gcps=20, progress=_CancelAtCommit())
    assert os.listdir(tmp_path) == ["keep.txt"]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_mid_run_exits_130_and_leaves_no_file(tmp_path, sig):
    out = tmp_path / "scene"
    proc = subprocess.Popen([sys.executable, "-m", "gdal_gf4cal.cli", "simulate", "--sensor", "gf4", "--out", str(out),
                             "--size", "2000", "2000", "--render", "--workers", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not out.exists() and time.monotonic() < deadline:     # wait until the run has started writing
        time.sleep(0.05)
    time.sleep(0.5)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------------------------------------ CLI errors
def test_unexpected_exception_is_one_line_and_debug_zero_hides_the_traceback(tmp_path):
    bad = tmp_path / "camera.json"
    bad.write_text(json.dumps({"model": "lookangle-cubic"}))
    for debug, traceback in (("0", False), ("1", True)):
        proc = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "apply-calibration", str(bad), "--current",
                               str(bad), "--new", str(bad), "--out", str(tmp_path / "o")], capture_output=True,
                              text=True, env=dict(os.environ, GF4CAL_DEBUG=debug))
        assert ("Traceback" in proc.stderr) is traceback, proc.stderr
        if not traceback:
            assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not (tmp_path / "o").exists()


def test_report_warnings_reach_the_cli(gf4, tmp_path, capsys):
    """``report["warnings"]`` (engine warnings included) are printed as ``gf4cal: warning:`` lines."""
    import warnings
    from gdal_gf4cal.cli import print_warnings
    print_warnings({"warnings": ["check points got worse after compensation"]})
    assert capsys.readouterr().err == "gf4cal: warning: check points got worse after compensation\n"
    from gdal_gf4cal.workflows._common import collect_warnings
    got = []
    with collect_warnings(got):
        warnings.warn("layout is weak", UserWarning)
    assert got == ["layout is weak"]
    rep = __import__("gdal_gf4cal").workflows.refine_rpc(gf4 / "scene.tif", gf4 / "gcps.csv", "affine",
                                                         out=tmp_path / "r.RPB")
    assert isinstance(rep["warnings"], list)
    assert np.isfinite(rep["control"]["after"]["sample"]["rms"])


# ------------------------------------------------------------------------------------------------ report.json
def _nulls(obj, path="$"):
    """Every place where a JSON document holds null."""
    if obj is None:
        return [path]
    if isinstance(obj, dict):
        return [p for k, v in obj.items() for p in _nulls(v, f"{path}.{k}")]
    if isinstance(obj, list):
        return [p for i, v in enumerate(obj) for p in _nulls(v, f"{path}[{i}]")]
    return []


@pytest.mark.parametrize("command", ["refine", "calibrate-lookangle", "apply-calibration", "intersect", "assess"])
def test_every_report_json_holds_no_null(gf4, zy3, tmp_path, command):
    """Absent sections instead of nulls (issue 15), for every workflow that writes a report: walk the file."""
    out = tmp_path / "o"
    _workflow_calls(gf4, zy3, out)[command](None)
    reports = [p for p in out.iterdir() if p.name in ("r.json", "report.json", "p.json", "a.json")]
    assert len(reports) == 1
    rep = json.loads(reports[0].read_text())
    assert rep and _nulls(rep) == []


def test_report_without_check_points_has_no_check_section(gf4, tmp_path, capsys):
    """Control points only: `refine` and `assess` leave the check section out of report.json (no "check": null,
    no statistics of no points) and still print their table."""
    from gdal_gf4cal.workflows import assess_accuracy
    g = pd.read_csv(gf4 / "gcps.csv")
    g["role"] = "control"
    g.to_csv(tmp_path / "ctl.csv", index=False)
    assert main(["refine", str(gf4 / "scene.tif"), "--gcps", str(tmp_path / "ctl.csv"), "--model", "translation",
                 "--out", str(tmp_path / "r.RPB"), "--report", str(tmp_path / "r.json")]) == 0
    assert "control" in capsys.readouterr().out
    assess_accuracy(gf4 / "scene.tif", tmp_path / "ctl.csv", report=tmp_path / "a.json")
    rep = json.loads((tmp_path / "r.json").read_text())
    assert "check" not in rep and rep["control"]["after"]["n"] > 0 and _nulls(rep) == []
    rep = json.loads((tmp_path / "a.json").read_text())      # assess: "all", and a role only when roles differ
    assert "check" not in rep and rep["all"]["n"] > 0 and _nulls(rep) == []
