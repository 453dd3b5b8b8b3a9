"""Sub-CCD breakpoints of the pan-MS model (METHODS §9): the pan's own edges mapped into the MS through the sensor
models and the DEM, and the ``--breaks`` words ``ms`` / ``pan``."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal import panms
from gdal_gf4cal.simulate.gf7 import make_gf7_scene, true_misregistration
from gdal_gf4cal.workflows.panms import _parse_breaks


def _true_jumps(scene, n: int):
    """MS columns of the ``n`` largest jumps of the true nabla field along the middle line (0.25 px steps)."""
    W, H = scene.image("ms").size
    s = np.arange(50.0, W - 50.0, 0.25)
    ds, dl = true_misregistration(scene, s, np.full(s.shape, H / 2.0))
    jump = np.hypot(np.diff(ds), np.diff(dl))
    return np.sort(s[np.argsort(jump)[-n:]] + 0.125)


def test_pan_edges_mapped_into_ms_fall_on_the_true_jumps():
    """Without yaw steering and with a long look-time difference the pan and MS edges separate (METHODS §9's old
    0.395 s: ~64 MS px); the mapped pan edges land on the true field's jumps within the current models' own error
    (< 1 px), and the merged list holds both the MS and the pan edges."""
    scene = make_gf7_scene(seed=5, jitter=False, yaw_steering=False, look_time_s=0.395)
    pan, ms = scene.image("pan"), scene.image("ms")
    mapped = panms.pan_edges_in_ms(pan.current, ms.current, scene.dem, pan.size, 3)
    jumps = _true_jumps(scene, 4)
    ms_edges = panms.default_breaks(ms.size[0], 3)
    assert min(abs(mapped[0] - ms_edges[0]), abs(mapped[1] - ms_edges[1])) > 30.0      # separated edges
    for edge in list(mapped) + ms_edges:
        assert np.min(np.abs(jumps - edge)) < 1.0, (edge, jumps)
    merged = panms.merge_breaks(ms_edges, mapped, width=ms.size[0])
    assert len(merged) == 4 and merged == sorted(merged)


def test_yaw_steered_edges_coincide_and_merge():
    """With yaw steering (GF7 today) the pan edges fall on the MS ones: ``ms,pan`` gives the two MS edges."""
    scene = make_gf7_scene(seed=6, jitter=False)
    pan, ms = scene.image("pan"), scene.image("ms")
    mapped = panms.pan_edges_in_ms(pan.current, ms.current, scene.dem, pan.size, 3)
    ms_edges = panms.default_breaks(ms.size[0], 3)
    assert np.allclose(mapped, ms_edges, atol=0.5)
    assert len(panms.merge_breaks(ms_edges, mapped, width=ms.size[0])) == 2


def test_breaks_words_and_errors():
    assert _parse_breaks("2560, 5120") == [2560.0, 5120.0]
    assert _parse_breaks("ms,pan") == ["ms", "pan"]
    assert _parse_breaks(None) is None
    with pytest.raises(panms.PanMSError, match="ms, pan"):
        _parse_breaks("2560,left")
    assert panms.merge_breaks([0.0, 10.0, 10.4, 99.0, 100.0], width=100.0) == [10.2, 99.0]


def _window_matches(seed: int = 4, n_blunders: int = 20):
    """Window matches of a 2816 x 128 MS crop across two sub-CCD edges (the GF7 ``across_both`` crop's layout:
    32 px windows every 4 px, edges at columns 128 and 2688 with its jumps): a smooth field, each window's own
    noise (0.03 px), a texture bias shared by neighbouring columns (0.01 px, correlated over ~10 columns, as the
    matcher's column profile shows on the rendered crop) and ``n_blunders`` gross mismatches (+1.5 px)."""
    from scipy import ndimage
    rng = np.random.default_rng(seed)
    cols, rows = np.arange(20.0, 2797.0, 4.0), np.arange(20.0, 109.0, 4.0)
    S, L = (v.ravel() for v in np.meshgrid(cols, rows))
    u = S / 1408.0 - 1.0
    edges, jumps = np.array([128.0, 2688.0]), np.array([[0.49, 0.70], [-0.157, 0.049]])
    step = np.clip((S[:, None] - edges[None, :]) / 16.0 + 0.5, 0.0, 1.0) @ jumps          # a window mixes both sides
    bias = ndimage.gaussian_filter1d(rng.normal(size=(cols.size, 2)), 4.0, axis=0)
    bias *= 0.01 / bias.std()
    d = np.stack([-0.87 + 0.2 * u - 0.1 * u ** 3, -0.43 - 0.3 * u + 0.05 * u ** 4], axis=1) + step
    d += bias[np.searchsorted(cols, S)] + rng.normal(scale=0.03, size=d.shape)
    bad = rng.choice(S.size, n_blunders, replace=False)
    d[bad] += 1.5
    return S, L, d, bad


def test_window_screen_keeps_the_smaller_side_of_a_jump_and_flags_blunders():
    """A global low-order model with a MAD cut (the matcher's default screen) rejects every window left of the
    jump at column 128 (a 128 px piece); the screen within each column keeps them and flags the blunders."""
    from gdal_gf4cal.matching import reject_outliers
    S, L, d, bad = _window_matches()
    left = S < 112.0
    assert reject_outliers(S, L, d[:, 0], d[:, 1]).outlier[left].mean() > 0.9            # what went wrong before
    out = panms.screen_matches(S, L, d[:, 0], d[:, 1], spacing_px=4)
    assert out[bad].all()
    assert not out[left & ~np.isin(np.arange(S.size), bad)].any()
    assert out.sum() <= bad.size + 0.01 * S.size


def test_detect_breaks_finds_both_edges_and_no_jump_in_correlated_noise():
    """Both edges within 2 px, and no spurious edge in the texture bias (0.01 px, correlated over neighbouring
    columns: counting only the window's width as one independent column finds a 'jump' at column 951 in it)."""
    S, L, d, bad = _window_matches()
    ok = ~panms.screen_matches(S, L, d[:, 0], d[:, 1], spacing_px=4)
    found, info = panms.detect_breaks(S[ok], L[ok], d[ok, 0], d[ok, 1], width=2816, window_px=32, spacing_px=4)
    assert len(found) == 2 and np.allclose(found, [128.0, 2688.0], atol=2.0), found
    assert abs(info[0]["jump_line_px"] - 0.70) < 0.3 and abs(info[1]["jump_sample_px"] + 0.157) < 0.05, info


def test_detect_breaks_on_a_sparse_profile_never_fits_an_interval_it_cannot_determine():
    """A full GF7 scene matched every 32 MS px (window 32): two edges a window apart can enclose one column, where
    the smooth polynomial on that interval is undetermined (the full scene's register-pan-ms failed on a singular
    normal matrix), and a ramp 16 px wide between two columns is a step, as the intervals' constants. Candidates
    need JUMP_SMOOTH_ORDER + 2 columns on each side between their neighbouring edges and one inside their ramp: both
    edges found."""
    rng = np.random.default_rng(11)
    cols = np.arange(31.25, 7680.0, 32.0)
    x = np.repeat(cols, 40)
    line = np.tile(20.0 + 190.0 * np.arange(40), cols.size)           # 40 rows of windows
    d_s = 0.02 * np.sin(x / 300.0) + np.where(x > 2560.0, 0.4, 0.0) + rng.normal(0.0, 0.05, x.size)
    d_l = np.where(x > 5120.0, -0.3, 0.0) + rng.normal(0.0, 0.05, x.size)
    found, info = panms.detect_breaks(x, line, d_s, d_l, width=7680, window_px=32, spacing_px=32)
    assert len(found) >= 2 and min(abs(f - 2560.0) for f in found) < 32 and min(abs(f - 5120.0) for f in found) < 32
    from gdal_gf4cal.panms.breaks import _supported
    k = panms.JUMP_SMOOTH_ORDER + 2                                     # columns needed on each side
    ok = _supported(cols, [5111.7], np.array([5147.0, 4000.0, cols[k - 2] + 1.0, cols[k - 1] + 1.0, 4000.0 + 16.0]),
                    16.0)
    assert ok.tolist() == [False, True, False, True, False]


def test_detect_breaks_places_the_edges_and_jumps_of_the_full_scene_profile():
    """The full GF7 scene (seed 0) matched every 32 MS px: the window offsets are the simulator's true field of
    each sub-CCD (a window straddling an edge mixes both sides over its central 16 px) plus 0.03 px noise. The edge
    test's own place comes from one smooth polynomial across the edge: its misfit put the second edge a column gap
    off (5148 for 5120, as register-pan-ms did on the rendered scene: 5147), found jumps in the pieces' quartic
    bending (192, 1564 MS px) and read the jump off one column (-0.05 and -0.28 px for -0.157). Both true edges
    within 2 px, no other, and their jumps within 0.03 px of the truth."""
    from gdal_gf4cal.simulate.gf7 import make_gf7_scene, true_misregistration
    scene = make_gf7_scene(seed=0)
    W, H = scene.image("ms").size
    S, L = (v.ravel() for v in np.meshgrid(np.arange(32.0, W - 16.0, 32.0), np.linspace(100.0, H - 100.0, 24)))
    P = np.stack([np.stack(true_misregistration(scene, S, L, piece=k), axis=1) for k in range(3)])
    true_jumps = [np.mean(P[k + 1][S == e] - P[k][S == e], axis=0) for k, e in enumerate((2560.0, 5120.0))]
    r = np.clip((S[:, None] - np.array([2560.0, 5120.0])[None, :]) / 16.0 + 0.5, 0.0, 1.0)
    share = np.stack([1.0 - r[:, 0], r[:, 0] * (1.0 - r[:, 1]), r[:, 1]], axis=1)
    d0 = np.einsum("nk,knc->nc", share, P)
    for seed in (2, 3, 5):
        d = d0 + np.random.default_rng(seed).normal(0.0, 0.03, d0.shape)
        found, info = panms.detect_breaks(S, L, d[:, 0], d[:, 1], width=W, window_px=32, spacing_px=32)
        assert len(found) == 2 and np.allclose(found, [2560.0, 5120.0], atol=2.0), (seed, found)
        for it, tj in zip(info, true_jumps):
            assert np.allclose([it["jump_sample_px"], it["jump_line_px"]], tj, atol=0.03), (seed, info, true_jumps)
