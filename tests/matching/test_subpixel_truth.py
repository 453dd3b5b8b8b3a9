"""The sub-pixel estimator against truth on real textures moved by known sub-pixel amounts (issue 23).

On the real Sentinel-2 pair of bench/bench_arosics.py our offsets and AROSICS COREG_LOCAL's differ by a steady
0.04-0.06 px in y. These tests pin down that ours is the one on the truth: a real texture (a crop of that pair's
reference, and the Pleiades Ventoux crop; tests/data/matching/PROVENANCE.txt) is moved by 0.0 ... 0.9 px in x, in
y, in both and in opposite directions, exactly (Fourier shift) and through GDAL's own cubic resampling, and
:func:`phase_correlate` must return the amounts applied, with no bias on either axis (a half-pixel or
pixel-centre slip, a row/column swap or a sign flip in the peak fit would all show here).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from osgeo import gdal
from scipy import ndimage

from gdal_gf4cal.matching.correlate import phase_correlate

gdal.UseExceptions()

DATA = Path(__file__).parents[1] / "data" / "matching"
TEXTURES = {"sentinel2": (DATA / "s2a_t33uuu_b03_crop.tif", 0, 0), "pleiades": (DATA / "pleiades_ventoux_left.tif",
                                                                                150, 150)}
W = 64
SIZE = 192
CORNERS = [(48, 48), (48, 80), (80, 48), (80, 80)]  # 64-px windows >= 48 px from the crop's edges
STEPS = np.round(np.arange(10) * 0.1, 1)
SHIFTS = ([(s, 0.0) for s in STEPS] + [(0.0, s) for s in STEPS] + [(s, s) for s in STEPS]
          + [(-s, 0.5 * s) for s in STEPS] + [(2.3, -1.6), (-3.7, 0.4)])


def _texture(name):
    path, x0, y0 = TEXTURES[name]
    ds = gdal.Open(str(path))
    return ds.GetRasterBand(1).ReadAsArray(x0, y0, SIZE, SIZE).astype(np.float64)


def _fourier(a, sx, sy):
    """``a`` with its content moved by ``(sx, sy)`` px (x right, y down), exactly (periodic band-limited shift)."""
    return np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(a), (sy, sx))).real


def _gdal_cubic(a, sx, sy):
    """``a`` resampled by GDAL (cubic) on a grid moved by ``(-sx, -sy)``: output pixel (x, y) samples (x - sx, y - sy)."""
    src = gdal.GetDriverByName("MEM").Create("", SIZE, SIZE, 1, gdal.GDT_Float64)
    src.SetGeoTransform((0.0, 1.0, 0.0, 0.0, 0.0, -1.0))
    src.GetRasterBand(1).WriteArray(a)
    dst = gdal.GetDriverByName("MEM").Create("", SIZE, SIZE, 1, gdal.GDT_Float64)
    dst.SetGeoTransform((-sx, 1.0, 0.0, sy, 0.0, -1.0))
    gdal.ReprojectImage(src, dst, None, None, gdal.GRA_Cubic)
    return dst.GetRasterBand(1).ReadAsArray()


def _errors(a, move):
    """Estimated minus applied offsets, shape (shifts, windows, 2), all shifts in one batched call. As in
    collect-gcps, the moving window is cut at the whole-pixel part of the offset (found by the coarse level or a
    first pass) and the estimator measures the rest."""
    fixed = np.array([a[y:y + W, x:x + W] for x, y in CORNERS])
    whole = np.round(np.array(SHIFTS)).astype(int)
    moving = np.array([[move(a, sx, sy)[y + oy:y + oy + W, x + ox:x + ox + W] for x, y in CORNERS]
                       for (sx, sy), (ox, oy) in zip(SHIFTS, whole)])
    r = phase_correlate(np.broadcast_to(fixed, moving.shape), moving)
    return np.stack([r.dx, r.dy], axis=-1) + whole[:, None, :] - np.array(SHIFTS)[:, None, :]


@pytest.mark.parametrize("name", sorted(TEXTURES))
def test_exact_subpixel_shifts_of_a_real_texture(name):
    e = _errors(_texture(name), _fourier)
    # Measured: max 0.0062 px (Sentinel-2), 0.0064 px (Pleiades); mean bias <= 0.0007 px per axis.
    assert np.abs(e).max() < 0.02
    bias = e.reshape(-1, 2).mean(axis=0)
    assert np.all(np.abs(bias) < 0.003), bias
    # No axis-specific slip: x and y behave alike for the same amounts.
    ex = e[:10, :, 0]
    ey = e[10:20, :, 1]
    assert np.abs(ex - ey).max() < 0.01


@pytest.mark.parametrize("name", sorted(TEXTURES))
def test_gdal_cubic_shifts_of_a_real_texture(name):
    """GDAL's cubic kernel low-passes a little more at a half-pixel phase than at zero, so the resampled copy is
    not an exact shifted copy: the error follows the phase (up to ~0.05 px at 0.3 and 0.7 px) with no mean."""
    e = _errors(_texture(name), _gdal_cubic)
    # Measured: max 0.045 px (Sentinel-2), 0.043 px (Pleiades).
    assert np.abs(e).max() < 0.06
    # Mean over whole periods of the phase (the moves along x, along y and along both): no bias on either axis.
    assert np.all(np.abs(e[:30].reshape(-1, 2).mean(axis=0)) < 0.005)
    # Integer and half-pixel moves are symmetric for the cubic kernel: exact there.
    for k, (sx, sy) in enumerate(SHIFTS):
        if sx in (0.0, 0.5) and sy in (0.0, 0.5):
            assert np.abs(e[k]).max() < 0.02, (sx, sy)
