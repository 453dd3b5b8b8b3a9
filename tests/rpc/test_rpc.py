"""RPCModel: construction errors, projection, Jacobians, localisation, pathological real RPCs (METHODS §1)."""
from __future__ import annotations

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal import RPCFormatError, RPCModel, threads
from gdal_gf4cal.rpc import (DERIVATIVE_MATRICES, PROJECT_CHUNK, SERIAL_PROJECT_CHUNK, monomial_derivatives,
                             monomials)

gdal.UseExceptions()

REAL_RPCS = [
    "rpc/RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML",   # Pleiades DIMAP v2
    "rpc/PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif",   # Pleiades, GeoTIFF RPC tags
    "rpc/rpc.vrt",                                              # QuickBird-2
    "rpc/md_dg.RPB",                                            # WorldView-3
    "rpc/rpc_IKONOS.txt",                                       # IKONOS
    "rpc/rpc_SPOT6.xml",                                        # SPOT-6
    "rpc/20191015_073816_ssc1d3_0011_basic_l1a_panchromatic_dn_RPC.TXT",  # SkySat L1A
]


def _read_kv(path):
    with open(path) as fh:
        return dict(line.split("=", 1) for line in fh.read().splitlines() if "=" in line)


@pytest.fixture(params=REAL_RPCS, ids=lambda p: p.split("/")[-1][:28])
def real_rpc(request, data_dir):
    return RPCModel.from_file(data_dir / request.param)


def _mem_dataset(rpc):
    """A raster carrying ``rpc``, so GDAL's own RPC transformer can be compared with ours."""
    w, h = rpc.image_size
    ds = gdal.GetDriverByName("MEM").Create("", w, h)
    ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    return ds


def _image_grid(rpc, n=25, margin=0.02):
    w, h = rpc.image_size
    s, l = np.meshgrid(np.linspace(margin * w, (1 - margin) * w, n), np.linspace(margin * h, (1 - margin) * h, n))
    return s.ravel(), l.ravel()


# ---------------------------------------------------------------------------------------------- construction
def test_metadata_round_trip_is_exact(real_rpc):
    again = RPCModel.from_gdal_metadata(real_rpc.to_gdal_metadata())
    for name in ("line_off", "samp_off", "lat_off", "long_off", "height_off", "line_scale", "samp_scale",
                 "lat_scale", "long_scale", "height_scale"):
        assert getattr(again, name) == getattr(real_rpc, name)
    for name in ("line_num", "line_den", "samp_num", "samp_den"):
        np.testing.assert_array_equal(getattr(again, name), getattr(real_rpc, name))


@pytest.mark.parametrize("mutation, key", [
    (lambda md: md.pop("LINE_OFF"), "LINE_OFF"),
    (lambda md: md.__setitem__("SAMP_NUM_COEFF", " ".join(md["SAMP_NUM_COEFF"].split()[:19])), "SAMP_NUM_COEFF"),
    (lambda md: md.__setitem__("LAT_SCALE", "abc"), "LAT_SCALE"),
    (lambda md: md.__setitem__("LONG_SCALE", "0"), "LONG_SCALE"),
    (lambda md: md.__setitem__("HEIGHT_OFF", "nan"), "HEIGHT_OFF"),
])
def test_malformed_metadata_names_the_key(data_dir, mutation, key):
    md = RPCModel.from_file(data_dir / REAL_RPCS[0]).to_gdal_metadata()
    mutation(md)
    with pytest.raises(RPCFormatError, match=key):
        RPCModel.from_gdal_metadata(md, source="scene.RPB")


def test_empty_metadata_is_a_clear_error():
    with pytest.raises(RPCFormatError, match="no RPC"):
        RPCModel.from_gdal_metadata({}, source="plain.tif")


# ---------------------------------------------------------------------------------------------- polynomials
def test_derivative_matrices_match_analytic_monomial_derivatives():
    rng = np.random.default_rng(3)
    L, P, H = rng.uniform(-1, 1, (3, 50))
    m = monomials(L, P, H)
    for D, d in zip(DERIVATIVE_MATRICES, monomial_derivatives(L, P, H)):
        np.testing.assert_allclose(D @ m, d, atol=1e-14)


def test_project_matches_gdal_transformer(real_rpc):
    """GDAL's RPC transformer is the reference for ground -> image (METHODS §0)."""
    ds = _mem_dataset(real_rpc)
    tr = gdal.Transformer(ds, None, ["METHOD=RPC"])
    s, l = _image_grid(real_rpc, 12)
    h = np.linspace(*real_rpc.height_range, s.size)
    lon, lat = real_rpc.localize(s, l, h)
    ok = np.isfinite(lon)
    assert ok.mean() > 0.95
    out, _ = tr.TransformPoints(1, np.column_stack([lon[ok], lat[ok], h[ok]]))
    out = np.asarray(out)
    ps, pl = real_rpc.project(lon[ok], lat[ok], h[ok])
    assert np.max(np.abs(out[:, 0] - ps)) < 1e-6
    assert np.max(np.abs(out[:, 1] - pl)) < 1e-6


def test_scalar_and_array_shapes(real_rpc):
    s, l = real_rpc.project(real_rpc.long_off, real_rpc.lat_off, real_rpc.height_off)
    assert isinstance(s, float) and isinstance(l, float)
    lon = np.full((3, 4), real_rpc.long_off)
    s, l = real_rpc.project(lon, real_rpc.lat_off, real_rpc.height_off)
    assert s.shape == (3, 4) and l.shape == (3, 4)
    lo, la = real_rpc.localize(s, l, real_rpc.height_off)
    assert lo.shape == (3, 4)


def test_pixel_conventions_differ_by_half_a_pixel(real_rpc):
    args = (real_rpc.long_off, real_rpc.lat_off, real_rpc.height_off)
    sg, lg = real_rpc.project(*args)
    sr, lr = real_rpc.project(*args, pixel_convention="rpc")
    assert sg - sr == pytest.approx(0.5, abs=1e-9) and lg - lr == pytest.approx(0.5, abs=1e-9)
    # At the offsets (L = P = H = 0) the raw convention returns SAMP_OFF/LINE_OFF plus the constant terms' ratio.
    assert sr == pytest.approx(real_rpc.samp_off + real_rpc.samp_scale * real_rpc.samp_num[0] / real_rpc.samp_den[0],
                               abs=1e-9)
    assert lr == pytest.approx(real_rpc.line_off + real_rpc.line_scale * real_rpc.line_num[0] / real_rpc.line_den[0],
                               abs=1e-9)
    with pytest.raises(ValueError, match="pixel_convention"):
        real_rpc.project(*args, pixel_convention="centre")


def test_jacobian_matches_finite_differences(real_rpc):
    s, l = _image_grid(real_rpc, 5)
    h = np.full(s.size, real_rpc.height_off)
    lon, lat = real_rpc.localize(s, l, h)
    J = real_rpc.project_jacobian(lon, lat, h)
    steps = (1e-6, 1e-6, 1e-2)
    for k, step in enumerate(steps):
        d = [np.zeros_like(lon), np.zeros_like(lon), np.zeros_like(lon)]
        d[k] = np.full_like(lon, step)
        sp, lp = real_rpc.project(lon + d[0], lat + d[1], h + d[2])
        sm, lm = real_rpc.project(lon - d[0], lat - d[1], h - d[2])
        np.testing.assert_allclose(J[:, 0, k], (sp - sm) / (2 * step), rtol=1e-5, atol=1e-6 * np.abs(J).max())
        np.testing.assert_allclose(J[:, 1, k], (lp - lm) / (2 * step), rtol=1e-5, atol=1e-6 * np.abs(J).max())


@pytest.mark.parametrize("convention", ["gdal", "rpc"])
def test_project_with_jacobian_is_project_and_its_jacobian(real_rpc, convention):
    """One evaluation gives both: the pixels of ``project`` (to 1e-9 px) and the Jacobian of ``project_jacobian``
    (the same bits), over several thread blocks and in the input's shape."""
    rng = np.random.default_rng(3)
    n = 3 * threads.BLOCK + 17
    g = [o + sc * rng.uniform(-0.9, 0.9, n) for o, sc in ((real_rpc.long_off, real_rpc.long_scale),
                                                           (real_rpc.lat_off, real_rpc.lat_scale),
                                                           (real_rpc.height_off, real_rpc.height_scale))]
    s, l, J = real_rpc.project_with_jacobian(*g, pixel_convention=convention)
    s0, l0 = real_rpc.project(*g, pixel_convention=convention)
    assert np.abs(s - s0).max() < 1e-9 and np.abs(l - l0).max() < 1e-9
    with threads.limit(1):
        J1 = real_rpc.project_jacobian(*g)
    assert J.shape == (n, 2, 3) and np.array_equal(J, J1)
    s2, l2, J2 = real_rpc.project_with_jacobian(*(a.reshape(-1, 1)[:10] for a in g), pixel_convention=convention)
    assert s2.shape == (10, 1) and J2.shape == (10, 1, 2, 3) and np.array_equal(J2[:, 0], J[:10])


# ---------------------------------------------------------------------------------------------- localisation
def test_localize_round_trip_below_1e6_px(real_rpc):
    s, l = _image_grid(real_rpc, 30)
    for h in (real_rpc.height_range[0], real_rpc.height_off, real_rpc.height_range[1]):
        lon, lat, stats = real_rpc.localize(s, l, h, full_output=True)
        assert stats.n_failed == 0
        s2, l2 = real_rpc.project(lon, lat, h)
        assert np.max(np.hypot(s2 - s, l2 - l)) <= 1e-6


def test_localize_agrees_with_gdal(real_rpc):
    ds = _mem_dataset(real_rpc)
    tr = gdal.Transformer(ds, None, ["METHOD=RPC", "RPC_PIXEL_ERROR_THRESHOLD=1e-9", f"RPC_HEIGHT={real_rpc.height_off}"])
    s, l = _image_grid(real_rpc, 10)
    out, ok = tr.TransformPoints(0, np.column_stack([s, l, np.zeros(s.size)]))
    out, ok = np.asarray(out), np.asarray(ok, dtype=bool)
    lon, lat = real_rpc.localize(s, l, real_rpc.height_off)
    assert ok.mean() > 0.9
    J = real_rpc.project_jacobian(lon[ok], lat[ok], real_rpc.height_off)[:, :, :2]
    d_px = np.einsum("nij,nj->ni", J, np.column_stack([out[ok, 0] - lon[ok], out[ok, 1] - lat[ok]]))
    assert np.max(np.hypot(*d_px.T)) < 1e-3


def test_negative_lat_scale_rpc_gdal_6162(data_dir):
    """GDAL autotest test_transformer_11: fails at h=4000 (far outside HEIGHT_SCALE), exact at h=1150."""
    rpc = RPCModel.from_gdal_metadata(_read_kv(data_dir / "rpc_edge" / "transformer_11_rpc.txt"))
    assert rpc.lat_scale < 0
    lon, lat, stats = rpc.localize(0.0, 0.0, 4000.0, full_output=True)
    assert np.isnan(lon) and np.isnan(lat) and stats.n_failed == 1
    lon, lat = rpc.localize(0.0, 0.0, 1150.0)
    assert lon == pytest.approx(77.350939956024618, abs=1e-7)
    assert lat == pytest.approx(38.739703990877814, abs=1e-7)


def test_gdal_5395_convergence_case(data_dir):
    rpc = RPCModel.from_file(data_dir / "rpc" / "rpc_5395.vrt")
    lon, lat = rpc.localize(0.5, 0.5, 0.0)
    assert lon == pytest.approx(28.26163232, abs=1e-4) and lat == pytest.approx(-27.79853245, abs=1e-4)


def test_quickbird_expected_values_from_gdal_autotest(data_dir):
    rpc = RPCModel.from_file(data_dir / "rpc" / "rpc.vrt")
    lon, lat = rpc.localize(20.5, 10.5, 0.0)
    assert lon == pytest.approx(125.64830100509131, abs=1e-6) and lat == pytest.approx(39.869433991997553, abs=1e-6)
    lon, lat = rpc.localize(20.5, 10.5, 30.0)
    assert lon == pytest.approx(125.64828521533849, abs=1e-6) and lat == pytest.approx(39.869345204440144, abs=1e-6)


def test_skysat_corner_localises_like_gdal_at_70_and_90_m(data_dir):
    """rpcm's test expects its own iteration to fail at h=70 m for this SkySat RPC. The RPC is regular there:
    GDAL converges and so do we, to the same point, with an exact round trip. A wrong NaN is no better than a
    wrong number, so we return the solution and check it against GDAL."""
    rpc = RPCModel.from_file(data_dir / "rpc" / "20191015_073816_ssc1d3_0011_basic_l1a_panchromatic_dn_RPC.TXT")
    ds = _mem_dataset(rpc)
    for h in (70.0, 90.0):
        lon, lat = rpc.localize(0.5, 0.5, h)
        s, l = rpc.project(lon, lat, h)
        assert abs(s - 0.5) < 1e-6 and abs(l - 0.5) < 1e-6
        tr = gdal.Transformer(ds, None, ["METHOD=RPC", f"RPC_HEIGHT={h}", "RPC_PIXEL_ERROR_THRESHOLD=1e-9"])
        ok, (glon, glat, _) = tr.TransformPoint(0, 0.5, 0.5, 0.0)
        assert ok
        assert abs(glon - lon) < 1e-9 and abs(glat - lat) < 1e-9


def test_far_outside_points_come_back_nan_and_counted(real_rpc):
    w, h = real_rpc.image_size
    lon, lat, stats = real_rpc.localize(np.array([w / 2, 1e9]), np.array([h / 2, -1e9]), real_rpc.height_off,
                                        full_output=True)
    assert np.isfinite(lon[0]) and np.isnan(lon[1]) and stats.n_failed == 1


def test_localize_settles_each_point_on_its_own(real_rpc):
    """The chunk solver (issue 23) settles a chunk whose points all converge together in a few calls and takes
    its per-point path otherwise (a point without solution, one that needs damping or the orientation check):
    a point gets the same bits either way, and the same pixels to 1e-8 px. max_iter=1 accepts the start (the cubic
    inverse) at a loose tolerance; a tight one gives NaN."""
    s, l = _image_grid(real_rpc, 12)
    h = np.full(s.size, real_rpc.height_off)
    w, hh = real_rpc.image_size
    *together, stats = real_rpc.localize(s, l, h, full_output=True)
    assert stats.n_failed == 0                  # Pleiades, WorldView-3, IKONOS, SPOT-6: all settle at the 2nd
    odd = [(np.nan, 0.0), (1e9, -1e9), (-3.0 * w, 4.0 * hh)]        # no solution, far, a damped start
    mixed = real_rpc.localize(np.r_[s, [p[0] for p in odd]], np.r_[l, [p[1] for p in odd]],
                              np.r_[h, h[:len(odd)]], full_output=True)
    assert mixed[2].max_iterations > 2 and np.isnan(mixed[0][s.size:s.size + 2]).all()
    assert np.array_equal(mixed[0][:s.size], together[0]) and np.array_equal(mixed[1][:s.size], together[1])
    ps, pl = real_rpc.project(*together, h)
    assert np.max(np.hypot(ps - s, pl - l)) <= 1e-8 * 1.5
    start = real_rpc.localize(s, l, h, tol_px=1e4, max_iter=1)       # SkySat's cubic start: 2,000 px off
    ps, pl = real_rpc.project(*start, h)
    assert 1e-8 < np.max(np.hypot(ps - s, pl - l)) < 1e4
    assert np.isnan(real_rpc.localize(s, l, h, max_iter=1)[0]).all()


# ---------------------------------------------------------------------------------------------- corrections
@pytest.mark.parametrize("convention", ["gdal", "rpc"])
def test_with_image_affine_folds_shift_and_scale_exactly(real_rpc, convention):
    s, l = _image_grid(real_rpc, 6)
    lon, lat = real_rpc.localize(s, l, real_rpc.height_off)
    new = real_rpc.with_image_affine(3.25, -7.5, 1.0002, 0.9997, pixel_convention=convention)
    s0, l0 = real_rpc.project(lon, lat, real_rpc.height_off, pixel_convention=convention)
    s1, l1 = new.project(lon, lat, real_rpc.height_off, pixel_convention=convention)
    np.testing.assert_allclose(s1, 3.25 + 1.0002 * s0, atol=1e-8)
    np.testing.assert_allclose(l1, -7.5 + 0.9997 * l0, atol=1e-8)


def test_project_kernel_chunks_and_antimeridian(data_dir):
    """RPCModel.project's fused per-chunk kernel (issue 23): a point gives the same pixel alone, at a chunk
    boundary and in a long array; a longitude past the antimeridian (RPC at 179.99 E) the same as its value -360."""
    rpc = RPCModel.from_file(data_dir / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    rng = np.random.default_rng(1)
    n = PROJECT_CHUNK + 3
    lon = rpc.long_off + rng.uniform(-1, 1, n) * rpc.long_scale
    lat = rpc.lat_off + rng.uniform(-1, 1, n) * rpc.lat_scale
    h = rpc.height_off + rng.uniform(-1, 1, n) * rpc.height_scale
    with threads.limit(2):                               # two blocks over the pool: chunks of PROJECT_CHUNK
        s, l = rpc.project(lon, lat, h)
    with threads.limit(1):                               # one thread: chunks of SERIAL_PROJECT_CHUNK, the same bits
        alone = rpc.project(lon, lat, h)
    assert np.array_equal(alone[0], s) and np.array_equal(alone[1], l)
    for i in (0, SERIAL_PROJECT_CHUNK - 1, SERIAL_PROJECT_CHUNK, PROJECT_CHUNK - 1, PROJECT_CHUNK, n - 1):
        si, li = rpc.project(lon[i], lat[i], h[i])
        assert abs(si - s[i]) < 1e-9 and abs(li - l[i]) < 1e-9
    # the polynomial in the RPC's own normalisation (the definition) gives the same pixels to 1e-9 px
    L, P = (lon - rpc.long_off) / rpc.long_scale, (lat - rpc.lat_off) / rpc.lat_scale
    v = rpc._coeffs @ monomials(L, P, (h - rpc.height_off) / rpc.height_scale)
    np.testing.assert_allclose(s, v[0] / v[1] * rpc.samp_scale + rpc.samp_off + 0.5, atol=1e-9, rtol=0)
    np.testing.assert_allclose(l, v[2] / v[3] * rpc.line_scale + rpc.line_off + 0.5, atol=1e-9, rtol=0)
    far = rpc.replace(long_off=179.99)
    east = 179.99 + rng.uniform(0.0, 0.009, 50)
    s1, l1 = far.project(np.concatenate([east, east]), np.concatenate([lat[:50]] * 2),
                         np.concatenate([h[:50]] * 2))
    s2, l2 = far.project(np.concatenate([east, east - 360.0]), np.concatenate([lat[:50]] * 2),
                         np.concatenate([h[:50]] * 2))
    np.testing.assert_allclose(s2, s1, atol=1e-6)
    np.testing.assert_allclose(l2, l1, atol=1e-6)
    assert rpc.project(np.zeros(0), np.zeros(0), np.zeros(0))[0].shape == (0,)


def test_project_chunk_size_keeps_the_bits(data_dir, monkeypatch):
    """PROJECT_CHUNK and SERIAL_PROJECT_CHUNK change no bit (issue 23: the chunks are a cache/speed choice only):
    chunks of 1000 points (a last partial one of 17, and one of 2 columns that is never a one-column product) give
    the bits of one chunk of the whole array, with and without thread blocks (BLOCK 2000: blocks not a multiple of
    the chunk)."""
    from gdal_gf4cal import rpc as rpc_module
    rpc = RPCModel.from_file(data_dir / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    rng = np.random.default_rng(5)
    n = 3 * 1000 + 17
    g = [o + sc * rng.uniform(-1.2, 1.2, n) for o, sc in ((rpc.long_off, rpc.long_scale),
                                                           (rpc.lat_off, rpc.lat_scale),
                                                           (rpc.height_off, rpc.height_scale))]
    for name in ("PROJECT_CHUNK", "SERIAL_PROJECT_CHUNK"):
        monkeypatch.setattr(rpc_module, name, 10 ** 9)
    whole = rpc.project(*g)
    for chunk, block, t in ((1000, threads.BLOCK, 1), (1000, 2000, 2), (3015, threads.BLOCK, 1)):
        for name in ("PROJECT_CHUNK", "SERIAL_PROJECT_CHUNK"):
            monkeypatch.setattr(rpc_module, name, chunk)
        monkeypatch.setattr(threads, "BLOCK", block)
        with threads.limit(t):
            chunked = rpc.project(*g)
        assert np.array_equal(chunked[0], whole[0]) and np.array_equal(chunked[1], whole[1]), (chunk, block, t)


def test_monomial_buffers_and_localize_chunks_keep_the_bits(data_dir, monkeypatch):
    """The kernels' reused buffers change no bit (issue 23): fill_monomials' grouped products and the chunks of
    monomial_chunks are the products of monomials() term by term; localize solved in chunks of LOCALIZE_CHUNK
    (points off the image, NaN, a last partial chunk) gives the bits of one solve of the whole array, with the same
    iteration count."""
    from gdal_gf4cal import rpc as rpc_module
    from gdal_gf4cal._rpc_poly import monomial_chunks
    rng = np.random.default_rng(4)
    L, P, H = (rng.uniform(-1.3, 1.3, 5000) for _ in range(3))
    ref = np.stack([np.ones_like(L), L, P, H, L * P, L * H, P * H, L * L, P * P, H * H, (L * P) * H, (L * L) * L,
                    (P * P) * L, (H * H) * L, (L * L) * P, (P * P) * P, (H * H) * P, (L * L) * H, (P * P) * H,
                    (H * H) * H])
    assert np.array_equal(monomials(L, P, H), ref)
    parts = [(i, j, m.copy()) for i, j, m in monomial_chunks(L, P, H, chunk=1024)]
    assert [(i, j) for i, j, _ in parts][-1] == (4096, 5000)
    assert np.array_equal(np.hstack([m for _, _, m in parts]), ref)
    rpc = RPCModel.from_file(data_dir / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    w, h = rpc.image_size
    n = 3 * 1000 + 17
    s, l = rng.uniform(-0.5 * w, 1.5 * w, n), rng.uniform(-0.5 * h, 1.5 * h, n)
    s[::97] = np.nan
    hh = rng.uniform(*rpc.height_range, n)
    monkeypatch.setattr(rpc_module, "LOCALIZE_CHUNK", 1000)
    chunked = rpc.localize(s, l, hh, full_output=True)
    monkeypatch.setattr(rpc_module, "LOCALIZE_CHUNK", 10 ** 9)
    whole = rpc.localize(s, l, hh, full_output=True)
    assert np.array_equal(chunked[0], whole[0], equal_nan=True) and np.array_equal(chunked[1], whole[1], equal_nan=True)
    assert chunked[2].max_iterations == whole[2].max_iterations and chunked[2].n_failed == whole[2].n_failed > 0
    assert 0.3 < np.isfinite(whole[0]).mean() < 0.99


def test_scratch_buffers_are_per_thread_and_never_shared_while_in_use():
    """_rpc_poly.scratch (issue 23): a thread gets its buffer back on the next call (no fresh memory to fault in),
    a nested request for the same rows while it is in use gets another one, and another thread never gets it."""
    import threading

    from gdal_gf4cal._rpc_poly import scratch
    with scratch(7, 100) as a:
        a[:] = 1.0
        with scratch(7, 50) as b:
            assert b.shape == (7, 50) and not np.shares_memory(a, b)
    with scratch(7, 80) as c:
        assert c.shape == (7, 80) and np.shares_memory(a, c)
    seen = []
    t = threading.Thread(target=lambda: seen.append(scratch(7, 80).__enter__()))
    t.start()
    t.join()
    assert not np.shares_memory(seen[0], a)


def test_small_normalised_projections_give_the_bits_of_a_large_one(real_rpc):
    """Up to 64 points the localisations' normalised projection takes fresh arrays instead of the reused buffers
    (a small call's fixed cost): each column is the same product, the same bits as inside a call of 3000 points
    (from 2 points: one point is a matrix-vector product, BLAS's own rounding, with buffers or without)."""
    rng = np.random.default_rng(2)
    L, P, H = (rng.uniform(-1.2, 1.2, 3000) for _ in range(3))
    large = np.array(real_rpc._project_normalised(L, P, H))
    for a, b in ((1, 3), (1, 5), (7, 71), (100, 164), (200, 265)):
        np.testing.assert_array_equal(np.array(real_rpc._project_normalised(L[a:b], P[a:b], H[a:b])), large[:, a:b])
