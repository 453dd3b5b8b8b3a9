"""Detector look-angle camera model (METHODS §5, eq. 3 of seed 000).

Each detector ``(s, l)`` of the focal plane looks along ``(tan(phi_x), tan(phi_y), 1)`` in the camera frame, with

    tan(phi_x)(s, l) = a0 + a1 s + a2 l + a3 s l + a4 s² + a5 l² + a6 s² l + a7 s l² + a8 s³ + a9 l³
    tan(phi_y)(s, l) = b0 + b1 s + ... (same ten terms)

(the paper's eq. 4 prints ``s'l'²`` twice; the seventh term is ``s'² l'``, METHODS §5).

Detector numbers ``(s, l)`` are image coordinates in GDAL's convention (centre of the first detector at 0.5).
Coefficients are stored for raw detector numbers, in the units a camera file uses; evaluation and inversion
normalise internally so that a 10240 x 10240 array is well conditioned. Push-broom sensors use the same class with
the ``l`` terms zero.

Camera file (JSON)::

    {"model": "lookangle-cubic", "size": [W, H], "x": [a0, ..., a9], "y": [b0, ..., b9],
     "pixel_convention": "gdal", "name": "...", "notes": "..."}
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Optional, Sequence, Tuple

import numpy as np

from .atomic import atomic_output
from .outputs import check_output_path
from .basis import lookangle_cubic, lookangle_cubic_derivatives
from .errors import Gf4calError

MODEL_NAME = "lookangle-cubic"
N_TERMS = 10


class CameraFormatError(Gf4calError, ValueError):
    """A camera file is missing, malformed or of another model."""


def lookangle_terms(s, l) -> np.ndarray:
    """The ten cubic terms ``1, s, l, s·l, s², l², s²·l, s·l², s³, l³``, shape ``(10, N)`` (:mod:`~gdal_gf4cal.basis`)."""
    return np.ascontiguousarray(lookangle_cubic(np.asarray(s, dtype=float).ravel(),
                                                np.asarray(l, dtype=float).ravel()).T)


def lookangle_term_derivatives(s, l) -> Tuple[np.ndarray, np.ndarray]:
    """Derivatives of :func:`lookangle_terms` with respect to s and l, each ``(10, N)``."""
    ds, dl = lookangle_cubic_derivatives(np.asarray(s, dtype=float).ravel(), np.asarray(l, dtype=float).ravel())
    return np.ascontiguousarray(ds.T), np.ascontiguousarray(dl.T)


def _normalisation_matrix(centre: Tuple[float, float], half: Tuple[float, float]) -> np.ndarray:
    """Matrix T with terms(s, l) = T @ terms(u, v) where u = (s - cs)/hs, v = (l - cl)/hl.

    Used to convert coefficients between raw detector numbers and normalised coordinates exactly.
    """
    # Evaluate terms at enough points and solve: exact because both are bases of the same cubic space restricted
    # to these ten monomials (the term set is closed under affine per-axis changes of variables).
    g = np.linspace(-1.0, 1.0, 5)
    u, v = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    s = centre[0] + half[0] * u
    l = centre[1] + half[1] * v
    Tu = lookangle_terms(u, v).T
    Ts = lookangle_terms(s, l).T
    T, *_ = np.linalg.lstsq(Tu, Ts, rcond=None)
    return T.T  # terms_raw = T @ terms_norm


@dataclass(frozen=True, eq=False)
class LookAngleModel:
    """Cubic detector look-angle model ``(s, l) -> (tan(phi_x), tan(phi_y))`` (METHODS §5)."""

    size: Tuple[int, int]
    x: np.ndarray
    y: np.ndarray
    name: str = ""
    notes: str = ""
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        size = tuple(int(v) for v in self.size)
        if len(size) != 2 or min(size) <= 0:
            raise CameraFormatError(f"camera size must be [width, height] > 0, not {self.size!r}")
        object.__setattr__(self, "size", size)
        for axis in ("x", "y"):
            arr = np.array(getattr(self, axis), dtype=float).ravel()
            if arr.size != N_TERMS or not np.all(np.isfinite(arr)):
                raise CameraFormatError(f"camera coefficients '{axis}' must be {N_TERMS} finite numbers")
            arr.flags.writeable = False
            object.__setattr__(self, axis, arr)

    # ------------------------------------------------------------------ normalisation
    @property
    def centre(self) -> Tuple[float, float]:
        return (self.size[0] / 2.0, self.size[1] / 2.0)

    @property
    def half_size(self) -> Tuple[float, float]:
        return (self.size[0] / 2.0, self.size[1] / 2.0)

    def normalise(self, s, l):
        """Detector numbers -> normalised (u, v) in about [-1, 1]."""
        (cs, cl), (hs, hl) = self.centre, self.half_size
        return (np.asarray(s, dtype=float) - cs) / hs, (np.asarray(l, dtype=float) - cl) / hl

    def normalised_coefficients(self) -> Tuple[np.ndarray, np.ndarray]:
        """Coefficients for the normalised coordinates of :meth:`normalise` (better conditioned)."""
        T = _normalisation_matrix(self.centre, self.half_size)
        return self.x @ T, self.y @ T

    @classmethod
    def from_normalised_coefficients(cls, size, xn, yn, **kwargs) -> "LookAngleModel":
        """Inverse of :meth:`normalised_coefficients`."""
        size = (int(size[0]), int(size[1]))
        centre = (size[0] / 2.0, size[1] / 2.0)
        T = _normalisation_matrix(centre, centre)
        Tinv = np.linalg.inv(T)
        return cls(size=size, x=np.asarray(xn) @ Tinv, y=np.asarray(yn) @ Tinv, **kwargs)

    # ------------------------------------------------------------------ evaluation
    def tan_angles(self, s, l):
        """``(tan(phi_x), tan(phi_y))`` at detector numbers ``(s, l)`` (GDAL convention); scalars or arrays."""
        s, l = np.broadcast_arrays(np.asarray(s, dtype=float), np.asarray(l, dtype=float))
        shape = s.shape
        u, v = self.normalise(s.ravel(), l.ravel())
        xn, yn = self._norm
        t = lookangle_terms(u, v)
        tx, ty = xn @ t, yn @ t
        if shape == ():
            return float(tx[0]), float(ty[0])
        return tx.reshape(shape), ty.reshape(shape)

    @property
    def _norm(self):
        cached = self.__dict__.get("_norm_cache")
        if cached is None:
            cached = self.normalised_coefficients()
            self.__dict__["_norm_cache"] = cached
        return cached

    def jacobian(self, s, l) -> np.ndarray:
        """``d(tan_x, tan_y) / d(s, l)``, shape ``(..., 2, 2)``."""
        s, l = np.broadcast_arrays(np.asarray(s, dtype=float), np.asarray(l, dtype=float))
        shape = s.shape
        u, v = self.normalise(s.ravel(), l.ravel())
        du, dv = lookangle_term_derivatives(u, v)
        xn, yn = self._norm
        hs, hl = self.half_size
        J = np.empty((u.size, 2, 2))
        J[:, 0, 0] = (xn @ du) / hs
        J[:, 0, 1] = (xn @ dv) / hl
        J[:, 1, 0] = (yn @ du) / hs
        J[:, 1, 1] = (yn @ dv) / hl
        return J.reshape(shape + (2, 2))

    def angular_pixel_size(self, s, l):
        """Local angular size of one detector along s and along l (tan units per pixel)."""
        J = self.jacobian(s, l)
        return np.hypot(J[..., 0, 0], J[..., 1, 0]), np.hypot(J[..., 0, 1], J[..., 1, 1])

    def detector_of(self, tan_x, tan_y, s0=None, l0=None, *, tol_px: float = 1e-9, max_iter: int = 30):
        """Invert the model: detector numbers whose look angles are ``(tan_x, tan_y)`` (2-D Newton, vectorised).

        ``s0, l0`` are starting points (default: the inverse of the linear part). NaN where it does not converge.
        """
        tx, ty = np.broadcast_arrays(np.asarray(tan_x, dtype=float), np.asarray(tan_y, dtype=float))
        shape = tx.shape
        tx, ty = tx.ravel(), ty.ravel()
        if s0 is None or l0 is None:
            # Linear part around the array centre gives a start within the distortion (a few pixels).
            c = self.centre
            t0 = np.array(self.tan_angles(c[0], c[1]))
            J0 = self.jacobian(c[0], c[1])
            d = np.linalg.solve(J0, np.vstack([tx - t0[0], ty - t0[1]]))
            s, l = c[0] + d[0], c[1] + d[1]
        else:
            s = np.broadcast_to(np.asarray(s0, dtype=float), shape).ravel().copy()
            l = np.broadcast_to(np.asarray(l0, dtype=float), shape).ravel().copy()
        ok = np.zeros(tx.size, dtype=bool)
        active = np.arange(tx.size)
        for _ in range(max_iter):
            cx, cy = self.tan_angles(s[active], l[active])
            J = self.jacobian(s[active], l[active])
            rx, ry = tx[active] - cx, ty[active] - cy
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            ds = (J[:, 1, 1] * rx - J[:, 0, 1] * ry) / det
            dl = (J[:, 0, 0] * ry - J[:, 1, 0] * rx) / det
            s[active] += ds
            l[active] += dl
            done = (np.abs(ds) <= tol_px) & (np.abs(dl) <= tol_px)
            ok[active[done]] = True
            active = active[~done & np.isfinite(ds) & np.isfinite(dl)]
            if active.size == 0:
                break
        s[~ok], l[~ok] = np.nan, np.nan
        if shape == ():
            return float(s[0]), float(l[0])
        return s.reshape(shape), l.reshape(shape)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_nominal(cls, size: Sequence[int], focal_length_m: float, pixel_size_m: float,
                     principal_point: Optional[Tuple[float, float]] = None, radial_k1: float = 0.0,
                     name: str = "nominal") -> "LookAngleModel":
        """Ideal pinhole camera from focal length, detector pitch and principal point (default: array centre).

        ``tan(phi_x) = (s - s0) * p / f``, ``tan(phi_y) = (l - l0) * p / f``, optionally with a cubic radial term
        ``k1 * r²`` (r in tan units). For users without a camera file: the recalibrated RPC is equally right;
        the calibrated camera is then meaningful relative to this nominal model (METHODS §5).
        """
        if focal_length_m <= 0 or pixel_size_m <= 0:
            raise CameraFormatError("focal length and pixel size must be positive")
        W, H = int(size[0]), int(size[1])
        s0, l0 = principal_point if principal_point is not None else (W / 2.0, H / 2.0)
        k = pixel_size_m / focal_length_m
        # Fit the exact expression on a grid (exact for k1 = 0; cubic radial terms are representable too).
        g_s = np.linspace(0, W, 9)
        g_l = np.linspace(0, H, 9)
        S, L = (a.ravel() for a in np.meshgrid(g_s, g_l, indexing="ij"))
        tx, ty = (S - s0) * k, (L - l0) * k
        r2 = tx * tx + ty * ty
        tx, ty = tx * (1 + radial_k1 * r2), ty * (1 + radial_k1 * r2)
        model = cls.fit(S, L, tx, ty, size=(W, H), name=name,
                        notes=f"nominal: f={focal_length_m} m, pixel={pixel_size_m} m, pp=({s0}, {l0}), k1={radial_k1}")
        return model

    @classmethod
    def fit(cls, s, l, tan_x, tan_y, size, weights=None, **kwargs) -> "LookAngleModel":
        """Least-squares cubic model through samples ``(s, l) -> (tan_x, tan_y)``, solved normalised."""
        size = (int(size[0]), int(size[1]))
        centre = (size[0] / 2.0, size[1] / 2.0)
        u = (np.asarray(s, dtype=float).ravel() - centre[0]) / centre[0]
        v = (np.asarray(l, dtype=float).ravel() - centre[1]) / centre[1]
        A = lookangle_terms(u, v).T
        w = np.ones(u.size) if weights is None else np.sqrt(np.asarray(weights, dtype=float).ravel())
        rhs = np.column_stack([np.asarray(tan_x, dtype=float).ravel(), np.asarray(tan_y, dtype=float).ravel()])
        coef, *_ = np.linalg.lstsq(A * w[:, None], rhs * w[:, None], rcond=None)
        return cls.from_normalised_coefficients(size, coef[:, 0], coef[:, 1], **kwargs)

    # ------------------------------------------------------------------ I/O
    def to_dict(self) -> dict:
        d = {"model": MODEL_NAME, "size": list(self.size), "x": [float(v) for v in self.x],
             "y": [float(v) for v in self.y], "pixel_convention": "gdal",
             "terms": ["1", "s", "l", "s*l", "s^2", "l^2", "s^2*l", "s*l^2", "s^3", "l^3"]}
        if self.name:
            d["name"] = self.name
        if self.notes:
            d["notes"] = self.notes
        d.update(self.extra)
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera") -> "LookAngleModel":
        if not isinstance(d, dict):
            raise CameraFormatError(f"{source}: not a JSON object")
        if d.get("model") != MODEL_NAME:
            raise CameraFormatError(f"{source}: model is {d.get('model')!r}, expected {MODEL_NAME!r}")
        for key in ("size", "x", "y"):
            if key not in d:
                raise CameraFormatError(f"{source}: missing key {key!r}")
        if d.get("pixel_convention", "gdal") != "gdal":
            raise CameraFormatError(f"{source}: pixel_convention {d['pixel_convention']!r} is not supported "
                                    "(use 'gdal', centre of the first detector at 0.5)")
        known = {"model", "size", "x", "y", "name", "notes", "pixel_convention", "terms"}
        extra = {k: v for k, v in d.items() if k not in known}
        try:
            return cls(size=tuple(d["size"]), x=d["x"], y=d["y"], name=d.get("name", ""), notes=d.get("notes", ""),
                       extra=extra)
        except (TypeError, ValueError) as exc:
            raise CameraFormatError(f"{source}: {exc}") from None

    def to_json(self, path, overwrite: bool = False) -> str:
        """Write the camera file atomically (temporary file in the same folder, then ``os.replace``).

        Raises :class:`~gdal_gf4cal.errors.InputOverwriteError` if ``path`` exists and ``overwrite`` is false.
        """
        path = check_output_path(path, overwrite=overwrite)
        with atomic_output(path) as tmp, open(tmp, "w") as fh:
            json.dump(self.to_dict(), fh, indent=2)
            fh.write("\n")
        return path

    @classmethod
    def from_json(cls, path) -> "LookAngleModel":
        path = os.fspath(path)
        try:
            with open(path) as fh:
                d = json.load(fh)
        except FileNotFoundError:
            raise CameraFormatError(f"camera file not found: {path}") from None
        except json.JSONDecodeError as exc:
            raise CameraFormatError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
        except (OSError, UnicodeDecodeError) as exc:    # a folder, no permission, a binary file
            raise CameraFormatError(f"{path}: cannot read the camera file "
                                    f"({getattr(exc, 'strerror', None) or exc.__class__.__name__}); "
                                    "give a lookangle-cubic JSON file") from None
        return cls.from_dict(d, source=path)
