"""The built plugin in Debian's qgis_process (shell-level test): build, enable, run gf4cal:refinerpc.

Debian's ``qgis_process`` wrapper sources /etc/default/qgis and breaks on it, so ``qgis_process.bin`` is called
directly, with /usr/bin first on PATH, offscreen Qt and a temporary HOME (the user's QGIS profile is not touched).
The plugin's vendored engine is what runs: PYTHONPATH is cleared and the working directory is a temporary folder.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
QGIS_PROCESS = shutil.which("qgis_process.bin", path="/usr/bin") or shutil.which("qgis_process.bin")


@pytest.fixture(scope="module")
def qgis_env(tmp_path_factory):
    if QGIS_PROCESS is None:
        if os.environ.get("CI"):
            pytest.fail("qgis_process.bin not found (apt install qgis)")
        pytest.skip("qgis_process.bin not found (apt install qgis)")
    base = tmp_path_factory.mktemp("qgis_process")
    plugins, dist, home = base / "plugins", base / "dist", base / "home"
    home.mkdir()
    build = subprocess.run([sys.executable, os.path.join(ROOT, "tools", "build_plugin.py"),
                            "--build-dir", str(plugins), "--dist-dir", str(dist)],
                           capture_output=True, text=True, timeout=120)
    assert build.returncode == 0, build.stderr
    assert (dist / "gdal_gf4cal_plugin.zip").exists()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "QGIS", "VIRTUAL_ENV"))}
    env.update({"HOME": str(home), "QGIS_PLUGINPATH": str(plugins), "QT_QPA_PLATFORM": "offscreen",
                "PATH": "/usr/bin:/bin:" + env.get("PATH", ""), "XDG_RUNTIME_DIR": tempfile.mkdtemp(),
                "PYTHONWARNINGS": "ignore"})

    def run(*args, check=True):
        proc = subprocess.run([QGIS_PROCESS, *args], env=env, cwd=str(base), capture_output=True, text=True,
                              timeout=300)
        if check:
            assert proc.returncode == 0, f"{args}: rc {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
        return proc

    enable = run("plugins", "enable", "gdal_gf4cal_plugin")
    assert "gdal_gf4cal_plugin" in enable.stdout
    return run, base


def test_plugin_lists_the_algorithms(qgis_env):
    run, _ = qgis_env
    out = run("list").stdout
    assert "GF4 RPC calibration" in out
    for alg in ("gf4cal:rpcinfo", "gf4cal:simulatescene", "gf4cal:refinerpc", "gf4cal:calibratelookangle",
                "gf4cal:applycalibration", "gf4cal:assessaccuracy", "gf4cal:collectgcps"):
        assert alg in out


def test_qgis_process_refinerpc_writes_the_geopackage(qgis_env, scene):
    from osgeo import ogr
    run, base = qgis_env
    files, truth = scene
    out_rpc, out_gpkg = base / "refined_RPC.TXT", base / "residuals.gpkg"
    proc = run("--json", "run", "gf4cal:refinerpc", "--", f"INPUT={files['image']}", f"GCPS={files['gcps']}",
               "MODEL=2", f"OUTPUT_RPC={out_rpc}", f"OUTPUT_GPKG={out_gpkg}")
    results = json.loads(proc.stdout[proc.stdout.index("{"):])["results"]
    assert results["OUTPUT_GPKG"] == str(out_gpkg) and results["N_OUTLIERS"] == 1
    assert results["CHECK_RMS_AFTER"] < 1.5 * 2 ** 0.5 * truth["noise_px"] < results["CHECK_RMS_BEFORE"]
    ds = ogr.Open(str(out_gpkg))
    assert ds.GetLayerByName("gcps").GetFeatureCount() == len(truth["ids"])
    assert ds.GetLayerByName("residual_vectors").GetFeatureCount() == len(truth["ids"])
    assert ds.GetLayerByName("layer_styles").GetFeatureCount() >= 3
    assert out_rpc.exists()


def test_qgis_process_bad_input_fails_cleanly(qgis_env, scene):
    run, base = qgis_env
    files, _ = scene
    out = base / "bad"
    out.mkdir()
    proc = run("run", "gf4cal:refinerpc", "--", f"INPUT={files['norpc']}", f"GCPS={files['gcps']}", "MODEL=2",
               f"OUTPUT_RPC={out / 'r.RPB'}", f"OUTPUT_GPKG={out / 'r.gpkg'}", check=False)
    assert proc.returncode != 0
    assert "no RPC metadata" in proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    assert os.listdir(out) == []


def test_plugin_zip_layout_and_metadata(tmp_path):
    import configparser
    import zipfile
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "tools", "build_plugin.py"), "--build-dir",
                           str(tmp_path / "b"), "--dist-dir", str(tmp_path / "d")], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    with zipfile.ZipFile(tmp_path / "d" / "gdal_gf4cal_plugin.zip") as zf:
        names = set(zf.namelist())
        md_text = zf.read("gdal_gf4cal_plugin/metadata.txt").decode()
        init = zf.read("gdal_gf4cal_plugin/__init__.py").decode()
    for required in ("gdal_gf4cal_plugin/__init__.py", "gdal_gf4cal_plugin/plugin.py",
                     "gdal_gf4cal_plugin/processing_provider/provider.py",
                     "gdal_gf4cal_plugin/processing_provider/algorithms/refinerpc.py",
                     "gdal_gf4cal_plugin/libs/gdal_gf4cal/__init__.py",
                     "gdal_gf4cal_plugin/libs/gdal_gf4cal/report/__init__.py",
                         "gdal_gf4cal_plugin/libs/gdal_gf4cal/workflows/refine.py"):
        assert required in names, required
    assert not any("__pycache__" in n or n.endswith(".pyc") for n in names)
    assert "def classFactory(iface)" in init
    cp = configparser.ConfigParser(interpolation=None)
    cp.read_string(md_text)
    md = cp["general"]
    assert md["qgisMinimumVersion"] == "3.22" and md["version"] == "0.1.0"
    assert md["hasProcessingProvider"] == "yes" and md["license"] == "GPL-2.0-or-later"
    for key in ("name", "description", "about", "author", "email", "tracker", "repository", "category", "tags"):
        assert md.get(key), key
    # the unzipped folder is the same plugin
    assert (tmp_path / "b" / "gdal_gf4cal_plugin" / "metadata.txt").read_text() == md_text
    # reproducible: a second build gives the same zip bytes
    first = (tmp_path / "d" / "gdal_gf4cal_plugin.zip").read_bytes()
    subprocess.run([sys.executable, os.path.join(ROOT, "tools", "build_plugin.py"), "--build-dir",
                    str(tmp_path / "b"), "--dist-dir", str(tmp_path / "d")], check=True, capture_output=True)
    assert (tmp_path / "d" / "gdal_gf4cal_plugin.zip").read_bytes() == first
