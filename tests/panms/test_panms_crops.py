"""register-pan-ms on crops of a simulated full GF7 product as delivered (issue 20, METHODS §9): five places
(inside one sub-CCD, across one edge, across two), each crop keeping its place in the product (pixel-unit
geotransform) beside the product's RPC. With default options the correction is the true field within 0.05 MS px
RMS and the jumps are found within 2 MS px of the true edges; any ``--cell`` from 4 to 128 and ``--jitter`` from 0
to 20 ends in exit 0 or a clean exit 2 (never a solver failure or an "unexpected" error).

The crops are rendered alone (seconds each); the truth comes from the simulator's public API
(:func:`~gdal_gf4cal.simulate.gf7.crop_sub_ccd_edges`) and ``ms/misregistration_truth.tif`` on the crop's grid.
"""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal.cli import main
from gdal_gf4cal.simulate.gf7 import crop_sub_ccd_edges, make_gf7_scene, write_gf7_scene

pytestmark = pytest.mark.slow

SEED = 5
#: name -> (x0, y0, w, h) in pan pixels of the full 30720^2 product (MS sub-CCD edges at MS columns 2560, 5120).
PLACES = {
    "inside_first": (4 * 1280 - 512, 4 * 3840 - 512, 1024, 1024),
    "inside_middle": (4 * 3840 - 512, 4 * 1000, 1024, 1024),
    "across_first": (4 * 2560 - 384, 4 * 6000, 1024, 1024),            # edge at crop MS column 96
    "across_second": (4 * 5120 - 640, 4 * 3000, 1024, 1024),           # edge at crop MS column 160
    "across_both": (4 * 2432, 4 * 5000, 4 * 2816, 512),                # edges at crop MS columns 128 and 2688
}


@pytest.fixture(scope="module")
def full():
    return make_gf7_scene(seed=SEED)


@pytest.fixture(scope="module", params=sorted(PLACES))
def crop(request, tmp_path_factory):
    name = request.param
    d = tmp_path_factory.mktemp(name)
    write_gf7_scene(d, seed=SEED, crop=PLACES[name], n_gcps=5, workers=2)
    return name, d


def rpc_args(d):
    """The RPCs of a crop given apart from its images (the product's, as with the CNES crops)."""
    return ["--pan-rpc", str(d / "pan" / "product.RPB"), "--ms-rpc", str(d / "ms" / "product.RPB")]


def register(d, out, *options):
    return main(["register-pan-ms", str(d / "pan" / "scene.tif"), str(d / "ms" / "scene.tif"), "--dem",
                 str(d / "dem.tif"), "--out", str(out), *rpc_args(d), *options])


def _clean_exit(rc, err):
    """Exit 0, or exit 2 with one line naming a cause (no solver failure, no "unexpected" error)."""
    if rc == 0:
        return True
    lines = err.strip().splitlines()
    bad = ("unexpected", "did not converge", "singular", "linalgerror", "traceback", "nan")
    return rc == 2 and len(lines) == 1 and not any(b in lines[0].lower() for b in bad)


def test_defaults_give_the_true_field_and_edges(crop, full, tmp_path, capsys):
    name, d = crop
    out = tmp_path / "out"
    rc = register(d, out)
    err = capsys.readouterr().err
    assert rc == 0, err
    edges = crop_sub_ccd_edges(full, PLACES[name])
    rep = json.loads((out / "report.json").read_text())
    found = [float(b) for b in rep["breaks_ms_px"]]
    # every true edge found within 2 MS px, and no jump where there is none
    assert len(found) == len(edges) and all(abs(f - e) <= 2.0 for f, e in zip(sorted(found), edges)), (found, edges)
    corr = gdal.Open(str(out / "correction.tif")).ReadAsArray()[:2].astype(float)    # (bands 3+: per MS band)
    truth = gdal.Open(str(d / "ms" / "misregistration_truth.tif")).ReadAsArray().astype(float)
    assert corr.shape == truth.shape
    cols = np.arange(truth.shape[2]) + 0.5
    away = np.all(np.abs(cols[:, None] - np.array(edges + [-99.0])[None, :]) > 2.0, axis=1)
    e = (corr - truth)[:, :, away]
    assert np.sqrt(np.mean(e[0] ** 2 + e[1] ** 2)) <= 0.05
    # ms_approx.RPB carries the whole model (its numerators refitted): no fallback to the linear term, whatever
    # rounding, and within a fraction of a pixel of it (it cannot carry the jumps)
    assert not any("linear term only" in n for n in rep["notes"]), rep["notes"]
    assert rep["ms_approx_rpc"]["rms_px"] <= 0.2 and rep["ms_approx_rpc"]["max_px"] <= 0.6


#: (--cell, --jitter) pairs per place: together every cell size from 4 to 128 and jitter from 0 to 20.
SWEEP = [("4", "0"), ("6", "20"), ("8", "3"), ("12", "1"), ("16", "20"), ("24", "8"), ("32", "0"), ("48", "12"),
         ("64", "20"), ("96", "2"), ("128", "5"), ("128", "20")]


def test_cell_and_jitter_never_end_in_a_solver_failure(crop, tmp_path, capsys):
    name, d = crop
    k = sorted(PLACES).index(name)
    failures = []
    for i, (cell, jitter) in enumerate(SWEEP[k::4]):          # the 5 places share out the 12 pairs
        rc = register(d, tmp_path / f"o{i}", "--cell", cell, "--jitter", jitter)
        err = capsys.readouterr().err
        if not _clean_exit(rc, err):
            failures.append((cell, jitter, rc, err.strip()[-300:]))
    assert not failures, failures


@pytest.mark.parametrize("crop", ["across_first"], indirect=True)
def test_more_jitter_sines_than_the_cell_rows_resolve_is_refused(crop, tmp_path, capsys):
    """``--cell 6 --jitter 20`` on a 256-line crop: ~37 usable cell rows resolve 11 sines per axis (3 rows each, 4 for
    the mean and the fit's check), not 20. Refused in one line naming the rows and what to do, nothing written (it
    ended in exit 0 with 1 and 3 sines and no word of it, or, with other matching tiles, in a singular solve)."""
    _, d = crop
    out = tmp_path / "out"
    rc = register(d, out, "--cell", "6", "--jitter", "20")
    err = capsys.readouterr().err.strip()
    assert rc == 2 and _clean_exit(rc, err), err
    m = re.search(r"--jitter 20: the usable cells lie on (\d+) rows .* use --jitter (\d+) or fewer, auto, or a "
                  r"smaller --cell$", err)
    assert m and 30 <= int(m.group(1)) <= 43 and int(m.group(2)) == (int(m.group(1)) - 4) // 3, err
    assert not out.exists()


def test_breaks_a_pixel_off_the_true_edges_still_register(crop, full, tmp_path, capsys):
    """``--breaks`` one MS px off each true edge (a user's reading of the product's layout): the short pieces this
    leaves must not end in a solver failure (the blunder step's start once trimmed a short quartic piece away, a
    "condition number" exit 2 that depended on the BLAS thread count), and the field away from the edges holds."""
    name, d = crop
    edges = crop_sub_ccd_edges(full, PLACES[name])
    if not edges:
        pytest.skip(f"{name}: no sub-CCD edge in this crop")
    x0_ms = PLACES[name][0] // 4                            # the crop's MS origin in the product
    given = ",".join(str(x0_ms + e + 1) for e in edges)
    out = tmp_path / "out"
    rc = register(d, out, "--breaks", given)
    err = capsys.readouterr().err
    assert rc == 0, err
    corr = gdal.Open(str(out / "correction.tif")).ReadAsArray()[:2].astype(float)
    truth = gdal.Open(str(d / "ms" / "misregistration_truth.tif")).ReadAsArray().astype(float)
    cols = np.arange(truth.shape[2]) + 0.5
    away = np.all(np.abs(cols[:, None] - np.array(edges + [-99.0])[None, :]) > 4.0, axis=1)
    e = (corr - truth)[:, :, away]
    assert np.sqrt(np.mean(e[0] ** 2 + e[1] ** 2)) <= 0.05
