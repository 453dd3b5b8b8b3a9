"""Issue 14: the simulator's render reads and writes windows only. GDAL's block cache (up to 5 % of the RAM) must
not fill with the scene: rendering a 24,576^2 scene from a reference kept ~1.2 GB of it before the tiles' blocks
were flushed (bench/bench_scale.py measures the peak RSS at 8,192^2 and 24,576^2)."""
from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
@pytest.mark.parametrize("from_reference", [False, True])
def test_render_keeps_gdal_block_cache_at_a_few_tiles(tmp_path, from_reference):
    from osgeo import gdal
    from gdal_gf4cal.simulate import make_scene, write_reference_ortho
    from gdal_gf4cal.simulate.render import model_bounds, render_image
    n, tile = 2048, 256
    sc = make_scene("gf4", seed=1, size=(n, n), dem=4500.0)
    im = sc.images[0]
    ref = None
    if from_reference:
        ref = write_reference_ortho(str(tmp_path / "ref.tif"), model_bounds(im.true, margin=0.05),
                                    im.gsd_m / 111320.0, seed=1, scale_m=3 * im.gsd_m)
        assert gdal.Open(ref).RasterXSize * gdal.Open(ref).RasterYSize > n * n   # bigger than the image
    used = []
    base = gdal.GetCacheUsed()      # process-wide: blocks other tests left in the cache are not this render's
    render_image(im.true, sc.dem, str(tmp_path / "scene.tif"), reference=ref, seed=1, gsd_m=im.gsd_m, tile=tile,
                 workers=2, progress=lambda f, m="": used.append(gdal.GetCacheUsed()))
    # Without the flushes the cache grew with every tile (the image's written blocks, the reference's read
    # blocks): to about n^2 bytes (4 MB) here, 600 MB+ at full size.
    assert max(used) - base < 12 * tile * tile, (max(used), base, n * n)
    assert len(used) == (n // tile) ** 2
    arr = gdal.Open(str(tmp_path / "scene.tif")).ReadAsArray()
    assert arr.shape == (n, n) and np.count_nonzero(arr) == n * n
