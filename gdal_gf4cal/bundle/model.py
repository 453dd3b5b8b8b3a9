"""The bundle-adjustment problem: views, their image-space corrections and the rays of the points (METHODS §11).

Per view ``j`` a correction ``Δ_j`` in the bases of METHODS §4.1 (:class:`~gdal_gf4cal.compensation.
CompensationModel`: translation, shift-drift, affine), a polynomial of ``u = (s' - w/2) / (w/2)``,
``v = (l' - h/2) / (h/2)`` over the view's image (``(s', l')`` the RPC-predicted position, so the estimate folds
into a new RPC exactly as ``refine``'s does). The parameters of all views form one vector: view after view, the
sample terms then the line terms (the order of ``CompensationResult.coef_sample`` / ``coef_line``).

Points (ties and GCPs) are the rows of the observation table grouped by ``point_id``; every point has a padded
layout of ``2 K`` ray rows (``K`` the largest number of views seeing one point; sample, line per ray) followed by
three ground rows (east, north, up prior: a GCP's known ground, the DEM's weak height prior), the shape
:func:`gdal_gf4cal.estimation.solve_with_points` eliminates.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..basis import monomial_derivatives, monomials, term_name
from ..compensation import CompensationModel
from ..errors import GCPError

__all__ = ["BundleError", "DEFAULT_PRIOR_M", "DEFAULT_PRIOR_PX", "BUNDLE_MODELS", "MIN_SPAN", "PAIR_FOLLOWER_FACTOR", "ViewLayout", "Rays", "prior_sigma_px",
           "pixel_size_m"]

#: Prior standard deviation (m on the ground, converted to px by the view's pixel size) of every correction
#: parameter when the RPC states no bias error (ERR_BIAS): the absolute accuracy of current very-high-resolution
#: vendor RPCs (Pleiades: 5 m, ~7 px). Wide enough that a DEM's height prior, not the views' priors, fixes the
#: along-epipolar part of the relative bias (which ties alone cannot see).
DEFAULT_PRIOR_M = 5.0
#: A pair of views is adjusted relative to its first view (the reference, as CARS corrects the right image of a
#: stereo pair): the second view's default prior is this many times wider. With two views nothing in the ties or a
#: DEM says which RPC is off, so equal priors would split one view's bias between both and move the block; the
#: first view named holds it instead (``--prior-sigma`` for both views, or per view, overrides this).
PAIR_FOLLOWER_FACTOR = 1000.0
#: Prior standard deviation (px) when neither ERR_BIAS nor the pixel size is known.
DEFAULT_PRIOR_PX = 3.0
#: Correction models of the bundle adjustment (METHODS §11).
BUNDLE_MODELS = ("translation", "shift-drift", "affine")
#: Smallest spread of a view's ties (5th-95th percentile, as a fraction of the image side) along each axis for a
#: correction with slope terms; below it the view falls back to a translation (nothing extrapolated silently).
MIN_SPAN = 0.3


class BundleError(GCPError):
    """Bad input of a bundle adjustment (one line: the cause and what to do)."""


@dataclass
class ViewLayout:
    """Views and their parameters: ``views`` (ids), ``sizes`` (w, h), ``models_used`` (view -> CompensationModel),
    ``offset`` (start of each view's parameters in the vector), ``n_params``, ``prior_px`` (per parameter),
    ``notes``."""

    views: List[str]
    sizes: Dict[str, Tuple[int, int]]
    models_used: Dict[str, CompensationModel]
    offset: Dict[str, int]
    n_params: int
    prior_px: np.ndarray
    notes: List[str]

    def frame(self, view: str) -> Tuple[float, float, float, float]:
        w, h = self.sizes[view]
        return (0.5 * w, 0.5 * w, 0.5 * h, 0.5 * h)

    def slices(self, view: str) -> Tuple[slice, slice]:
        """Slices of the view's sample and line coefficients in the parameter vector."""
        ts, tl = self.models_used[view].terms
        o = self.offset[view]
        return slice(o, o + len(ts)), slice(o + len(ts), o + len(ts) + len(tl))

    @property
    def names(self) -> List[str]:
        out = []
        for v in self.views:
            ts, tl = self.models_used[v].terms
            out += [f"{v}:{term_name('sample', t)}" for t in ts] + [f"{v}:{term_name('line', t)}" for t in tl]
        return out

    def design(self, view: str, s, l):
        """Basis of the view's sample and line corrections at RPC-predicted ``(s, l)``: ``(A_s, A_l)``."""
        s0, ss, l0, ls = self.frame(view)
        u, v = (np.asarray(s, float) - s0) / ss, (np.asarray(l, float) - l0) / ls
        ts, tl = self.models_used[view].terms
        return monomials(ts, u, v), monomials(tl, u, v)

    def correction(self, view: str, x, s, l, design: bool = False):
        """``(ds, dl)`` and ``d(ds, dl)/d(s, l)`` (..., 2, 2) of the view's correction at predicted ``(s, l)``;
        with ``design`` also :meth:`design` there (the same monomials)."""
        s0, ss, l0, ls = self.frame(view)
        u, v = (np.asarray(s, float) - s0) / ss, (np.asarray(l, float) - l0) / ls
        ts, tl = self.models_used[view].terms
        sl_s, sl_l = self.slices(view)
        cs, cl = x[sl_s], x[sl_l]
        dsu, dsv = monomial_derivatives(ts, u, v)
        dlu, dlv = monomial_derivatives(tl, u, v)
        jac = np.empty(np.shape(u) + (2, 2))
        jac[..., 0, 0], jac[..., 0, 1] = dsu @ cs / ss, dsv @ cs / ls
        jac[..., 1, 0], jac[..., 1, 1] = dlu @ cl / ss, dlv @ cl / ls
        a_s, a_l = monomials(ts, u, v), monomials(tl, u, v)
        return (a_s @ cs, a_l @ cl, jac) + (((a_s, a_l),) if design else ())


@dataclass
class Rays:
    """The observation rows as arrays: ``view`` (index into the layout's views), ``point`` (index into
    ``point_ids``), ``slot`` (the ray's place in its point's padded rows), ``meas`` (n, 2), ``sigma``,
    ``is_gcp``, ``control`` (enters the estimate), ``ground`` (n_points, 3: GCPs' lon, lat, h; NaN for ties),
    ``point_ids``, ``point_is_gcp``, ``point_control``, ``k`` (largest number of rays of one point), ``row`` (each
    ray's row in the observation table; None: the same order). :func:`~gdal_gf4cal.bundle.inputs.make_rays` sorts
    the rays by view, then point: a view's rays are then one slice (:meth:`view_rows`), in the order of its
    points."""

    view: np.ndarray
    point: np.ndarray
    slot: np.ndarray
    meas: np.ndarray
    sigma: np.ndarray
    is_gcp: np.ndarray
    control: np.ndarray
    ground: np.ndarray
    point_ids: np.ndarray
    point_is_gcp: np.ndarray
    point_control: np.ndarray
    k: int
    row: Optional[np.ndarray] = None

    @cached_property
    def _by_view(self) -> bool:
        return not (self.view.size > 1 and bool(np.any(self.view[1:] < self.view[:-1])))

    def view_rows(self, j: int):
        """The rays of view ``j``: a slice when the rays are sorted by view, else their indices."""
        if not self._by_view:
            return np.flatnonzero(self.view == j)
        a, b = np.searchsorted(self.view, [j, j + 1])
        return slice(int(a), int(b))

    def to_table_order(self, a: np.ndarray) -> np.ndarray:
        """Per-ray values ``a`` (first axis: the rays) in the observation table's row order."""
        if self.row is None:
            return a
        out = np.empty_like(a)
        out[self.row] = a
        return out

    @property
    def n_points(self) -> int:
        return int(self.point_ids.size)

    @property
    def rows_per_point(self) -> int:
        return 2 * self.k + 3

    def subset(self, points: np.ndarray) -> "Rays":
        """The rays of the points ``points`` (bool, n_points), points renumbered in order."""
        new = np.full(self.n_points, -1)
        new[points] = np.arange(int(points.sum()))
        r = new[self.point] >= 0
        return Rays(view=self.view[r], point=new[self.point[r]], slot=self.slot[r], meas=self.meas[r],
                    sigma=self.sigma[r], is_gcp=self.is_gcp[r], control=self.control[r], ground=self.ground[points],
                    point_ids=self.point_ids[points], point_is_gcp=self.point_is_gcp[points],
                    point_control=self.point_control[points], k=self.k,
                    row=None if self.row is None else self.row[r])

    def flat_rows(self, axis: int) -> np.ndarray:
        """Each ray's row (``axis`` 0: sample, 1: line) in the flattened padded layout ``(n_points * R)``."""
        return self.point * self.rows_per_point + 2 * self.slot + axis


def pixel_size_m(rpc, size: Tuple[int, int]) -> float:
    """Ground size of a pixel (m, geometric mean of both axes) at the image centre and the RPC's mid height."""
    from ..geodesy import metres_per_degree
    h = float(np.mean(rpc.height_range))
    lon, lat = rpc.localize(0.5 * size[0], 0.5 * size[1], h)
    jac = np.asarray(rpc.project_jacobian(lon, lat, h), float)[:2, :2]
    mx, my = metres_per_degree(lat, h)
    det = abs(np.linalg.det(jac / np.array([float(mx), float(my)])[None, :]))
    return float(1.0 / np.sqrt(det)) if det > 0 else float("nan")


def prior_sigma_px(rpc, size: Tuple[int, int], given=None) -> Tuple[float, str]:
    """Prior σ (px) of a view's correction parameters and where it comes from: ``given``, else the RPC's ERR_BIAS
    (m, per horizontal axis) over the pixel size, else :data:`DEFAULT_PRIOR_M` over the pixel size, else
    :data:`DEFAULT_PRIOR_PX`."""
    if given is not None:
        val = float(given)
        if not np.isfinite(val) or val <= 0:
            raise BundleError(f"prior sigma must be a positive number of pixels, got {given!r}")
        return val, "given"
    bias = getattr(rpc, "err_bias", None)
    gsd = pixel_size_m(rpc, size)
    if not (np.isfinite(gsd) and gsd > 0):
        return DEFAULT_PRIOR_PX, f"default {DEFAULT_PRIOR_PX:g} px"
    if bias is not None and np.isfinite(bias) and bias > 0:
        return float(bias) / gsd, f"ERR_BIAS {float(bias):g} m / {gsd:.3g} m px"
    return DEFAULT_PRIOR_M / gsd, f"default {DEFAULT_PRIOR_M:g} m / {gsd:.3g} m px"
