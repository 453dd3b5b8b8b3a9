"""``gf4cal bundle-adjust`` refuses bad input with one line, exit status 2 and nothing written (issue 22): fewer than
two views, no tie source, ties naming an image not given, a tie seen by one view only, ties outside their image, a
view sharing no tie with the others, a view overlapping no other (matching), matching an RPC file alone. Real
Pleiades Ventoux crops (tests/ventouxpair.py)."""
from __future__ import annotations

import shutil

import pandas as pd
import pytest

import ventouxpair as V
from gdal_gf4cal.cli import main


def _refused(capsys, args, match, out):
    rc = main(["bundle-adjust", *map(str, args), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in err and match in err, err
    assert not out.exists() or not any(out.iterdir())
    return err


def _ties(path, rows):
    pd.DataFrame(rows, columns=["point_id", "image", "sample", "line"]).to_csv(path, index=False)
    return path


GOOD = [("p1", "left", 100.0, 400.0), ("p1", "right", 120.0, 60.0), ("p2", "left", 300.0, 450.0),
        ("p2", "right", 290.0, 110.0)]


@pytest.fixture()
def views(tmp_path):
    return V.pair(tmp_path / "in")


def test_fewer_than_two_views(views, tmp_path, capsys):
    _refused(capsys, [views[0], "--match-ties", *V.dem_args()], "at least two views", tmp_path / "out")


def test_dem_sigma_not_positive(views, tmp_path, capsys):
    _refused(capsys, [*views, "--match-ties", *V.dem_args(), "--dem-sigma", "0"], "--dem-sigma 0.0: give the DEM's",
             tmp_path / "out")


def test_no_tie_source(views, tmp_path, capsys):
    _refused(capsys, [*views, *V.dem_args()], "--ties OBS", tmp_path / "out")


def test_ties_naming_an_image_not_given(views, tmp_path, capsys):
    obs = _ties(tmp_path / "t.csv", GOOD + [("p3", "left", 50.0, 420.0), ("p3", "middle", 60.0, 70.0)])
    _refused(capsys, [*views, "--ties", obs], "'middle', which is not among the images given", tmp_path / "out")


def test_tie_seen_by_one_view_only(views, tmp_path, capsys):
    obs = _ties(tmp_path / "t.csv", GOOD + [("p3", "left", 50.0, 420.0)])
    _refused(capsys, [*views, "--ties", obs], "seen by only one image", tmp_path / "out")


def test_ties_outside_their_image(views, tmp_path, capsys):
    obs = _ties(tmp_path / "t.csv", GOOD + [("p3", "left", 50.0, 420.0), ("p3", "right", 760.0, 70.0)])
    err = _refused(capsys, [*views, "--ties", obs], "lie outside their image", tmp_path / "out")
    assert "'p3' in 'right'" in err


def test_view_sharing_no_tie(views, tmp_path, capsys):
    third = tmp_path / "in" / "third.geom"          # an RPC file alone: a view with --ties
    shutil.copyfile(V.LEFT_GEOM, third)
    obs = _ties(tmp_path / "t.csv", GOOD)
    _refused(capsys, [*views, third, "--ties", obs], "third", tmp_path / "out")


def test_matching_an_rpc_file_alone(views, tmp_path, capsys):
    _refused(capsys, [views[0], V.RIGHT_GEOM, "--match-ties", *V.dem_args()], "--match-ties needs every view's pixels",
             tmp_path / "out")


def test_view_overlapping_no_other(views, tmp_path, capsys):
    far = tmp_path / "in" / "nice.tif"               # a Pleiades chip over Nice with its RPC tags: 130 km away
    shutil.copyfile(V.DATA / "rpc" / "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif", far)
    _refused(capsys, [*views, far, "--match-ties", *V.dem_args()], "nice overlaps no other view", tmp_path / "out")


def test_unknown_model_and_bad_max_pairs(views, tmp_path, capsys):
    _refused(capsys, [*views, "--match-ties", "--max-pairs", "0"], "--max-pairs 0", tmp_path / "out")
    with pytest.raises(SystemExit) as info:           # argparse: choices
        main(["bundle-adjust", *map(str, views), "--match-ties", "--model", "cubic", "--out", str(tmp_path / "o")])
    assert info.value.code == 2


def test_matching_without_a_dem_names_the_dem(views, tmp_path, capsys):
    """The Ventoux crops (B/H ~0.5, 500 px) do not overlap at the RPCs' mean height (1075 m): the refusal says the
    views were placed at that constant height and asks for a DEM."""
    _refused(capsys, [*views, "--match-ties"], "constant 1075 m: give --dem", tmp_path / "out")
