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
