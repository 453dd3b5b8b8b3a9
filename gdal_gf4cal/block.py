"""Multi-CCD / multi-band block calibration in RPC space (METHODS §8, seed 003, Jilin1-KF01A wide-field camera).

Model (METHODS §8, one RPC per CCD image and band; image ``i`` of CCD ``k``, band ``b``; GDAL pixel convention)::

    s_meas = s_RPC_i(X) + E_s + I_s(u)        E_s = (e0 + e3 t - kappa Y_i) / r_i
    l_meas = l_RPC_i(X) + E_l + I_l(u)        E_l = (e1 + e4 t + kappa X_i(u)) / r_i
    I_s = sum_j<=3 a_ij u^j,  I_l = sum_j<=3 b_ij u^j,  u = (s_meas - W_i/2) / (W_i/2),  t = r_i (l_meas - H_i/2) / T

* the **exterior** ``e0, e1`` (roll, pitch offsets), ``e3, e4`` (their drifts), ``kappa`` (yaw, in mrad) is shared
  by every CCD and band of the group; ``e*`` are in pixels of the reference band;
* the **interior** (a cubic in the detector position ``u`` per axis) belongs to each image (CCD and band);
* ``r_i`` is the image's pixel size over the reference band's (0.25 for 0.75 m pan against 3 m MS), ``X_i(u)``
  the detector's cross-track focal-plane position and ``Y_i`` its row's along-track offset, in px of the reference
  band, ``T`` half the height of the reference CCD image (so ``t`` is in the same time units for every image);
* the **datum**: the reference CCD's ``a0, b0, b1`` duplicate ``e0, e1, kappa`` and are fixed at 0 (a frozen
  block ``datum:<image>``);
* every **tie point** has unknown ``(lon, lat)`` with ``h`` from the DEM (rays of adjacent CCDs are nearly parallel:
  no height from intersection), eliminated by Schur complement
  (:func:`~gdal_gf4cal.estimation.solve_with_points`, sparse): the reduced system is ``5 + 8 n_images - 3``
  unknowns whatever the number of tie points; GCPs (known ground) add to it directly.

The **layout** comes from what a user has (:func:`derive_layout`): the reference-band CCD images in their order
across track, which image is a band of which CCD (``bands_of``), and the RPCs: ``r_i`` from the RPC Jacobians,
``X_i`` by chaining each CCD's centre into its neighbour's RPC. ``Y_i`` is set to 0: a constant per image, it is
absorbed by the free constant terms of every image but the reference CCD, where it only redefines ``e0``. Adjacent
CCDs must overlap (checked on their RPCs).

**Solvers**: ``"simultaneous"`` (default): Gauss-Newton on exterior + interiors + tie points at once;
``"alternating"`` (the paper's scheme): exterior with interiors fixed, then interiors with the exterior fixed
(frozen columns), repeated until stable. **Band-to-band**: the reference band (all images not in ``bands_of``) is
adjusted absolutely (GCPs + ties); then the other bands' interiors alone, with the reference exterior and interiors
frozen, from their tie points and their own control GCPs if any. **Robust weights**: the core's radial
Huber weights (:func:`~gdal_gf4cal.estimation.radial_huber_weights`) on residuals normalised by their redundancy;
first down-weighting only, then rejection (``z > 5``), until the rejected set is stable.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from .basis import detector_polynomial
from .errors import DegenerateGeometryError, GCPError
from .estimation import Block, Estimate, weighted_lsq
from .sensor import SensorModelMixin

__all__ = ["EXTERIOR_NAMES", "DATUM_TERMS", "ImageLayout", "BlockLayout", "BlockEstimate", "BlockCorrectedRPC",
           "derive_layout", "adjust_block", "corrected_model", "seam_offsets", "calibration_dict",
           "write_calibration", "read_calibration", "calibrated_model", "prediction_std", "layout_from_calibration",
           "BlockError", "supported_degree"]

EXTERIOR_NAMES = ("e0", "e1", "e3", "e4", "kappa_mrad")
INTERIOR_NAMES = ("a0", "a1", "a2", "a3", "b0", "b1", "b2", "b3")
#: Interior terms of the reference CCD that duplicate the exterior (e0, e1, kappa): fixed at 0 (METHODS §8 datum).
DATUM_TERMS = ("a0", "b0", "b1")
CALIBRATION_MODEL = "block-rpc-cubic"
#: A polynomial term is estimated only where its observations support it (METHODS §8, coverage): the largest
#: prediction variance of the polynomial over the whole detector (interior, in ``u``) or the whole strip (exterior
#: drifts, in ``t``) at most this many times its largest at an observation (5x the standard deviation: a cubic
#: needs about 70 % of the detector when centred, 78 % from one edge; a slope a third of it). Higher terms are held
#: at 0 before solving: an interior cubic fitted on 800 of 40,000 detector columns extrapolated to tens of pixels.
#: Full coverage gives 1.
MAX_EXTRAPOLATION_VARIANCE = 25.0


class BlockError(GCPError):
    """A block that cannot be adjusted as given (layout, overlaps, images, control): the message says what to do."""


# ----------------------------------------------------------------------------------------------------- layout
@dataclass
class ImageLayout:
    """Where one image sits in the group (METHODS §8): see the module docstring for ``ratio``, ``x0_px``, ``y_px``."""

    image_id: str
    reference: str            # the reference-band image of its CCD (itself for reference-band images)
    ccd: int                  # 1-based position across track of its CCD, in the order given
    size: Tuple[int, int]
    ratio: float = 1.0        # pixel size / reference band pixel size
    x0_px: float = 0.0        # focal-plane cross-track position of the detector centre, ref-band px
    y_px: float = 0.0         # along-track row offset, ref-band px

    @property
    def is_reference(self) -> bool:
        return self.reference == self.image_id


@dataclass
class BlockLayout:
    """The group: its images (reference band first, in CCD order), the reference CCD and the time scale ``T``."""

    images: Dict[str, ImageLayout]
    order: List[str]
    reference_ccd: str
    time_scale: float

    @property
    def band_images(self) -> List[str]:
        return [i for i, im in self.images.items() if not im.is_reference]

    def adjacent_pairs(self) -> List[Tuple[str, str]]:
        """Adjacent reference-band CCD images (left, right), in the order given."""
        return list(zip(self.order[:-1], self.order[1:]))

    def to_dict(self) -> Dict[str, Any]:
        return {"order": list(self.order), "reference_ccd": self.reference_ccd, "time_scale": self.time_scale,
                "images": {k: {"reference": v.reference, "ccd": v.ccd, "size": list(v.size), "ratio": v.ratio,
                               "x0_px": v.x0_px, "y_px": v.y_px} for k, v in self.images.items()}}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "BlockLayout":
        ims = {k: ImageLayout(k, v["reference"], int(v["ccd"]), tuple(int(x) for x in v["size"]), float(v["ratio"]),
                              float(v["x0_px"]), float(v.get("y_px", 0.0))) for k, v in d["images"].items()}
        return cls(ims, list(d["order"]), str(d["reference_ccd"]), float(d["time_scale"]))


def _model_size(model, size=None) -> Tuple[int, int]:
    if size is not None:
        return int(size[0]), int(size[1])
    if getattr(model, "size", None) is not None:
        return int(model.size[0]), int(model.size[1])
    # an RPC alone: its normalisation spans the image
    return int(round(2 * model.samp_off + 1)), int(round(2 * model.line_off + 1))


def _mid_height(model) -> float:
    lo, hi = model.height_range
    return 0.5 * (lo + hi)


def _overlap_fraction(a, size_a, b, size_b, h, n: int = 9) -> float:
    """Share of a grid over image ``b`` that falls inside image ``a`` (through ``b.localize`` and ``a.project``)."""
    W, H = size_b
    s, l = (v.ravel() for v in np.meshgrid((np.arange(n) + 0.5) * W / n, (np.arange(n) + 0.5) * H / n))
    lon, lat = b.localize(s, l, np.full(s.shape, h))
    sa, la = a.project(lon, lat, np.full(s.shape, h))
    inside = np.isfinite(sa) & np.isfinite(la) & (sa >= 0) & (sa <= size_a[0]) & (la >= 0) & (la <= size_a[1])
    return float(np.mean(inside))


def _pixel_ground_size(model, size, h) -> float:
    lon, lat = model.localize(size[0] / 2.0, size[1] / 2.0, h)
    j = np.asarray(model.project_jacobian(lon, lat, h))[..., :2].reshape(2, 2)
    from .geodesy import metres_per_degree
    mx, my = metres_per_degree(lat, h)
    j = j / np.array([float(mx), float(my)])[None, :]
    return float(1.0 / math.sqrt(abs(np.linalg.det(j))))


def derive_layout(models: Mapping[str, Any], order: Sequence[str], *, bands_of: Optional[Mapping[str, str]] = None,
                  sizes: Optional[Mapping[str, Tuple[int, int]]] = None, reference_ccd: Optional[str] = None,
                  h: Optional[float] = None) -> BlockLayout:
    """The group's layout from the RPCs and what the user says (module docstring, METHODS §8).

    Parameters
    ----------
    models : ``{image id: sensor model}`` (RPCs).
    order : the reference-band CCD images, in their order across track (adjacent ones must overlap).
    bands_of : ``{band image id: reference-band image id of its CCD}`` for the other bands (relative calibration).
    sizes : ``{image id: (width, height)}`` (default: the model's ``size`` or its RPC normalisation).
    reference_ccd : the CCD image whose ``a0, b0, b1`` fix the datum (default: the middle one of ``order``).
    h : height of the overlap checks (default: the middle of the first RPC's height range).

    Raises
    ------
    BlockError
        An image overlapping no other CCD image (images of different groups or scenes), adjacent CCDs without
        overlap, a band image outside its CCD's image, unknown or repeated images.
    """
    bands_of = dict(bands_of or {})
    order = [str(o) for o in order]
    if len(order) < 1:
        raise BlockError("no reference-band CCD image; give the CCD images of one band (and --bands-of the others)")
    if len(set(order)) != len(order):
        raise BlockError("an image is given twice; give each CCD image once")
    for im in list(order) + list(bands_of):
        if im not in models:
            raise BlockError(f"image {im!r} has no sensor model; give its RPC")
    for band, ref in bands_of.items():
        if band in order:
            raise BlockError(f"{band} is given both as a CCD image and as a band of {ref}; give it once")
        if ref not in order:
            raise BlockError(f"--bands-of {band}={ref}: {ref} is not one of the reference-band CCD images "
                             f"({', '.join(order)})")
    sizes = {k: _model_size(m, (sizes or {}).get(k)) for k, m in models.items()}
    h = _mid_height(models[order[0]]) if h is None else float(h)
    ref = reference_ccd if reference_ccd is not None else order[(len(order) - 1) // 2]
    if ref not in order:
        raise BlockError(f"reference CCD {ref!r} is not one of the reference-band CCD images ({', '.join(order)})")
    # groups mixed: an image that overlaps none of the others
    if len(order) > 1:
        for a in order:
            if all(_overlap_fraction(models[b], sizes[b], models[a], sizes[a], h) == 0.0
                   and _overlap_fraction(models[a], sizes[a], models[b], sizes[b], h) == 0.0
                   for b in order if b != a):
                raise BlockError(f"{a} overlaps none of the other CCD images: the images are not one group "
                                 "(different groups or scenes mixed); give the CCD images of one group")
    for a, b in zip(order[:-1], order[1:]):
        if _overlap_fraction(models[a], sizes[a], models[b], sizes[b], h, n=33) == 0.0:
            raise BlockError(f"no overlap between {a} and {b}, given as adjacent CCDs; list the CCD images in their "
                             "order across track")
    gsd_ref = _pixel_ground_size(models[ref], sizes[ref], h)
    layout: Dict[str, ImageLayout] = {}
    x0 = {order[0]: 0.0}
    for a, b in zip(order[:-1], order[1:]):
        lon, lat = models[b].localize(sizes[b][0] / 2.0, sizes[b][1] / 2.0, h)
        sa, _ = models[a].project(lon, lat, h)
        ra = _pixel_ground_size(models[a], sizes[a], h) / gsd_ref
        x0[b] = x0[a] + (float(sa) - sizes[a][0] / 2.0) * ra
    for k, im in enumerate(order):
        layout[im] = ImageLayout(im, im, k + 1, sizes[im], _pixel_ground_size(models[im], sizes[im], h) / gsd_ref,
                                 x0[im] - x0[ref])
    for band, r in bands_of.items():
        if _overlap_fraction(models[r], sizes[r], models[band], sizes[band], h) == 0.0:
            raise BlockError(f"--bands-of {band}={r}: {band} does not overlap {r}; give the reference-band image "
                             "of the same CCD")
        lon, lat = models[band].localize(sizes[band][0] / 2.0, sizes[band][1] / 2.0, h)
        sr, _ = models[r].project(lon, lat, h)
        x = layout[r].x0_px + (float(sr) - sizes[r][0] / 2.0) * layout[r].ratio
        layout[band] = ImageLayout(band, r, layout[r].ccd, sizes[band],
                                   _pixel_ground_size(models[band], sizes[band], h) / gsd_ref, x)
    return BlockLayout(layout, order, ref, sizes[ref][1] / 2.0)


# ----------------------------------------------------------------------------------------------------- the model
def _local_design(im: ImageLayout, time_scale: float, s, l) -> np.ndarray:
    """``(n, 2, 13)`` derivatives of the (sample, line) correction of image ``im`` at measured ``(s, l)`` by
    ``[e0, e1, e3, e4, kappa_mrad, a0..a3, b0..b3]`` (module docstring)."""
    s = np.asarray(s, float).ravel()
    l = np.asarray(l, float).ravel()
    W, H = im.size
    u = (s - W / 2.0) / (W / 2.0)
    t = im.ratio * (l - H / 2.0) / time_scale
    r = im.ratio
    n = s.size
    d = np.zeros((n, 2, 13))
    d[:, 0, 0] = 1.0 / r
    d[:, 0, 2] = t / r
    d[:, 0, 4] = -1e-3 * im.y_px / r
    d[:, 1, 1] = 1.0 / r
    d[:, 1, 3] = t / r
    d[:, 1, 4] = 1e-3 * (im.x0_px / r + (W / 2.0) * u)
    pw = np.stack([np.ones(n), u, u * u, u ** 3], axis=1)
    d[:, 0, 5:9] = pw
    d[:, 1, 9:13] = pw
    return d


@dataclass
class ImageCorrection:
    """The block correction of one image: exterior (5) and interior (8) values with its layout entry."""

    layout: ImageLayout
    time_scale: float
    exterior: np.ndarray
    interior: np.ndarray

    def correction(self, sample, line) -> Tuple[np.ndarray, np.ndarray]:
        """(ds, dl) px at measured GDAL-convention ``(sample, line)``."""
        d = _local_design(self.layout, self.time_scale, sample, line)
        v = d @ np.concatenate([self.exterior, self.interior])
        return v[:, 0], v[:, 1]

    def to_dict(self) -> Dict[str, Any]:
        im = self.layout
        return {"reference": im.reference, "ccd": im.ccd, "size": list(im.size), "ratio": im.ratio,
                "x0_px": im.x0_px, "y_px": im.y_px,
                "interior": {n: float(v) for n, v in zip(INTERIOR_NAMES, self.interior)}}


class BlockCorrectedRPC(SensorModelMixin):
    """An image's RPC with its block correction (METHODS §8): ``project`` solves ``s = s_RPC + E + I(u(s))`` by
    fixed-point iteration (the correction's slope is far below 1), ``localize`` removes the correction from the
    measured position and localises it with the RPC. GDAL pixel convention. No writers: fit an RPC of it
    (:func:`gdal_gf4cal.rpc_fit.fit_rpc_from_model`)."""

    def __init__(self, rpc, corr: ImageCorrection):
        self.rpc, self.corr = rpc, corr
        self.size = tuple(corr.layout.size)

    @property
    def height_range(self):
        return tuple(self.rpc.height_range)

    def _project_gdal(self, lon, lat, h):
        s0, l0 = self.rpc.project(lon, lat, h)
        s0 = np.asarray(s0, float).ravel()
        l0 = np.asarray(l0, float).ravel()
        s, l = s0.copy(), l0.copy()
        for _ in range(30):
            ds, dl = self.corr.correction(s, l)
            ns, nl = s0 + ds, l0 + dl
            done = np.nanmax(np.abs(np.concatenate([ns - s, nl - l]))) if ns.size else 0.0
            s, l = ns, nl
            if not done > 1e-10:
                break
        return s, l

    def _localize_gdal(self, sample, line, h):
        ds, dl = self.corr.correction(sample, line)
        return self.rpc.localize(np.asarray(sample, float).ravel() - ds, np.asarray(line, float).ravel() - dl, h)


# ----------------------------------------------------------------------------------------------------- parameters
def _parameter_blocks(layout: BlockLayout) -> Tuple[List[Block], Dict[str, np.ndarray]]:
    """Named blocks (``exterior``, ``datum:<ref>``, ``interior:<image>``) and per image the 13 global indices of
    ``[exterior, a0..a3, b0..b3]``."""
    blocks = [Block("exterior", EXTERIOR_NAMES)]
    pos = len(EXTERIOR_NAMES)
    index: Dict[str, np.ndarray] = {}
    for im in layout.images:
        if im == layout.reference_ccd:
            datum = [n for n in INTERIOR_NAMES if n in DATUM_TERMS]
            rest = [n for n in INTERIOR_NAMES if n not in DATUM_TERMS]
            blocks.append(Block(f"datum:{im}", [f"{im}.{n}" for n in datum]))
            blocks.append(Block(f"interior:{im}", [f"{im}.{n}" for n in rest]))
            where = {n: pos + i for i, n in enumerate(datum + rest)}
            pos += 8
        else:
            blocks.append(Block(f"interior:{im}", [f"{im}.{n}" for n in INTERIOR_NAMES]))
            where = {n: pos + i for i, n in enumerate(INTERIOR_NAMES)}
            pos += 8
        index[im] = np.array(list(range(len(EXTERIOR_NAMES))) + [where[n] for n in INTERIOR_NAMES])
    return blocks, index


@dataclass
class BlockEstimate(Estimate):
    """The core's :class:`~gdal_gf4cal.estimation.Estimate` of a block adjustment (per observation row: 2 residuals,
    sample then line, in :attr:`residuals`), plus the block's own results.

    ``table``: the observation table with ``pred_sample_before/after``, ``res_sample_before/after`` (and line),
    ``outlier`` flags, tie-point ground coordinates estimated (``lon, lat, h``); ``layout``; ``stages``: per stage
    (``reference`` band, ``bands``) the images, solver, iterations (normal-equation solves), convergence and the
    size of the reduced system; ``comparison``: the other solver's stages when asked (:func:`adjust_block`).
    """

    table: Any = None
    layout: Optional[BlockLayout] = None
    stages: List[Dict[str, Any]] = field(default_factory=list)
    comparison: Optional[Dict[str, Any]] = None
    cov_pending: List[Any] = field(default_factory=list, repr=False)

    def complete_covariance(self) -> np.ndarray:
        """Add to :attr:`cov` what the earlier stages' errors do to the band stage's parameters
        (:func:`_propagate_frozen`; computed once, on demand: :func:`prediction_std` calls it). Returns ``cov``."""
        while self.cov_pending:
            _propagate_frozen(*self.cov_pending.pop(0), self.cov)
        return self.cov

    def correction(self, image_id: str) -> ImageCorrection:
        idx = _parameter_blocks(self.layout)[1][image_id]
        v = self.x[idx]
        return ImageCorrection(self.layout.images[image_id], self.layout.time_scale, v[:5].copy(), v[5:].copy())


def corrected_model(estimate: BlockEstimate, image_id: str, rpc) -> BlockCorrectedRPC:
    """The corrected sensor model of one image of the block."""
    return BlockCorrectedRPC(rpc, estimate.correction(image_id))


# ----------------------------------------------------------------------------------------------------- coverage
def supported_degree(x, max_degree: int = 3) -> int:
    """The highest polynomial degree (<= ``max_degree``) in ``x`` (normalised to [-1, 1] over the detector or strip)
    that observations at ``x`` support: its largest prediction variance (leverage) over [-1, 1] at most
    :data:`MAX_EXTRAPOLATION_VARIANCE` x its largest at the observations. Computed in coordinates centred on the
    observations (the leverage does not depend on the polynomial basis)."""
    x = np.unique(np.asarray(x, float)[np.isfinite(x)])
    if x.size < 2:
        return 0
    c, r = 0.5 * (x.max() + x.min()), 0.5 * (x.max() - x.min())
    if not r > 0:
        return 0
    grid = (np.linspace(-1.0, 1.0, 201) - c) / r
    for d in range(min(max_degree, x.size - 1), 0, -1):
        q, rr = np.linalg.qr(detector_polynomial((x - c) / r, d))
        if not np.all(np.abs(np.diag(rr)) > 1e-9 * np.abs(rr).max()):
            continue
        g = np.linalg.solve(rr.T, detector_polynomial(grid, d).T)      # R^-T p: its squared norm is the leverage
        if np.max(np.sum(g * g, axis=0)) <= MAX_EXTRAPOLATION_VARIANCE * np.max(np.sum(q * q, axis=1)):
            return d
    return 0


def _coverage(tab, layout: "BlockLayout", index: Mapping[str, np.ndarray], p: int, interiors: bool = True):
    """Parameters the observations cannot support (held at 0 before solving) and the warnings saying so: per image
    the interior terms above :func:`supported_degree` of its observations' detector positions ``u``; the exterior
    drifts ``e3, e4`` when the observations' times ``t`` do not support a slope (METHODS §8). ``interiors=False``:
    the interiors are not estimated (a calibration's), only the drifts are judged."""
    used = (tab["kind"] == "tie").to_numpy() | (tab["role"] == "control").to_numpy()
    img = tab["image_id"].to_numpy(object)
    s_all, l_all = tab["sample"].to_numpy(float), tab["line"].to_numpy(float)
    off = np.zeros(p, bool)
    warns: List[str] = []
    times = []
    for im, lay in layout.images.items():
        m = used & (img == im)
        W, H = lay.size
        times.append(lay.ratio * (l_all[m] - H / 2.0) / layout.time_scale)
        d = supported_degree((s_all[m] - W / 2.0) / (W / 2.0)) if interiors else 3
        if d < 3:
            held = [n for n in INTERIOR_NAMES if int(n[1]) > d]
            off[index[im][5:][[INTERIOR_NAMES.index(n) for n in held]]] = True
            lo, hi = (np.nanmin(s_all[m]), np.nanmax(s_all[m])) if m.any() else (0.0, 0.0)
            warns.append(f"{im}: the observations cover detector columns {lo:.0f}..{hi:.0f} of {W} "
                         f"({(hi - lo) / W:.0%}): its interior is estimated to degree {d} only ({', '.join(held)} "
                         "held at 0, not extrapolated over the detector); add ties or GCPs across the whole width "
                         "for a full calibration")
    t = np.concatenate(times) if times else np.zeros(0)
    if supported_degree(t, 1) < 1:
        off[[EXTERIOR_NAMES.index("e3"), EXTERIOR_NAMES.index("e4")]] = True
        warns.append(f"the observations cover {np.ptp(t) / 2 if t.size else 0:.0%} of the strip's time (lines): "
                     "the exterior drifts e3, e4 are held at 0 (not extrapolated); add GCPs or ties along the whole "
                     "image height to estimate them")
    return off, warns


# ----------------------------------------------------------------------------------------------------- solver
class _Stage:
    """Arrays of one adjustment stage: observation rows, tie-point slots, weights."""

    def __init__(self, tab, rows, models, layout, index, dem, used_gcp):
        self.rows = rows                                           # row positions in ``tab``
        sub = tab.iloc[rows]
        self.image = sub["image_id"].to_numpy(object)
        self.meas = np.stack([sub["sample"].to_numpy(float), sub["line"].to_numpy(float)], axis=1)
        self.sigma = sub["sigma"].to_numpy(float)
        self.is_tie = (sub["kind"] == "tie").to_numpy()
        self.ground = np.stack([sub[c].to_numpy(float) for c in ("lon", "lat", "h")], axis=1)
        self.base_w = np.where(self.is_tie | used_gcp[rows], 1.0 / self.sigma ** 2, 0.0)
        self.cols = np.stack([index[i] for i in self.image]) if len(rows) else np.zeros((0, 13), int)
        self.design = np.zeros((len(rows), 2, 13))
        for im in dict.fromkeys(self.image):
            m = self.image == im
            self.design[m] = _local_design(layout.images[im], layout.time_scale, self.meas[m, 0], self.meas[m, 1])
        tie_rows = np.flatnonzero(self.is_tie)
        pids = sub["point_id"].to_numpy(object)[tie_rows]
        self.point_ids, self.point_of = np.unique(pids, return_inverse=True) if tie_rows.size else (
            np.zeros(0, object), np.zeros(0, int))
        counts = np.bincount(self.point_of, minlength=self.point_ids.size)
        self.max_rays = int(counts.max()) if counts.size else 1
        order = np.argsort(self.point_of, kind="stable")
        slot = np.empty(tie_rows.size, int)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int) if counts.size else np.zeros(0, int)
        slot[order] = np.arange(tie_rows.size) - np.repeat(starts, counts)
        self.tie_rows, self.slot = tie_rows, slot
        self.models, self.dem = models, dem

    def initial_points(self, x):
        """Tie-point ground (lon, lat): mean of every ray's DEM localisation with the current corrections."""
        n = self.point_ids.size
        lon = np.zeros(n)
        lat = np.zeros(n)
        cnt = np.zeros(n)
        v = np.einsum("nkc,nc->nk", self.design, x[self.cols])
        for im in dict.fromkeys(self.image[self.tie_rows]):
            m = self.tie_rows[self.image[self.tie_rows] == im]
            lo, la, _ = self.models[im].localize_dem(self.meas[m, 0] - v[m, 0], self.meas[m, 1] - v[m, 1], self.dem)
            ok = np.isfinite(lo) & np.isfinite(la)
            p = self.point_of[np.searchsorted(self.tie_rows, m)]
            np.add.at(lon, p[ok], np.asarray(lo)[ok])
            np.add.at(lat, p[ok], np.asarray(la)[ok])
            np.add.at(cnt, p[ok], 1.0)
        if (cnt == 0).any():
            bad = self.point_ids[cnt == 0][0]
            raise BlockError(f"tie point {bad!r} cannot be localised on the DEM in any of its images; check the DEM "
                             "covers the images and the tie point's image coordinates")
        return lon / cnt, lat / cnt

    def evaluate(self, x, plon, plat, with_jacobian=True):
        """Predicted positions (n, 2), RPC Jacobians by (lon, lat) along the DEM (n, 2, 2, per metre) and heights."""
        g = self.ground.copy()
        jp = None
        if self.tie_rows.size:
            lon = plon[self.point_of]
            lat = plat[self.point_of]
            h, dhx, dhy = self.dem.sample_with_gradient(lon, lat)
            h = np.asarray(h, float)
            if not np.all(np.isfinite(h)):
                raise BlockError(f"{int((~np.isfinite(h)).sum())} tie point(s) fall outside the DEM; give a DEM "
                                 "that covers the images")
            g[self.tie_rows] = np.stack([lon, lat, h], axis=1)
        pred = np.zeros((len(self.rows), 2))
        if with_jacobian and self.tie_rows.size:
            jp = np.zeros((self.tie_rows.size, 2, 2))
        for im in dict.fromkeys(self.image):
            m = self.image == im
            s, l = self.models[im].project(g[m, 0], g[m, 1], g[m, 2])
            pred[m, 0], pred[m, 1] = s, l
            if jp is not None:
                mt = m[self.tie_rows]
                if mt.any():
                    rows = self.tie_rows[mt]
                    j = np.asarray(self.models[im].project_jacobian(g[rows, 0], g[rows, 1], g[rows, 2]))
                    j = j.reshape(-1, 2, 3)
                    jj = j[:, :, :2] + j[:, :, 2:3] * np.stack([dhx[mt], dhy[mt]], axis=1)[:, None, :]
                    from .geodesy import metres_per_degree
                    mx, my = metres_per_degree(g[rows, 1], g[rows, 2])
                    jp[mt] = jj / np.stack([mx, my], axis=1)[:, None, :]
        corr = np.einsum("nkc,nc->nk", self.design, x[self.cols])
        return pred + corr, pred, jp, g

    def solve(self, x, free, v, w, jp, covariance=False):
        """One Gauss-Newton step: (dx_global over all parameters, point steps in metres (N, 2), solution)."""
        import scipy.sparse as sp
        from .estimation import solve_with_points
        fidx = np.full(x.size, -1)
        fidx[free] = np.arange(int(free.sum()))
        pf = int(free.sum())
        N, m = self.point_ids.size, self.max_rays
        k = 2 * m
        if jp is None:
            jp = np.zeros((0, 2, 2))
        # tie rows -> padded point layout
        jpp = np.zeros((N, k, 2))
        rr = np.zeros((N, k))
        ww = np.zeros((N, k))
        t = self.tie_rows
        base = self.point_of * k + 2 * self.slot
        for ax in range(2):
            jpp.reshape(N * k, 2)[base + ax] = jp[:, ax, :]
            rr.reshape(N * k)[base + ax] = v[t, ax]
            ww.reshape(N * k)[base + ax] = w[t, ax]

        def sparse_rows(rows_idx, out_rows, n_rows):
            c = fidx[self.cols[rows_idx]]                              # (n, 13)
            data, ri, ci = [], [], []
            for ax in range(2):
                d = self.design[rows_idx, ax, :]
                keep = (c >= 0) & (d != 0)
                data.append(d[keep])
                ri.append(np.broadcast_to((out_rows + ax)[:, None], c.shape)[keep])
                ci.append(c[keep])
            return sp.csr_matrix((np.concatenate(data), (np.concatenate(ri), np.concatenate(ci))), shape=(n_rows, pf))

        jg = sparse_rows(t, base, N * k)
        g_rows = np.flatnonzero(~self.is_tie & (w.sum(axis=1) > 0))
        extra = None
        if g_rows.size:
            je = sparse_rows(g_rows, 2 * np.arange(g_rows.size), 2 * g_rows.size)
            extra = (je, v[g_rows].ravel(), w[g_rows].ravel())
        sol = solve_with_points(jpp, rr, ww, jg, extra=extra, covariance=covariance)
        dx = np.zeros(x.size)
        dx[free] = sol.dx_global
        dp = np.where(np.isfinite(sol.dx_points), sol.dx_points, 0.0)
        return dx, dp, sol


def _redundancy(stage: _Stage, w) -> np.ndarray:
    """Approximate redundancy per row: ``1 - 1/m`` for a ray of a tie point with ``m`` used rays, 1 for GCPs."""
    red = np.ones(len(stage.rows))
    if stage.tie_rows.size:
        used = (w[stage.tie_rows].sum(axis=1) > 0).astype(float)
        m = np.bincount(stage.point_of, weights=used, minlength=stage.point_ids.size)
        red[stage.tie_rows] = np.clip(1.0 - 1.0 / np.maximum(m[stage.point_of], 1.0), 0.05, 1.0)
    return red


def _robust(stage: _Stage, v, w_used, n_params, reject: bool, reject_k: float):
    from .estimation import radial_huber_weights
    red = _redundancy(stage, w_used)
    sig = stage.sigma * np.sqrt(red)
    fw, out, scale, z = radial_huber_weights(v, sig, n_params, reject_k=reject_k)
    if not reject:
        out = np.zeros_like(out)
    factor = np.where(out, 0.0, fw)
    return factor, out, z


def _run_stage(stage: _Stage, x, free_sets, *, robust: bool, tol: float, max_iter: int, reject_k: float,
               progress=None):
    """Gauss-Newton (+ robust reweighting) cycling through ``free_sets`` (one set: simultaneous; exterior then
    interior: alternating). Returns (x, plon, plat, info)."""
    plon, plat = stage.initial_points(x)
    npar = int(np.any(free_sets, axis=0).sum())
    factor = np.ones(len(stage.rows))
    rejected = np.zeros(len(stage.rows), bool)
    phase = 0 if robust else 2            # 0: a-priori weights, 1: down-weighting, 2: rejection
    history: List[float] = []
    small_in_row = in_phase = 0
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        free = free_sets[(it - 1) % len(free_sets)]
        pred, _, jp, _ = stage.evaluate(x, plon, plat)
        v = stage.meas - pred
        w = stage.base_w[:, None] * factor[:, None] * np.ones((1, 2))
        dx, dp, _ = stage.solve(x, free, v, w, jp)
        x = x + dx
        from .geodesy import metres_per_degree
        mx, my = metres_per_degree(plat, 0.0)
        plon = plon + dp[:, 0] / mx
        plat = plat + dp[:, 1] / my
        # change: the largest move of a corrected position through the global parameters, and the 99th percentile
        # of the tie points' moves (a blunder's point may cycle over a DEM kink until it is rejected)
        move = np.abs(np.einsum("nkc,nc->nk", stage.design, dx[stage.cols]))
        change = float(np.max(move[stage.base_w > 0])) if (stage.base_w > 0).any() else 0.0
        if stage.tie_rows.size:
            pm = np.abs(np.einsum("nkq,nq->nk", jp, dp[stage.point_of])).max(axis=1)
            change = max(change, float(np.percentile(pm, 99)))
        history.append(change)
        if progress is not None:
            progress(min(it / max_iter, 0.99), f"iteration {it}: largest change {change:.3g} px")
        small_in_row = small_in_row + 1 if change < tol else 0
        in_phase += 1
        if small_in_row >= len(free_sets) or (phase < 2 and in_phase >= 4 * len(free_sets) and change < 100 * tol):
            if phase == 2:
                pred, _, _, _ = stage.evaluate(x, plon, plat, with_jacobian=False)
                v = stage.meas - pred
                f2, out, _ = _robust(stage, v, w, npar, True, reject_k) if robust else (factor, rejected, None)
                if np.array_equal(out, rejected):
                    converged = True
                    break
                factor, rejected = f2, out
                small_in_row = 0
                continue
            phase += 1
            small_in_row = in_phase = 0
        if phase >= 1 and robust:
            pred, _, _, _ = stage.evaluate(x, plon, plat, with_jacobian=False)
            v = stage.meas - pred
            factor, rejected, _ = _robust(stage, v, w, npar, phase == 2, reject_k)
    return x, plon, plat, {"iterations": it, "converged": converged, "history": history, "factor": factor,
                           "rejected": rejected}


def _rows_of(tab, images, kinds=("gcp", "tie")):
    return tab["image_id"].isin(list(images)).to_numpy() & tab["kind"].isin(list(kinds)).to_numpy()


def _stage_rows(tab, images: Sequence[str], band_stage: bool, all_images: Sequence[str]):
    """Rows of a stage: GCPs of its images; ties with >= 2 rays in the images considered (reference stage: its own
    images; band stage: every image, for ties with at least one ray in a band image)."""
    in_stage = tab["image_id"].isin(list(images)).to_numpy()
    tie = (tab["kind"] == "tie").to_numpy()
    gcp_rows = np.flatnonzero(in_stage & ~tie)
    if band_stage:
        cand = tie & tab["image_id"].isin(list(all_images)).to_numpy()
        touched = set(tab.loc[tie & in_stage, "point_id"])
        cand &= tab["point_id"].isin(touched).to_numpy()
    else:
        cand = tie & in_stage
    n = tab[cand].groupby("point_id")["image_id"].transform("size")
    tie_rows = np.flatnonzero(cand)[(n.to_numpy() >= 2)]
    return np.sort(np.concatenate([gcp_rows, tie_rows]))


def _check_control(tab, layout: BlockLayout, min_gcps: int = 4):
    ctrl = tab[(tab["kind"] == "gcp") & (tab["role"] == "control")]
    counts = ctrl.groupby("image_id")["point_id"].nunique()
    for im in layout.order:
        n = int(counts.get(im, 0))
        if n < min_gcps:
            raise BlockError(f"{im}: {n} control GCP(s); the block needs >= {min_gcps} per reference-band CCD image "
                             "to fix its interior cubic and the datum; add GCPs (--gcps)")


def adjust_block(observations, models: Mapping[str, Any], dem, *, layout: Optional[BlockLayout] = None,
                 order: Optional[Sequence[str]] = None, bands_of: Optional[Mapping[str, str]] = None,
                 reference_ccd: Optional[str] = None, solver: str = "simultaneous", robust: bool = True,
                 compare: bool = False, tol: float = 1e-3, max_iter: int = 60, reject_k: float = 5.0,
                 calibration: Optional[Mapping[str, Any]] = None, progress=None) -> BlockEstimate:
    """Block calibration of one group in RPC space (METHODS §8; module docstring).

    Parameters
    ----------
    observations : the long observation table (:mod:`gdal_gf4cal.observations`): GCP rows (``lon, lat, h``) and tie
        rows (``kind='tie'``, shared ``point_id``); ``image_id`` = the keys of ``models``. ``sigma`` in px.
    models : ``{image id: RPCModel}`` (any sensor model with ``project``/``project_jacobian``/``localize``).
    dem : :class:`~gdal_gf4cal.dem.DEM` (ellipsoidal): tie-point heights.
    layout : a :class:`BlockLayout`; default :func:`derive_layout` (``order``, ``bands_of``, ``reference_ccd``).
    order : the reference-band CCD images across track (default: the images without ``bands_of`` entry, in the
        order of ``models``).
    solver : ``"simultaneous"`` (one sparse Gauss-Newton on everything) or ``"alternating"`` (exterior, then
        interior, repeated; METHODS §8's paper scheme).
    robust : robust reweighting and blunder rejection (module docstring).
    compare : also run the other solver and keep its stages (iterations, parameters) in ``comparison``.
    tol : convergence: largest change of any predicted position in one iteration, px.
    calibration : a group calibration (:func:`calibration_dict`; ``models`` keyed by its image names): only the
        scene's exterior is estimated, every interior held at the calibrated values (another scene of the same
        camera and group with a few GCPs, METHODS §8's validation); ``layout`` comes from the calibration.

    Returns
    -------
    BlockEstimate
        ``x`` over the blocks ``exterior``, ``datum:<reference CCD>`` (frozen, 0), ``interior:<image>``; ``cov``
        (a-posteriori) and the per-row diagnostics (``residuals`` / ``weights`` / ``normalised`` are ``(n_rows * 2)``,
        sample then line of each row of ``table``); ``outlier`` per row.

    Raises
    ------
    BlockError
        Unknown images in the observations, too few GCPs for the datum, a layout problem (:func:`derive_layout`).
    DegenerateGeometryError
        The observations do not determine the parameters.
    """
    from .observations import validate_observations
    if solver not in ("simultaneous", "alternating"):
        raise BlockError(f"solver {solver!r} unknown; choose simultaneous or alternating")
    tab = validate_observations(observations, need_height=False, dem=dem)
    unknown = sorted(set(tab["image_id"]) - set(models))
    if unknown:
        raise BlockError(f"the observations name image {unknown[0]!r}, which is not among the images "
                         f"({', '.join(list(models)[:6])}{', ...' if len(models) > 6 else ''}); give that image or "
                         "fix the observation file's image column")
    if calibration is not None:
        layout = layout_from_calibration(calibration, models)
    if layout is None:
        bands_of = dict(bands_of or {})
        if order is None:
            order = [m for m in models if m not in bands_of]
        layout = derive_layout(models, order, bands_of=bands_of, reference_ccd=reference_ccd)
    gcp = (tab["kind"] == "gcp").to_numpy()
    if gcp.any() and not np.all(np.isfinite(tab.loc[gcp, "h"].to_numpy(float))):
        raise BlockError("some GCPs have no height; give h or a DEM to take it from")
    if calibration is not None:
        n = int(tab.loc[(tab["kind"] == "gcp") & (tab["role"] == "control"), "point_id"].nunique())
        if n < 3:
            raise BlockError(f"{n} control GCP(s); the scene's exterior (5 terms) needs >= 3; add GCPs (--gcps)")
        return _adjust(tab, models, dem, layout, solver, robust, tol, max_iter, reject_k, progress,
                       start=calibration)
    _check_control(tab, layout)
    result = _adjust(tab, models, dem, layout, solver, robust, tol, max_iter, reject_k, progress)
    if compare:
        other = "alternating" if solver == "simultaneous" else "simultaneous"
        alt = _adjust(tab, models, dem, layout, other, robust, tol, max_iter * 4 if other == "alternating" else
                      max_iter, reject_k, None)
        result.comparison = {"solver": other, "stages": alt.stages, "parameters": alt.parameters,
                             "table": alt.table}
    return result


def layout_from_calibration(cal: Mapping[str, Any], models: Optional[Mapping[str, Any]] = None) -> BlockLayout:
    """The layout stored in a calibration (:func:`calibration_dict`); ``models`` must all be in it."""
    ims = {k: ImageLayout(k, v["reference"], int(v["ccd"]), tuple(int(x) for x in v["size"]), float(v["ratio"]),
                          float(v["x0_px"]), float(v.get("y_px", 0.0))) for k, v in cal["images"].items()}
    missing = [m for m in (models or {}) if m not in ims]
    if missing:
        raise BlockError(f"image {missing[0]!r} is not in the calibration (images: {', '.join(list(ims)[:8])}); name "
                         "the scene's images as in the calibrated group")
    keep = [k for k in ims if models is None or k in models]
    order = [o for o in cal["order"] if o in keep]
    if cal["reference_ccd"] not in keep:
        raise BlockError(f"the calibration's reference CCD {cal['reference_ccd']!r} is not among the images; give it")
    return BlockLayout({k: ims[k] for k in order + [k for k in keep if k not in order]}, order,
                       str(cal["reference_ccd"]), float(cal["time_scale"]))


def _propagate_frozen(stage: _Stage, xs, free, frozen, w, jp, cov) -> None:
    """Add to ``cov`` (in place) what the errors of the ``frozen`` parameters (an earlier stage's, with their
    covariance already in ``cov``) do to this stage's ``free`` ones: the band stage fits each band's interior to the
    reference band's corrected positions, so a reference exterior or interior error is absorbed by the band interior
    (METHODS §6 propagation). Linear response ``S = d x_free / d x_frozen`` (one reduced solve per frozen parameter
    that this stage's rows see, tie points re-eliminated); ``cov_ff += S C S^T``, ``cov_fF = S C``."""
    fr = np.flatnonzero(frozen)
    if not fr.size:
        return
    seen = np.zeros(cov.shape[0], bool)
    seen[np.unique(stage.cols[np.any(stage.design != 0, axis=1)].ravel())] = True
    fr = fr[seen[fr]]
    if not fr.size:
        return
    fi = np.flatnonzero(free)
    sens = np.zeros((fi.size, fr.size))
    for j, c in enumerate(fr):
        dv = -stage.design[:, :, :] * (stage.cols == c)[:, None, :]
        dx, _, _ = stage.solve(xs, free, dv.sum(axis=2), w, jp)
        sens[:, j] = dx[fi]
    c_ff = cov[np.ix_(fr, fr)]
    cross = sens @ c_ff
    cov[np.ix_(fi, fi)] += cross @ sens.T
    cov[np.ix_(fi, fr)] = cross
    cov[np.ix_(fr, fi)] = cross.T


def _adjust(tab, models, dem, layout: BlockLayout, solver, robust, tol, max_iter, reject_k, progress,
            start: Optional[Mapping[str, Any]] = None) -> BlockEstimate:
    from . import progress as _progress
    blocks, index = _parameter_blocks(layout)
    names = [n for b in blocks for n in b.names]
    sl: Dict[str, slice] = {}
    pos = 0
    for b in blocks:
        sl[b.name] = slice(pos, pos + b.size)
        pos += b.size
    p = len(names)
    x = np.zeros(p)
    datum = np.zeros(p, bool)
    datum[sl[f"datum:{layout.reference_ccd}"]] = True
    unsupported, coverage_warnings = _coverage(tab, layout, index, p, interiors=start is None)
    ext = np.zeros(p, bool)
    ext[sl["exterior"]] = True
    ref_imgs = list(layout.order)
    band_imgs = layout.band_images
    is_ref_int = np.zeros(p, bool)
    for im in ref_imgs:
        is_ref_int[sl[f"interior:{im}"]] = True
    is_band_int = np.zeros(p, bool)
    for im in band_imgs:
        is_band_int[sl[f"interior:{im}"]] = True
    control = (tab["kind"] == "gcp").to_numpy() & (tab["role"] == "control").to_numpy()
    used_gcp_ref = control
    stages_out: List[Dict[str, Any]] = []
    n = len(tab)
    pred_after = np.full((n, 2), np.nan)
    pred_before = np.full((n, 2), np.nan)
    weights = np.zeros((n, 2))
    outl = np.zeros(n, bool)
    ground = tab[["lon", "lat", "h"]].to_numpy(float).copy()
    red_all = np.ones(n)
    specs = [("reference", ref_imgs, False, ext | is_ref_int)]
    if band_imgs:
        specs.append(("bands", band_imgs, True, is_band_int))
    if start is not None:                                   # another scene: its exterior only, interiors calibrated
        for im in layout.images:
            idx = index[im]
            x[idx[5:]] = [float(start["images"][im]["interior"][n]) for n in INTERIOR_NAMES]
        x[sl["exterior"]] = [float(start["exterior"][n]) for n in EXTERIOR_NAMES]
        specs = [("exterior", ref_imgs + band_imgs, False, ext)]
        used_gcp_ref = control
    final_stage = []
    for si, (label, imgs, band_stage, free_all) in enumerate(specs):
        rows = _stage_rows(tab, imgs, band_stage, ref_imgs + band_imgs)
        stage = _Stage(tab, rows, models, layout, index, dem, used_gcp_ref)
        free_all = free_all & ~datum & ~unsupported
        if solver == "alternating" and not band_stage:
            free_sets = [free_all & ext, free_all & ~ext]
        else:
            free_sets = [free_all]
        prog = _progress.scaled(progress, si / len(specs), (si + 0.9) / len(specs)) if progress else None
        # before: the original RPCs, tie points from their rays' mean
        x0 = x.copy()
        plon0, plat0 = stage.initial_points(x0)
        pb, _, _, _ = stage.evaluate(x0, plon0, plat0, with_jacobian=False)
        x, plon, plat, info = _run_stage(stage, x, np.array(free_sets), robust=robust, tol=tol, max_iter=max_iter,
                                         reject_k=reject_k, progress=prog)
        pa, _, _, g = stage.evaluate(x, plon, plat, with_jacobian=False)
        # a stage's rows: the earlier stage's values stay for rows it does not re-estimate (reference GCPs)
        mine = tab["image_id"].iloc[rows].isin(imgs).to_numpy() | np.isnan(pred_after[rows, 0])
        r = rows[mine]
        pred_before[r] = pb[mine]
        pred_after[r] = pa[mine]
        fw = stage.base_w * info["factor"]
        weights[r] = fw[mine, None]
        outl[r] = info["rejected"][mine]
        ground[rows[stage.is_tie]] = g[stage.is_tie]
        red_all[r] = _redundancy(stage, np.repeat(fw[:, None], 2, axis=1))[mine]
        dof_obs = int(2 * np.count_nonzero(fw > 0))
        n_pts = int(stage.point_ids.size)
        stages_out.append({"stage": label, "images": list(imgs), "solver": solver if not band_stage else
                           "simultaneous", "iterations": int(info["iterations"]), "converged": bool(info["converged"]),
                           "history_px": [float(h) for h in info["history"]], "n_free_parameters": int(free_all.sum()),
                           "reduced_system_size": int(free_all.sum()), "n_tie_points": n_pts,
                           "n_observations": dof_obs, "n_rejected": int(np.count_nonzero(info["rejected"]))})
        final_stage.append((stage, x.copy(), plon, plat, fw, free_all, dof_obs, n_pts))
    # a-posteriori covariance from the last solve of each stage
    cov = np.zeros((p, p))
    v_all = tab[["sample", "line"]].to_numpy(float) - pred_after
    wsum = float(np.nansum(weights * v_all ** 2))
    dof = sum(d - 2 * npt - int(f.sum()) for _, _, _, _, _, f, d, npt in final_stage)
    sigma0 = math.sqrt(wsum / dof) if dof > 0 else 1.0
    earlier = np.zeros(p, bool)                             # parameters of the stages before (frozen now)
    pending: List[Any] = []
    for stage, xs, plon, plat, fw, free_all, _, _ in final_stage:
        pred, _, jp, _ = stage.evaluate(xs, plon, plat)
        w = np.repeat(fw[:, None], 2, axis=1)
        try:
            _, _, sol = stage.solve(xs, free_all, stage.meas - pred, w, jp, covariance=True)
            fi = np.flatnonzero(free_all)
            cov[np.ix_(fi, fi)] = sigma0 ** 2 * sol.cov_global
            if earlier.any():                          # on demand (one reduced solve per frozen parameter)
                pending.append((stage, xs, free_all, earlier.copy(), w, jp))
        except DegenerateGeometryError:
            pass
        earlier |= free_all
    table = tab.copy()
    table[["lon", "lat", "h"]] = ground
    for tag, pr in (("before", pred_before), ("after", pred_after)):
        table[f"pred_sample_{tag}"] = pr[:, 0]
        table[f"pred_line_{tag}"] = pr[:, 1]
        table[f"res_sample_{tag}"] = table["sample"].to_numpy(float) - pr[:, 0]
        table[f"res_line_{tag}"] = table["line"].to_numpy(float) - pr[:, 1]
    from .observations import flag_outliers
    table = flag_outliers(table, outl, "robust")
    sig = table["sigma"].to_numpy(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        normalised = (v_all / (sigma0 * sig[:, None] * np.sqrt(red_all)[:, None])).ravel()
    frozen = (f"datum:{layout.reference_ccd}",)
    est = BlockEstimate(names=names, x=x, cov=cov, sigma0=sigma0, dof=int(dof), redundancy=np.repeat(red_all, 2),
                        residuals=v_all.ravel(), normalised=normalised, weights=weights.ravel(), blocks=sl,
                        frozen=frozen, outlier=outl, outlier_level=np.where(outl, "robust", ""),
                        iterations=int(sum(s["iterations"] for s in stages_out)), table=table, layout=layout,
                        stages=stages_out, cov_pending=pending)
    est.notes.append(f"datum: {', '.join(DATUM_TERMS)} of {layout.reference_ccd} fixed at 0 (they duplicate e0, e1, "
                     "kappa)")
    est.warnings.extend(coverage_warnings)
    for s in stages_out:
        if not s["converged"]:
            est.warnings.append(f"{s['stage']} stage ({s['solver']}) did not converge in {s['iterations']} "
                                "iterations; its results are the last iterate")
    return est


# ----------------------------------------------------------------------------------------------------- seams
def seam_offsets(table, models_before: Mapping[str, Any], models_after: Mapping[str, Any], dem,
                 pairs: Sequence[Tuple[str, str]]) -> List[Dict[str, Any]]:
    """Seam offset of each overlap (METHODS §8 seam report) from its tie points, before and after.

    For a tie point seen by ``a`` and ``b``: ``a``'s measurement is localised on the DEM with ``a``'s model and
    projected with ``b``'s; the offset is ``b``'s measurement minus that prediction (px of ``b``, sample and line;
    matching noise included: ``sqrt(2)`` x the tie sigma per axis). Rows flagged ``outlier`` are left out.
    Returns one dict per pair with ``n``, per epoch ``mean``/``rms``/``max`` per axis and planar (``max_px``: the
    largest single tie offset, noise included), ``seam_max_px`` (the seam itself, noise averaged: the offsets fitted
    by a straight line along the overlap's lines, its largest magnitude over them), and the per-point arrays under
    ``points`` (``point_id, lon, lat, line_b, ds/dl before/after``).
    """
    out = []
    ok = ~table["outlier"].to_numpy(bool) if "outlier" in table.columns else np.ones(len(table), bool)
    ties = table[(table["kind"] == "tie").to_numpy() & ok]
    for a, b in pairs:
        ta = ties[ties["image_id"] == a].set_index("point_id")
        tb = ties[ties["image_id"] == b].set_index("point_id")
        common = ta.index.intersection(tb.index)
        entry: Dict[str, Any] = {"pair": [a, b], "n": int(len(common))}
        if len(common) == 0:
            out.append(entry)
            continue
        sa, la = ta.loc[common, "sample"].to_numpy(float), ta.loc[common, "line"].to_numpy(float)
        sb, lb = tb.loc[common, "sample"].to_numpy(float), tb.loc[common, "line"].to_numpy(float)
        pts = {"point_id": np.asarray(common, dtype=object), "sample_b": sb, "line_b": lb}
        for tag, models in (("before", models_before), ("after", models_after)):
            lon, lat, h = models[a].localize_dem(sa, la, dem)
            ps, pl = models[b].project(lon, lat, h)
            ds, dl = sb - np.asarray(ps), lb - np.asarray(pl)
            pts[f"ds_{tag}"], pts[f"dl_{tag}"] = ds, dl
            if tag == "before":
                pts["lon"], pts["lat"], pts["h"] = np.asarray(lon), np.asarray(lat), np.asarray(h)
            rad = np.hypot(ds, dl)
            entry[tag] = {"mean_sample_px": float(np.nanmean(ds)), "mean_line_px": float(np.nanmean(dl)),
                          "mean_px": float(math.hypot(np.nanmean(ds), np.nanmean(dl))),
                          "rms_sample_px": float(np.sqrt(np.nanmean(ds ** 2))),
                          "rms_line_px": float(np.sqrt(np.nanmean(dl ** 2))),
                          "rms_px": float(np.sqrt(np.nanmean(rad ** 2))), "max_px": float(np.nanmax(rad)),
                          "seam_max_px": _systematic_seam(lb, ds, dl)}
        entry["points"] = pts
        out.append(entry)
    return out


def _systematic_seam(line, ds, dl) -> float:
    """Largest magnitude over ``line``'s range of the straight line (in ``line``) fitted to the offsets ``ds, dl``:
    a seam that drifts along track, without the matching noise of single ties."""
    ok = np.isfinite(line) & np.isfinite(ds) & np.isfinite(dl)
    if ok.sum() < 3:
        return float(np.nanmax(np.hypot(ds, dl))) if ok.any() else float("nan")
    lo, hi = float(line[ok].min()), float(line[ok].max())
    u = (line[ok] - 0.5 * (lo + hi)) / max(0.5 * (hi - lo), 1.0)
    a = np.column_stack([np.ones(u.size), u])
    fs = weighted_lsq(a, ds[ok]).x
    fl = weighted_lsq(a, dl[ok]).x
    ends = np.array([[1.0, -1.0], [1.0, 1.0]])
    return float(np.max(np.hypot(ends @ fs, ends @ fl)))


# ----------------------------------------------------------------------------------------------------- calibration
def calibration_dict(estimate: BlockEstimate, keys: Optional[Mapping[str, str]] = None) -> Dict[str, Any]:
    """The group's calibration (exterior + interior per CCD and band, with the layout) as a JSON-ready dict.

    ``keys`` maps image ids to the names other scenes' images are matched by (default: the ids)."""
    keys = dict(keys or {})
    lay = estimate.layout
    ext = estimate.block("exterior")
    images = {}
    for im in lay.images:
        c = estimate.correction(im).to_dict()
        c["reference"] = keys.get(c["reference"], c["reference"])
        images[keys.get(im, im)] = c
    return {"model": CALIBRATION_MODEL, "method": "METHODS §8 block calibration in RPC space",
            "pixel_convention": "gdal",
            "definition": "s = s_RPC + (e0 + e3 t - kappa Y)/r + sum a_j u^j; l = l_RPC + (e1 + e4 t + kappa X(u))/r + "
                          "sum b_j u^j; u = (s - W/2)/(W/2); t = r (l - H/2)/time_scale; X(u) = x0_px + r (W/2) u; "
                          "kappa = kappa_mrad * 1e-3",
            "exterior": {n: float(v) for n, v in zip(EXTERIOR_NAMES, ext)},
            "reference_ccd": keys.get(lay.reference_ccd, lay.reference_ccd),
            "order": [keys.get(o, o) for o in lay.order], "time_scale": lay.time_scale, "images": images}


def write_calibration(cal: Mapping[str, Any], path) -> str:
    """Write a calibration dict as JSON (atomic)."""
    from .atomic import atomic_output
    from .report import write_report_json
    path = os.fspath(path)
    with atomic_output(path) as tmp:
        write_report_json(dict(cal), tmp)
    return path


def read_calibration(path) -> Dict[str, Any]:
    """Read a block ``calibration.json``; :class:`BlockError` if it is not one."""
    try:
        with open(os.fspath(path), encoding="utf-8") as f:
            cal = json.load(f)
    except (OSError, ValueError) as exc:
        raise BlockError(f"cannot read the calibration {path}: {str(exc).splitlines()[0]}") from None
    if not isinstance(cal, dict) or cal.get("model") != CALIBRATION_MODEL:
        raise BlockError(f"{path} is not a block calibration (model {CALIBRATION_MODEL!r}); give the "
                         "calibration.json written by block-adjust")
    return cal


def calibrated_model(cal: Mapping[str, Any], key: str, rpc, size: Optional[Tuple[int, int]] = None
                     ) -> BlockCorrectedRPC:
    """The model of another scene's image ``key`` (same camera and group) with the calibration applied."""
    images = cal["images"]
    if key not in images:
        raise BlockError(f"image {key!r} is not in the calibration (images: {', '.join(list(images)[:8])}); name the "
                         "scenes' images as in the calibrated group")
    c = images[key]
    sz = tuple(int(v) for v in c["size"])
    if size is not None and tuple(size) != sz:
        raise BlockError(f"{key}: image size {tuple(size)} differs from the calibrated one {sz}; the calibration "
                         "applies to images of the same CCD and band")
    lay = ImageLayout(key, c["reference"], int(c["ccd"]), sz, float(c["ratio"]), float(c["x0_px"]),
                      float(c.get("y_px", 0.0)))
    ext = np.array([float(cal["exterior"][n]) for n in EXTERIOR_NAMES])
    inter = np.array([float(c["interior"][n]) for n in INTERIOR_NAMES])
    return BlockCorrectedRPC(rpc, ImageCorrection(lay, float(cal["time_scale"]), ext, inter))





def prediction_std(estimate: BlockEstimate, image_id: str, sample, line) -> Tuple[np.ndarray, np.ndarray]:
    """Propagated 1-sigma of the correction of ``image_id`` at ``(sample, line)`` (px, per axis) from the estimate's
    covariance: the precision floor the GCP and matching noise allow (METHODS §6). A band image's interior carries
    the reference band's errors it absorbed (its covariance with the frozen exterior and reference interiors,
    :func:`_propagate_frozen`), so its floor is the reference image's plus the band-to-band matching noise."""
    estimate.complete_covariance()
    idx = _parameter_blocks(estimate.layout)[1][image_id]
    d = _local_design(estimate.layout.images[image_id], estimate.layout.time_scale, sample, line)
    c = estimate.cov[np.ix_(idx, idx)]
    var = np.einsum("nkc,cd,nkd->nk", d, c, d)
    return np.sqrt(np.maximum(var[:, 0], 0.0)), np.sqrt(np.maximum(var[:, 1], 0.0))
