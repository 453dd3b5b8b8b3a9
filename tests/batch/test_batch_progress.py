"""Issue 14: progress over scenes AND inside them (tiles), on threads and on a Dask LocalCluster, at the API and
in the CLI's bar; cancel mid-batch: finished scenes stay, running ones leave no file, the summary says so."""
from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import time

import numpy as np
import pytest

from gdal_gf4cal.batch import run_batch
from gdal_gf4cal.errors import CancelledError
from gdal_gf4cal.executors import get_executor

HERE = os.path.dirname(os.path.abspath(__file__))


def _slow_scene(scene, outputs, *, steps, overwrite=False, progress=None):
    """A scene function writing its output line by line (a partial file while it runs), reporting each step."""
    from gdal_gf4cal.outputs import OutputSet
    outs = OutputSet([scene], overwrite=overwrite, cancelled=getattr(progress, "is_cancelled", None))
    outs.declare("out", outputs["out"])
    with outs:
        with open(outs.tmp("out"), "w") as fh:
            for k in range(steps):
                fh.write(f"{k}\n")
                fh.flush()
                progress((k + 1) / steps, f"step {k + 1}")
                time.sleep(0.1)
    return {"steps": steps}


def _scenes(tmp_path, n):
    paths = []
    for k in range(n):
        p = tmp_path / f"s{k}.txt"
        p.write_text(str(k))
        paths.append(str(p))
    return paths


def _outputs_for(out):
    return lambda s: {"out": str(out / os.path.basename(s))}


@pytest.mark.parametrize("spec", ["threads:2", "local:2"])
def test_progress_inside_running_scenes_reaches_the_caller(tmp_path, spec):
    """Two 2-s scenes on two workers: without the scenes' own progress the caller would only see 0, 1/2 and 1;
    it sees the steps in between (Dask: through worker events)."""
    seen = []
    out = tmp_path / "out"
    with get_executor(spec) as ex:
        rep = run_batch(_slow_scene, _scenes(tmp_path, 2), out, _outputs_for(out), params={"steps": 20},
                        executor=ex, progress=lambda f, m="": seen.append(f))
    assert rep["counts"]["ok"] == 2
    between = [f for f in seen if 0.05 < f < 0.95 and abs(f - 0.5) > 0.02]
    assert len(set(np.round(between, 3))) >= 3, seen
    assert seen[-1] == 1.0


@pytest.mark.parametrize("spec", ["serial", "threads:2", "local:2"])
def test_cancel_mid_batch_running_scenes_leave_nothing(tmp_path, spec):
    out = tmp_path / "out"
    scenes = _scenes(tmp_path, 5)

    def progress(f, m=""):
        # Cancel once the batch is past 30 %: serially that is inside the second scene.
        if f > 0.3:
            raise CancelledError("cancelled by the test")

    with get_executor(spec) as ex:
        with pytest.raises(CancelledError):
            run_batch(_slow_scene, scenes, out, _outputs_for(out), params={"steps": 15}, executor=ex,
                      progress=progress)
    summary = json.loads((out / "batch_summary.json").read_text())
    assert summary["cancelled"] is True
    statuses = {os.path.basename(r["scene"]): r["status"] for r in summary["scenes"]}
    assert set(statuses.values()) <= {"ok", "cancelled"} and statuses["s4.txt"] == "cancelled"
    if spec == "serial":
        assert [statuses[f"s{k}.txt"] for k in range(5)] == ["ok"] + ["cancelled"] * 4
    files = sorted(os.listdir(out))   # hidden temporaries included
    assert files == sorted(["batch_summary.csv", "batch_summary.json"]
                           + [s for s, st in statuses.items() if st == "ok"]), files
    for s, st in statuses.items():
        if st == "ok":
            assert (out / s).read_text().splitlines() == [str(k) for k in range(15)]


def _run_cli_on_a_terminal(args, cwd):
    """Run ``gf4cal ARGS`` with stderr on a pseudo-terminal (so the CLI draws its bar); returns (rc, stderr)."""
    import pty
    master, slave = pty.openpty()
    env = dict(os.environ, COLUMNS="120", PYTHONPATH=os.pathsep.join([os.path.dirname(HERE), HERE]))
    proc = subprocess.Popen([sys.executable, "-m", "gdal_gf4cal.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=slave, cwd=cwd, env=env)
    os.close(slave)
    chunks = []
    while True:
        r, _, _ = select.select([master], [], [], 0.2)
        if r:
            try:
                data = os.read(master, 65536)
            except OSError:
                break
            if not data:
                break
            chunks.append(data)
        elif proc.poll() is not None:
            break
    proc.wait(timeout=120)
    os.close(master)
    return proc.returncode, b"".join(chunks).decode("utf-8", "replace")


@pytest.mark.slow
def test_cli_progress_bar_over_tiles_and_scenes_on_a_local_cluster(tmp_path):
    """collect-gcps on a LocalCluster draws its bar over tiles (one scene) and over scenes (a batch)."""
    from osgeo import gdal
    from matchscene import build_scene, error_affine
    scenes = []
    for k, shift in enumerate([(6.2, -4.4), (-3.5, 5.1)]):
        d = tmp_path / f"s{k}"
        d.mkdir()
        sc = build_scene(d, texture="pleiades", size=(320, 320), seed=3, error=error_affine(shift=shift))
        gdal.Translate(str(tmp_path / f"scene{k}.tif"), sc.image)
        sc.rpc.write_rpb(str(tmp_path / f"scene{k}.RPB"))
        scenes.append(str(tmp_path / f"scene{k}.tif"))
    common = ["--reference", sc.reference, "--dem", sc.dem_path, "--dask", "local:2"]
    rc, err = _run_cli_on_a_terminal(["collect-gcps", scenes[0], *common, "--spacing", "24", "--out",
                                      str(tmp_path / "one.gpkg")], str(tmp_path))
    assert rc == 0, err
    tiles = sorted({m for m in __import__("re").findall(r"tile (\d+)/(\d+)", err)})
    assert len(tiles) >= 2 and all(b == tiles[0][1] for _, b in tiles) and int(tiles[0][1]) >= 2, err
    assert "100%" in err
    rc, err = _run_cli_on_a_terminal(["collect-gcps", *scenes, *common, "--spacing", "40", "--out",
                                      str(tmp_path / "many")], str(tmp_path))
    assert rc == 0, err
    assert "scene 1/2" in err and "scene 2/2" in err and "100%" in err, err
    assert (tmp_path / "many" / "scene0.gpkg").is_file() and (tmp_path / "many" / "scene1.gpkg").is_file()
