"""Line of sight x a 0.5 m urban DSM with holes (issue 19), on the real Pleiades Ventoux RPC, against a brute-force
first-crossing ray march written here (METHODS §2).

The DSM is built by :func:`gdal_gf4cal.simulate.dsm.urban_dsm` (seed 0): 400 x 400 px at 0.5 m in UTM 31N on the
real SRTM terrain of Mont Ventoux (EGM96 applied), 41 flat-roofed buildings 5-40 m high, 11 % no-data in blobs
at building walls (where a stereo pair's second view is occluded).
"""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal import DEM, RPCModel
from gdal_gf4cal import localization
from gdal_gf4cal.simulate.dsm import urban_dsm

CENTER = (5.2872, 44.1357)
CELL_M = 0.5


@pytest.fixture(scope="module")
def ventoux(ventoux_rpc_path):
    return RPCModel.from_file(ventoux_rpc_path)


@pytest.fixture(scope="module")
def dsm(tmp_path_factory, srtm_path):
    path = tmp_path_factory.mktemp("dsm") / "dsm.tif"
    info = urban_dsm(path, DEM.from_file(srtm_path, geoid="egm96"), CENTER, seed=0)
    assert info["hole_fraction"] >= 0.10 and info["n_buildings"] >= 20
    assert info["height_range"][1] - info["height_range"][0] > 40.0
    return DEM.from_file(path, nodata="nan")


def _footprint_points(rpc, dem, n, seed, widen=1.0):
    """Image points uniform over the image box of the DSM's footprint (``widen`` times as wide in sample)."""
    b = dem.bounds_lonlat()
    lo, hi = dem.height_range()
    s, l = rpc.project(np.array([b[0], b[2], b[0], b[2]]), np.array([b[1], b[1], b[3], b[3]]),
                       np.full(4, 0.5 * (lo + hi)))
    rng = np.random.default_rng(seed)
    return (rng.uniform(s.min(), s.min() + widen * (s.max() - s.min()), n), rng.uniform(l.min(), l.max(), n))


def _brute_force_first_crossing(model, s, l, dem, step_m=0.2):
    """Reference: exact localisations every ``step_m`` metres down each line of sight from the top of the DSM; the
    first sample at or below the surface after a sample above it (no-data samples stepped over), linearly
    interpolated between the two. NaN where no such crossing exists."""
    z_lo, z_hi = dem.height_range()
    last_h = np.full(s.size, np.nan)
    last_f = np.full(s.size, np.nan)
    h_out = np.full(s.size, np.nan)
    live = np.ones(s.size, dtype=bool)
    for hk in np.arange(z_hi + 1.0, z_lo - 1.0, -step_m):
        i = np.flatnonzero(live)
        lon, lat = model.localize(s[i], l[i], np.full(i.size, hk))
        f = dem.sample(lon, lat, nodata="nan") - hk
        hit = np.isfinite(f) & (f >= 0)
        cross = hit & np.isfinite(last_f[i])
        j = i[cross]
        h_out[j] = last_h[j] - last_f[j] * (hk - last_h[j]) / (f[cross] - last_f[j])
        live[i[hit]] = False
        above = np.isfinite(f) & (f < 0)
        last_h[i[above]], last_f[i[above]] = hk, f[above]
    return h_out


def _ground_distance_cells(model, s, l, h1, h2):
    lon1, lat1 = model.localize(s, l, h1)
    lon2, lat2 = model.localize(s, l, h2)
    return np.hypot((lon1 - lon2) * 111320.0 * np.cos(np.radians(lat1)), (lat1 - lat2) * 110574.0) / CELL_M


@pytest.mark.parametrize("fast_path", [True, False])
def test_first_crossing_on_a_dsm_with_holes(ventoux, dsm, fast_path):
    s, l = _footprint_points(ventoux, dsm, 1500, seed=3)
    ref = _brute_force_first_crossing(ventoux, s, l, dsm)
    reached = np.isfinite(ref)
    assert reached.mean() > 0.7
    lon, lat, h, stats = localization.localize_dem(ventoux, s, l, dsm, full_output=True, fast_path=fast_path)
    found = np.isfinite(h)
    d = _ground_distance_cells(ventoux, s[reached & found], l[reached & found], h[reached & found],
                               ref[reached & found])
    # >= 95 % of the points the ray march reaches are found, within one DSM cell of its crossing.
    assert np.count_nonzero(d <= 1.0) >= 0.95 * np.count_nonzero(reached)
    assert np.count_nonzero(found & ~reached) <= 0.002 * s.size
    # Exact solutions: on the line of sight to 1e-6 px; on the DSM where it has data; some in holes (bridged).
    s2, l2 = ventoux.project(lon[found], lat[found], h[found])
    assert np.max(np.hypot(s2 - s[found], l2 - l[found])) <= 1e-6
    z = dsm.sample(lon[found], lat[found], nodata="nan")
    on_data = np.isfinite(z)
    off = np.abs(z[on_data] - h[found][on_data]) > 1e-3
    # Off the surface only where bridged at a hole's very edge (no-data within a pixel), and rarely.
    px, py = dsm.to_pixel(lon[found][on_data][off], lat[found][on_data][off])
    near_hole = np.zeros(px.size, dtype=bool)
    for dx in (-1.0, 0.0, 1.0):
        for dy in (-1.0, 0.0, 1.0):
            near_hole |= np.isnan(dsm.sample_pixel(px + dx, py + dy))
    assert np.all(near_hole) and np.count_nonzero(off) <= 0.005 * found.size
    assert np.count_nonzero(~on_data) >= 0.02 * found.size          # bridged: inside holes
    assert stats.n_failed == np.count_nonzero(~found)


def test_rays_off_the_dsm_give_up_at_once(ventoux, dsm, monkeypatch):
    """Half the points outside the DSM: NaN there, the same answers inside, and no DEM sample spent on them."""
    s, l = _footprint_points(ventoux, dsm, 4000, seed=4, widen=2.0)
    b = dsm.bounds_lonlat()
    lon_top, _ = ventoux.localize(s, l, np.full(s.size, b[0] * 0 + dsm.height_range()[1] + 1.0))
    lon_bot, _ = ventoux.localize(s, l, np.full(s.size, dsm.height_range()[0] - 1.0))
    outside = (np.minimum(lon_top, lon_bot) > b[2] + 1e-5)          # east of the DSM over its whole height range
    assert 0.4 < outside.mean() < 0.6
    counted = []
    sample_pixel = DEM.sample_pixel
    monkeypatch.setattr(DEM, "sample_pixel", lambda self, px, py: counted.append(np.size(px)) or
                        sample_pixel(self, px, py))
    lon, lat, h = ventoux.localize_dem(s, l, dsm)
    n_all = sum(counted)
    assert np.all(np.isnan(h[outside])) and np.isfinite(h[~outside]).mean() > 0.7
    counted.clear()
    lon_in, lat_in, h_in = ventoux.localize_dem(s[~outside], l[~outside], dsm)
    np.testing.assert_allclose(h_in, h[~outside], atol=1e-6)
    assert n_all <= 1.02 * sum(counted)          # the rays outside cost (almost) no DEM sample


def test_a_fallback_height_serves_the_rays_off_the_dsm(ventoux, dsm):
    """A numeric no-data policy: rays meeting no DSM surface are localised at that height, the others as before."""
    s, l = _footprint_points(ventoux, dsm, 600, seed=6, widen=2.0)
    h_nan = ventoux.localize_dem(s, l, dsm)[2]
    lon, lat, h = ventoux.localize_dem(s, l, dsm.with_nodata(1000.0))
    miss = np.isnan(h_nan)
    assert 0.4 < miss.mean() < 0.7 and np.all(h[miss] == 1000.0)
    np.testing.assert_allclose(h[~miss], h_nan[~miss], atol=1e-6)
    s2, l2 = ventoux.project(lon, lat, h)
    assert np.max(np.hypot(s2 - s, l2 - l)) <= 1e-6
