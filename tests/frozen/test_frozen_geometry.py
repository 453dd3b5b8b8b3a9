"""Frozen numbers of look-angle calibration (METHODS §5), RPC fitting (§3) and forward intersection (§7)."""
from __future__ import annotations

import pytest

from .compare import assert_close, load
from .scenes import K, compute_intersection, compute_lookangle, compute_rpc_fit, gf4_scene


@pytest.fixture(scope="module")
def scene():
    return gf4_scene()


def test_lookangle_frozen(scene):
    want, got = load("lookangle"), compute_lookangle(scene)
    assert got["outliers"] == want["outliers"]
    assert got["residual_rms"]["n_outliers"] == want["residual_rms"]["n_outliers"] == 8
    # Tan-angles on a grid: 1e-6 px of look angle = 1e-6 * K tan units; coefficients: relative 1e-6 (raw units
    # span ~20 orders of magnitude, so only a relative tolerance is meaningful).
    assert_close(got["tan_grid"], want["tan_grid"], rel=0.0, abs_=1e-6 * K, path="tan_grid")
    assert_close(got["coefficients"], want["coefficients"], rel=1e-6, path="coefficients")
    # Propagated precision (~0.1-0.35 px) and residual RMS (~0.5 px): relative 1e-6, floor 1e-9 px.
    assert_close(got["precision_px"], want["precision_px"], rel=1e-6, abs_=1e-9, path="precision_px")
    assert_close(got["residual_rms"], want["residual_rms"], rel=1e-6, abs_=1e-9, path="residual_rms")


def test_rpc_fit_frozen(scene):
    # Fit/check errors are ~1e-4 px residuals of a 10240 px image: float noise of the coordinates is ~1e-11 px,
    # so an absolute 1e-8 px (plus relative 1e-6) is three orders above the noise and far below any real change.
    assert_close(compute_rpc_fit(scene), load("rpc_fit"), rel=1e-6, abs_=1e-8, path="rpc_fit")


def test_intersection_frozen():
    want, got = load("intersection"), compute_intersection()
    # Coordinates: 1e-10 deg is ~1e-5 m, h to 1e-5 m (Gauss-Newton converges to ~1e-9 m).
    for k, tol in (("lon", 1e-10), ("lat", 1e-10), ("h", 1e-5)):
        assert_close(got["coordinates"][k], want["coordinates"][k], rel=0.0, abs_=tol, path=k)
    # Sigmas (~0.3 m) and the covariance (~0.01-1 m^2): relative 1e-6, floor 1e-12 m^2 for off-diagonal zeros.
    assert_close(got["sigmas"], want["sigmas"], rel=1e-6, abs_=1e-9, path="sigmas")
    assert_close(got["cov_enu_m2"], want["cov_enu_m2"], rel=1e-6, abs_=1e-12, path="cov_enu_m2")
