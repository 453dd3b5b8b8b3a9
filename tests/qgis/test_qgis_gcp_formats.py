"""Issue 24: GCP files whose format maps its own fields load in QGIS as the CLI loads them, with no field choice:
orthority's GCP GeoJSON (``ji``, pixel centres at integers), ASP ``.gcp`` and QGIS Georeferencer ``.points``. The
scene's GCPs written in each format give in QGIS the same statistics as the GeoPackage they came from, and the same
refined RPC numbers as ``gf4cal refine`` reading the same file."""
from __future__ import annotations

import json

import pytest

FORMATS = {"orthority": "gcps_ji.geojson", "asp": "gcps.gcp", "points": "gcps.points"}


@pytest.fixture(scope="module")
def gcp_files(scene, tmp_path_factory):
    from gdal_gf4cal.gcp import read_gcps, write_gcps
    files, _ = scene
    d = tmp_path_factory.mktemp("gcpfmt")
    g = read_gcps(files["gcps"])
    return {fmt: write_gcps(g, str(d / name), format=fmt, image=files["image"]) for fmt, name in FORMATS.items()}


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_gcp_file_formats_read_without_field_choice_same_numbers(run_alg, scene, gcp_files, fmt):
    from gdal_gf4cal.dem import DEM
    from gdal_gf4cal.gcp import read_gcps
    from gdal_gf4cal.workflows import assess_accuracy
    files, truth = scene
    got, fb = run_alg("gf4cal:assessaccuracy", {"INPUT": files["image"], "GCPS": gcp_files[fmt],
                                                 "DEM": files["dem"]})
    # the engine on the file as the CLI reads it (with the image: its rows, its pixel convention)
    table = read_gcps(gcp_files[fmt], dem=DEM.from_file(files["dem"]), image=files["image"])
    rep = assess_accuracy(files["image"], table, image_size=truth["size"])
    a = rep["all"]
    assert got["N"] == rep["n"] == len(table)
    for key, value in (("MEAN_SAMPLE", a["sample"]["mean"]), ("MEAN_LINE", a["line"]["mean"]),
                       ("RMS_SAMPLE", a["sample"]["rms"]), ("RMS_LINE", a["line"]["rms"]),
                       ("RMS_PLANAR", a["planar"]["rms"])):
        assert got[key] == pytest.approx(value, rel=1e-12), (fmt, key)
    # and the same GCPs as the GeoPackage they were written from (.points keeps only the control points: its
    # format has no roles, check points are written disabled)
    ref, _ = run_alg("gf4cal:assessaccuracy", {"INPUT": files["image"], "GCPS": files["gcps"], "DEM": files["dem"]})
    if fmt == "points":
        assert got["N"] == sum(r == "control" for r in truth["role"])
    else:
        assert got["N"] == ref["N"] == len(truth["ids"])
        for key in ("MEAN_SAMPLE", "MEAN_LINE", "RMS_SAMPLE", "RMS_LINE", "RMS_PLANAR"):
            assert got[key] == pytest.approx(ref[key], abs=1e-6), (fmt, key)


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_refine_in_qgis_equals_the_cli_on_the_same_gcp_file(run_alg, scene, gcp_files, fmt, tmp_path):
    from gdal_gf4cal.cli import main
    files, _ = scene
    res, _ = run_alg("gf4cal:refinerpc", {"INPUT": files["image"], "GCPS": gcp_files[fmt], "DEM": files["dem"],
                                          "MODEL": 2, "OUTPUT_RPC": str(tmp_path / "q.RPB"),
                                          "OUTPUT_GPKG": str(tmp_path / "q.gpkg")})
    assert main(["refine", files["image"], "--gcps", gcp_files[fmt], "--dem", files["dem"], "--model", "affine",
                 "--out", str(tmp_path / "c.RPB"), "--report", str(tmp_path / "c.json")]) == 0
    rep = json.loads((tmp_path / "c.json").read_text())
    st = rep["control"]["after"]
    cli_rms = (st["sample"]["rms"] ** 2 + st["line"]["rms"] ** 2) ** 0.5
    assert res["CONTROL_RMS_AFTER"] == pytest.approx(cli_rms, rel=1e-9)
    assert res["N_OUTLIERS"] == len(rep["outliers"]) == 1
    assert (tmp_path / "q.RPB").read_text() == (tmp_path / "c.RPB").read_text()
