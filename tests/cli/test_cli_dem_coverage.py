"""Issue 24: the DEM-coverage refusal names what to do with options that exist: a GCP without height beyond the DEM
stops `gf4cal refine` in one line (exit 2) that asks for a covering DEM and suggests no fallback height flag."""
from __future__ import annotations

import subprocess
import sys

import pandas as pd


def test_gcp_beyond_the_dem_refused_in_one_line_naming_no_missing_flag(tmp_path):
    from gdal_gf4cal.simulate import write_scene
    write_scene("gf4", tmp_path / "s", seed=2, size=(256, 256), n_gcps=12)
    g = pd.read_csv(tmp_path / "s" / "gcps.csv").drop(columns=["h"])
    g.loc[0, "lon"] += 20.0                         # far beyond the DEM (and the scene)
    g.to_csv(tmp_path / "noh.csv", index=False)
    proc = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "refine", str(tmp_path / "s" / "scene.tif"),
                           "--gcps", str(tmp_path / "noh.csv"), "--dem", str(tmp_path / "s" / "dem.tif"),
                           "--no-plausibility-check", "--out", str(tmp_path / "o.RPB")], capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip() and "warning" not in ln and "note" not in ln]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "DEM" in lines[0] and "covers the scene" in lines[0]
    assert "nodata=" not in lines[0] and "fallback" not in lines[0]
    assert not (tmp_path / "o.RPB").exists()
