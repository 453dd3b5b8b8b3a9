"""``simulate --center`` puts the scene where truth.json says, or refuses (METHODS §10, issue 11).

``--center 0 85`` wrote a scene at lat -82/-83 while truth.json said 85: the sun-synchronous orbits' ground track
reaches |lat| ~ 82 only, ``_orbit_over`` clipped, and the orbit alignment chased the unreachable target into the
other hemisphere (zy3 died of a NaN). Now every low-orbit sensor refuses such a centre with one line, and a
reachable high-latitude centre lands exactly.
"""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.cli import main
from gdal_gf4cal.simulate import SimulationError, make_scene


@pytest.mark.parametrize("sensor", ["zy3", "hj1", "gf7"])
def test_unreachable_center_is_refused(sensor):
    with pytest.raises(SimulationError, match="cannot see the centre") as err:
        make_scene(sensor, seed=0, center=(0.0, 85.0), size=(200, 200))
    assert "|lat| <= 80" in str(err.value) and "\n" not in str(err.value)


def test_cli_center_0_85_exits_with_one_line_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "sim"
    rc = main(["simulate", "--sensor", "hj1", "--out", str(out), "--center", "0", "85", "--size", "200", "200",
               "--n-gcps", "20"])
    assert rc != 0 and not out.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot see the centre" in err[0]


@pytest.mark.parametrize("sensor", ["zy3", "hj1"])
def test_high_latitude_center_lands_where_asked(sensor):
    scene = make_scene(sensor, seed=0, center=(10.0, 79.0), size=(200, 200))
    assert tuple(scene.center) == (10.0, 79.0)
    for im in scene.images:
        w, h = im.size
        lon, lat = im.true.localize(w / 2.0, h / 2.0, float(np.mean(scene.dem.height_range())))
        # Within a few km of the centre (stereo views and crops are offset a little from it), same hemisphere.
        assert abs(lat - 79.0) < 0.2 and abs(lon - 10.0) < 0.2 / np.cos(np.radians(79.0))


@pytest.mark.parametrize("sensor", ["gf7", "zy3"])
def test_cli_center_beyond_the_orbit_names_its_reach(sensor, tmp_path, capsys):
    # Issue 19: a latitude beyond the ground track (but a valid latitude) was "not a valid (lon, lat)".
    out = tmp_path / "sim"
    rc = main(["simulate", "--sensor", sensor, "--out", str(out), "--center", "10", "87", "--size", "64", "64"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and not out.exists() and len(err) == 1
    assert "beyond the orbit's reach" in err[0] and "-82.6 to 82.6" in err[0] and "not a valid" not in err[0]
    rc = main(["simulate", "--sensor", sensor, "--out", str(out), "--center", "10", "91", "--size", "64", "64"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "not a valid (lon, lat)" in err[0]
