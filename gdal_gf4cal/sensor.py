"""The one sensor-model contract (METHODS §1, §2): every model of the engine speaks the same verbs.

:class:`SensorModel` is the :class:`typing.Protocol` that :class:`~gdal_gf4cal.rpc.RPCModel`,
:class:`~gdal_gf4cal.compensation.CompensatedRPC`, :class:`~gdal_gf4cal.lookangle.RecalibratedSensor` and the
simulator's models (:mod:`gdal_gf4cal.simulate.models`) implement; code that only needs geometry (RPC fitting,
intersection, the simulator) takes any of them. :class:`SensorModelMixin` implements the shared parts once:

- scalars in, Python floats out; arrays broadcast and keep their shape;
- the pixel convention (``"gdal"``: centre of the first pixel at 0.5, the default; ``"rpc"``: at 0);
- ``localize_dem`` through the localisation layer (:func:`gdal_gf4cal.localization.localize_dem`);
- inputs of more than :data:`gdal_gf4cal.threads.BLOCK` points split into blocks over the thread pool
  (:func:`gdal_gf4cal.threads.split_points`: bit-identical results whatever ``GF4CAL_NUM_THREADS``);
- ``full_output=True`` on ``localize`` and ``localize_dem`` returns one :class:`LocalizationStats`;
- a numeric ``project_jacobian`` (central differences) for models without an analytic one.

A model built from the mixin implements two flat, GDAL-convention hooks: ``_project_gdal(lon, lat, h)`` and
``_localize_gdal(sample, line, h)`` (1-D float arrays in and out, NaN where there is no solution), plus
``height_range``. A composed model (an RPC with a correction) has no writers: it exposes what it is made of
(``.rpc``, ``.result``) explicitly and never forwards attributes to its parts.
"""
from __future__ import annotations

from typing import Any, Protocol, Tuple, runtime_checkable

import numpy as np

from .localization import LocalizationStats, localize_dem as _localize_dem
from .threads import split_points

__all__ = ["SensorModel", "SensorModelMixin", "LocalizationStats", "GDAL_PIXEL_OFFSET", "pixel_shift",
           "as_float_arrays", "shape_out"]

#: Offset between GDAL's pixel convention and the raw RPC00B one (gdal = raw + GDAL_PIXEL_OFFSET).
GDAL_PIXEL_OFFSET = 0.5

#: Ground steps of the numeric Jacobian (degrees, degrees, metres): ~1 m on the ground, exact to ~1e-7 relative
#: for the smooth models here (central differences).
_JACOBIAN_STEPS = (1e-5, 1e-5, 1.0)


@runtime_checkable
class SensorModel(Protocol):
    """What every sensor model offers (METHODS §1): ground <-> image, in the GDAL pixel convention by default.

    ``lon, lat`` are degrees WGS84, ``h`` ellipsoidal metres, ``sample, line`` pixels; all broadcast together;
    scalars in give Python floats out. Points without a solution come back NaN (never an exception).
    """

    @property
    def height_range(self) -> Tuple[float, float]:
        """(min, max) ellipsoidal height (m) over which the model is valid."""

    def project(self, lon, lat, h, *, pixel_convention: str = "gdal"):
        """Ground to image: ``(lon, lat, h) -> (sample, line)``."""

    def project_jacobian(self, lon, lat, h, *, pixel_convention: str = "gdal") -> np.ndarray:
        """``d(sample, line) / d(lon, lat, h)``, shape ``(..., 2, 3)`` (px/deg, px/deg, px/m)."""

    def localize(self, sample, line, h, *, pixel_convention: str = "gdal", full_output: bool = False):
        """Image to ground at height ``h``: ``(sample, line, h) -> (lon, lat[, LocalizationStats])``."""

    def localize_dem(self, sample, line, dem, *, pixel_convention: str = "gdal", full_output: bool = False):
        """Line of sight x DEM: ``(sample, line, dem) -> (lon, lat, h[, LocalizationStats])``."""


def pixel_shift(pixel_convention: str) -> float:
    """What to add to raw-convention pixel coordinates to get ``pixel_convention`` ones (METHODS §1)."""
    if pixel_convention == "gdal":
        return GDAL_PIXEL_OFFSET
    if pixel_convention == "rpc":
        return 0.0
    raise ValueError(f"pixel_convention must be 'gdal' or 'rpc', not {pixel_convention!r}")


def as_float_arrays(*xs) -> Tuple[Tuple[np.ndarray, ...], tuple]:
    """Broadcast float arrays, flattened, and their common shape (``()`` for scalars)."""
    arrays = np.broadcast_arrays(*[np.asarray(x, dtype=float) for x in xs])
    return tuple(a.ravel() for a in arrays), arrays[0].shape


def shape_out(values, shape: tuple):
    """A Python float for scalar input (``shape == ()``), else ``values`` reshaped to ``shape``."""
    values = np.asarray(values, dtype=float)
    if shape == ():
        return float(values.reshape(-1)[0])
    return values.reshape(shape)


class SensorModelMixin:
    """The shared half of :class:`SensorModel` (see the module docstring for the two hooks a model implements)."""

    # ------------------------------------------------------------------ hooks (flat arrays, GDAL convention)
    def _project_gdal(self, lon: np.ndarray, lat: np.ndarray, h: np.ndarray):  # pragma: no cover - abstract
        raise NotImplementedError

    def _localize_gdal(self, sample: np.ndarray, line: np.ndarray, h: np.ndarray):  # pragma: no cover - abstract
        raise NotImplementedError

    # ------------------------------------------------------------------ the contract
    def project(self, lon, lat, h, *, pixel_convention: str = "gdal"):
        """Ground to image (METHODS §1): ``(lon, lat, h) -> (sample, line)``; NaN where there is no solution."""
        shift = pixel_shift(pixel_convention) - GDAL_PIXEL_OFFSET
        (lon, lat, h), shape = as_float_arrays(lon, lat, h)
        s, l = split_points(self._project_gdal, lon, lat, h)
        s = np.asarray(s, dtype=float).ravel()
        l = np.asarray(l, dtype=float).ravel()
        if shift:
            s, l = s + shift, l + shift
        return shape_out(s, shape), shape_out(l, shape)

    def project_jacobian(self, lon, lat, h, *, pixel_convention: str = "gdal") -> np.ndarray:
        """``d(sample, line) / d(lon, lat, h)`` by central differences, shape ``(..., 2, 3)`` (METHODS §1).

        The same in either pixel convention (they differ by a constant); ``pixel_convention`` is only checked.
        """
        pixel_shift(pixel_convention)
        (lon, lat, h), shape = as_float_arrays(lon, lat, h)
        n = lon.size
        J = np.empty((n, 2, 3))
        base = (lon, lat, h)
        for k, step in enumerate(_JACOBIAN_STEPS):
            plus = [a + step if i == k else a for i, a in enumerate(base)]
            minus = [a - step if i == k else a for i, a in enumerate(base)]
            sp, lp = self._project_gdal(*plus)
            sm, lm = self._project_gdal(*minus)
            J[:, 0, k] = (np.asarray(sp, float).ravel() - np.asarray(sm, float).ravel()) / (2 * step)
            J[:, 1, k] = (np.asarray(lp, float).ravel() - np.asarray(lm, float).ravel()) / (2 * step)
        return J.reshape(shape + (2, 3))

    def localize(self, sample, line, h, *, pixel_convention: str = "gdal", full_output: bool = False):
        """Image to ground at ellipsoidal height ``h`` (METHODS §1): ``(sample, line, h) -> (lon, lat)``.

        NaN where there is no solution; with ``full_output=True`` a third item, :class:`LocalizationStats`
        (its ``max_residual_px`` is the largest re-projection error of the solutions, measured).
        """
        shift = pixel_shift(pixel_convention) - GDAL_PIXEL_OFFSET
        (s, l, hh), shape = as_float_arrays(sample, line, h)
        if shift:
            s, l = s - shift, l - shift
        lon, lat = split_points(self._localize_gdal, s, l, hh)
        lon = np.asarray(lon, dtype=float).ravel()
        lat = np.asarray(lat, dtype=float).ravel()
        out = (shape_out(lon, shape), shape_out(lat, shape))
        if not full_output:
            return out
        return out + (self._localization_stats(s, l, hh, lon, lat, iterations=0),)

    def localize_dem(self, sample, line, dem, *, pixel_convention: str = "gdal", full_output: bool = False,
                     **kw: Any):
        """Intersect the lines of sight with ``dem`` (METHODS §2): ``(sample, line, dem) -> (lon, lat, h)``.

        ``dem`` is anything :meth:`gdal_gf4cal.dem.DEM.from_user_input` accepts (a DEM, a path, a height).
        Delegates to :func:`gdal_gf4cal.localization.localize_dem` (``tol_m``, ``max_iter`` pass through); with
        ``full_output=True`` a fourth item, :class:`LocalizationStats`.
        """
        return _localize_dem(self, sample, line, dem, pixel_convention=pixel_convention, full_output=full_output,
                             **kw)

    # ------------------------------------------------------------------ helpers
    def _localization_stats(self, s, l, h, lon, lat, iterations: int) -> LocalizationStats:
        """Stats of a localisation at given heights: the re-projection error is measured, not assumed."""
        ok = np.isfinite(lon) & np.isfinite(lat)
        residual = np.nan
        if np.any(ok):
            ps, pl = self._project_gdal(lon[ok], lat[ok], h[ok])
            with np.errstate(invalid="ignore"):
                r = np.hypot(np.asarray(ps, float).ravel() - s[ok], np.asarray(pl, float).ravel() - l[ok])
            residual = float(np.nanmax(r)) if np.any(np.isfinite(r)) else np.nan
        return LocalizationStats(n_points=int(lon.size), n_failed=int(np.count_nonzero(~ok)),
                                 max_iterations=int(iterations), max_residual_px=residual)
