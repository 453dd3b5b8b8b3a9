"""LookAngleModel: terms, normalisation, inversion, nominal constructor, camera files (METHODS §5 eq. 3)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gdal_gf4cal import LookAngleModel
from gdal_gf4cal.camera import CameraFormatError, lookangle_terms


@pytest.fixture
def distorted():
    """A 10240 x 10240 camera with rotation, shift and a cubic radial distortion of a few pixels at the edges."""
    return LookAngleModel.from_nominal((10240, 10240), 50.0, 9e-6, principal_point=(5100.0, 5150.0),
                                       radial_k1=400.0)


def test_seventh_term_is_s2_l():
    """METHODS §5 fixes the paper's eq. 4 typo: the seventh term is s² l, the eighth s l²."""
    t = lookangle_terms(2.0, 3.0)[:, 0]
    np.testing.assert_array_equal(t, [1, 2, 3, 6, 4, 9, 12, 18, 8, 27])


def test_nominal_camera_is_a_pinhole():
    cam = LookAngleModel.from_nominal((1000, 800), 1.0, 1e-5)
    tx, ty = cam.tan_angles(np.array([500.0, 600.0]), np.array([400.0, 450.0]))
    np.testing.assert_allclose(tx, [0.0, 1e-3], atol=1e-15)
    np.testing.assert_allclose(ty, [0.0, 5e-4], atol=1e-15)
    dx, dy = cam.angular_pixel_size(500.0, 400.0)
    assert dx == pytest.approx(1e-5) and dy == pytest.approx(1e-5)


def test_radial_distortion_is_represented_exactly(distorted):
    s, l = np.meshgrid(np.linspace(0, 10240, 7), np.linspace(0, 10240, 7))
    k = 9e-6 / 50.0
    x, y = (s - 5100.0) * k, (l - 5150.0) * k
    r2 = x * x + y * y
    tx, ty = distorted.tan_angles(s, l)
    np.testing.assert_allclose(tx, x * (1 + 400.0 * r2), atol=1e-14)
    np.testing.assert_allclose(ty, y * (1 + 400.0 * r2), atol=1e-14)
    # Several pixels of distortion at the corner, as on GF4 (METHODS §10).
    assert 3 < abs(tx[0, 0] - x[0, 0]) / k < 10


def test_detector_of_inverts_tan_angles(distorted):
    rng = np.random.default_rng(0)
    s, l = rng.uniform(0, 10240, (2, 5000))
    s2, l2 = distorted.detector_of(*distorted.tan_angles(s, l))
    assert np.max(np.hypot(s2 - s, l2 - l)) < 1e-8


def test_jacobian_matches_finite_differences(distorted):
    s, l = np.array([100.0, 5000.0, 10000.0]), np.array([9000.0, 5000.0, 300.0])
    J = distorted.jacobian(s, l)
    e = 1e-3
    for k, (ds, dl) in enumerate(((e, 0), (0, e))):
        p = np.array(distorted.tan_angles(s + ds, l + dl))
        m = np.array(distorted.tan_angles(s - ds, l - dl))
        np.testing.assert_allclose(J[:, :, k], ((p - m) / (2 * e)).T, rtol=1e-7, atol=1e-15)


def test_normalised_coefficients_round_trip(distorted):
    xn, yn = distorted.normalised_coefficients()
    again = LookAngleModel.from_normalised_coefficients(distorted.size, xn, yn)
    s, l = np.meshgrid(np.linspace(0, 10240, 9), np.linspace(0, 10240, 9))
    np.testing.assert_allclose(np.array(again.tan_angles(s, l)), np.array(distorted.tan_angles(s, l)),
                               rtol=0, atol=1e-15)   # 1e-15 rad = 1e-8 px


def test_json_round_trip_and_errors(distorted, tmp_path):
    path = distorted.to_json(tmp_path / "camera.json")
    with open(path) as fh:
        d = json.load(fh)
    assert d["model"] == "lookangle-cubic" and d["size"] == [10240, 10240] and len(d["x"]) == 10
    again = LookAngleModel.from_json(path)
    np.testing.assert_array_equal(again.x, distorted.x)
    d["model"] = "polynomial"
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(CameraFormatError, match="lookangle-cubic"):
        LookAngleModel.from_json(tmp_path / "bad.json")
    (tmp_path / "short.json").write_text(json.dumps({"model": "lookangle-cubic", "size": [5, 5], "x": [0] * 9,
                                                     "y": [0] * 10}))
    with pytest.raises(CameraFormatError, match="10 finite"):
        LookAngleModel.from_json(tmp_path / "short.json")
    with pytest.raises(CameraFormatError, match="not found"):
        LookAngleModel.from_json(tmp_path / "none.json")


def test_camera_file_errors_are_project_errors(distorted, tmp_path):
    from gdal_gf4cal import Gf4calError
    path = distorted.to_json(tmp_path / "camera.json")
    import os
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(path).st_mode & 0o777 == 0o666 & ~umask      # not mkstemp's private 0600
    with pytest.raises(Gf4calError, match="exists"):
        distorted.to_json(path, overwrite=False)
    (tmp_path / "binary.json").write_bytes(b"\xff\xfe\x00\x01garbage")
    with pytest.raises(CameraFormatError, match="binary.json"):
        LookAngleModel.from_json(tmp_path / "binary.json")
    with pytest.raises(CameraFormatError, match="cannot read"):
        LookAngleModel.from_json(tmp_path)            # a folder
