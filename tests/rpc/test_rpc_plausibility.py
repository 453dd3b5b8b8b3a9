"""Physically impossible RPCs are refused with the reason in one line (METHODS §1, issue 11)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gdal_gf4cal import RPCModel
from gdal_gf4cal.errors import RPCFormatError
from gdal_gf4cal._rpc_poly import _EXPONENTS
from gdal_gf4cal.rpc import validate_rpc

RPB = Path(__file__).parents[1] / "data" / "rpc" / "md_dg.RPB"


@pytest.fixture(scope="module")
def md():
    return RPCModel.from_file(RPB).to_gdal_metadata()


def _with(md, **changes):
    out = dict(md)
    out.update({k: str(v) for k, v in changes.items()})
    return out


@pytest.mark.parametrize("changes,reason", [
    ({"LAT_OFF": 200}, "LAT_OFF = 200 is impossible"),
    ({"LAT_OFF": -90.5}, "LAT_OFF"),
    ({"LONG_OFF": 400}, "LONG_OFF = 400 is impossible"),
    ({"HEIGHT_OFF": 3e7}, "HEIGHT_OFF"),
    ({"LAT_SCALE": 1e-300}, "LAT_SCALE = 1e-300 is implausible"),
    ({"LONG_SCALE": 1e-300}, "LONG_SCALE"),
    ({"LINE_SCALE": 1e300}, "LINE_SCALE"),
    ({"HEIGHT_SCALE": 1e-200}, "HEIGHT_SCALE"),
])
def test_impossible_scalars_are_refused_with_the_reason(md, changes, reason):
    with pytest.raises(RPCFormatError, match=reason) as err:
        RPCModel.from_gdal_metadata(_with(md, **changes), source="x.RPB")
    assert "\n" not in str(err.value) and "x.RPB" in str(err.value)


def test_one_huge_coefficient_is_refused(md):
    """A 1e300 coefficient made ``refine`` write lineOffset = -2.2e302; now the reader refuses the RPC."""
    coeffs = md["LINE_NUM_COEFF"].split()
    coeffs[7] = "1e300"
    with pytest.raises(RPCFormatError, match="LINE_NUM_COEFF holds a coefficient of magnitude 1e\\+300"):
        RPCModel.from_gdal_metadata(_with(md, LINE_NUM_COEFF=" ".join(coeffs)))


def test_a_denominator_vanishing_in_the_ground_cube_is_refused(md):
    den = ["0"] * 20
    den[1] = "1"                     # the denominator is L: zero across the middle of the cube
    with pytest.raises(RPCFormatError, match="do not project to finite image points"):
        RPCModel.from_gdal_metadata(_with(md, SAMP_DEN_COEFF=" ".join(den)))


def test_negative_scales_stay_legal(md):
    """LAT_SCALE < 0 with the P-odd terms negated is the same camera (GDAL autotest has such a file)."""
    rpc = RPCModel.from_gdal_metadata(md)
    odd_p = [j for j, e in enumerate(_EXPONENTS) if e[1] % 2]
    flip = {}
    for name in ("LINE_NUM_COEFF", "LINE_DEN_COEFF", "SAMP_NUM_COEFF", "SAMP_DEN_COEFF"):
        c = np.array(md[name].split(), float)
        c[odd_p] *= -1
        flip[name] = " ".join(repr(v) for v in c)
    flipped = RPCModel.from_gdal_metadata(_with(md, LAT_SCALE=-rpc.lat_scale, **flip))
    assert flipped.lat_scale == -rpc.lat_scale
    lon, lat = rpc.long_off + 0.01, rpc.lat_off - 0.02
    assert np.allclose(flipped.project(lon, lat, 100.0), rpc.project(lon, lat, 100.0), atol=1e-9, rtol=0)
    assert validate_rpc(rpc) is rpc


def test_real_rpcs_pass(data_dir):
    for path in sorted((data_dir / "rpc").iterdir()):
        if path.name in ("PROVENANCE.txt", "rpc_unsupported.xml"):
            continue
        try:
            rpc = RPCModel.from_file(path)
        except RPCFormatError as exc:
            assert "not supported" in str(exc) or "no RPC" in str(exc), exc
            continue
        s, l = rpc.localize(*(np.array([v]) for v in (rpc.samp_off + 0.5, rpc.line_off + 0.5, rpc.height_off)))
        assert np.isfinite(s[0]) and np.isfinite(l[0])
