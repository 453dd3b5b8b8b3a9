"""``gf4cal info``: real RPCs, a real DEM, JSON output, one-line errors with exit status 2."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from gdal_gf4cal.cli import main


def test_info_json_on_real_rpc_and_dem(capsys, ventoux_rpc_path, srtm_path):
    assert main(["info", str(ventoux_rpc_path), "--dem", str(srtm_path), "--geoid", "egm96", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "dimap"
    assert len(info["corners"]) == 4
    # Pleiades: 0.5 m GSD; Ventoux: corners between 200 and 1200 m ellipsoidal on SRTM.
    assert 0.45 < info["gsd_m"]["sample"] < 0.6 and 0.45 < info["gsd_m"]["line"] < 0.6
    lo, hi = info["dem_height_range_m"]
    assert 150 < lo < hi < 1300
    assert info["footprint_wkt"].startswith("POLYGON ((5.")


def test_info_text_on_tiff_with_rpc_tags(capsys, data_dir):
    assert main(["info", str(data_dir / "rpc" / "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif")]) == 0
    out = capsys.readouterr().out
    assert "128 x 128 px" in out and "approximate GSD" in out


@pytest.mark.parametrize("target, message", [("/nonexistent.tif", "no such file"), (__file__, "no RPC")])
def test_errors_are_one_line_exit_2(target, message):
    proc = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "info", target], capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.startswith("gf4cal: error:") and message in proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
