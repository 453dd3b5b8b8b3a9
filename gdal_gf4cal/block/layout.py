"""The group's layout (METHODS §8): where each CCD and band image sits on the focal plane, derived from the RPCs and
the order and band pairing the user gives (:func:`derive_layout`), or read back from a calibration
(:func:`layout_from_calibration`)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from ..errors import GCPError
from ..geodesy import metres_per_degree

class BlockError(GCPError):
    """A block that cannot be adjusted as given (layout, overlaps, images, control): the message says what to do."""


class SeparateViewsError(BlockError):
    """Images that are separate views (stereo, tri-stereo, several dates), not CCDs or bands of one camera's pass:
    bundle adjustment (``gf4cal bundle-adjust``) is the method for them (issue 22)."""


#: Largest angle (degrees) between the lines of sight of two images at a ground point they share for them to be
#: CCDs or bands of one camera's pass: such images see a point from nearly the same place (staggered CCD rows and
#: band offsets on the focal plane: 0.03-0.49 deg in the simulated Jilin-1 group), separate views from another
#: place or attitude (19.6 deg for the Pleiades Ventoux stereo pair; a base-to-height ratio of 0.1 is 5.7 deg).
MAX_VIEW_ANGLE_DEG = 2.0
#: Two images whose footprints cover at least this share of each other are bands of one CCD (:func:`pair_bands`);
#: adjacent CCDs overlap a few percent.
SAME_CCD_OVERLAP = 0.5


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


def overlap_fraction(a, size_a, b, size_b, h, n: int = 9) -> float:
    """Share of a grid over image ``b`` that falls inside image ``a`` (through ``b.localize`` and ``a.project``)."""
    W, H = size_b
    s, l = (v.ravel() for v in np.meshgrid((np.arange(n) + 0.5) * W / n, (np.arange(n) + 0.5) * H / n))
    lon, lat = b.localize(s, l, np.full(s.shape, h))
    sa, la = a.project(lon, lat, np.full(s.shape, h))
    inside = np.isfinite(sa) & np.isfinite(la) & (sa >= 0) & (sa <= size_a[0]) & (la >= 0) & (la <= size_a[1])
    return float(np.mean(inside))


def pixel_ground_size(model, size, h) -> float:
    lon, lat = model.localize(size[0] / 2.0, size[1] / 2.0, h)
    j = np.asarray(model.project_jacobian(lon, lat, h))[..., :2].reshape(2, 2)
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
    check_one_pass(models, sizes, list(zip(order[:-1], order[1:])) + [(r, b) for b, r in bands_of.items()], h)
    # groups mixed: an image that overlaps none of the others
    if len(order) > 1:
        for a in order:
            if all(overlap_fraction(models[b], sizes[b], models[a], sizes[a], h) == 0.0
                   and overlap_fraction(models[a], sizes[a], models[b], sizes[b], h) == 0.0
                   for b in order if b != a):
                raise BlockError(f"{a} overlaps none of the other CCD images: the images are not one group "
                                 "(different groups or scenes mixed); give the CCD images of one group")
    for a, b in zip(order[:-1], order[1:]):
        if overlap_fraction(models[a], sizes[a], models[b], sizes[b], h, n=33) == 0.0:
            raise BlockError(f"no overlap between {a} and {b}, given as adjacent CCDs; list the CCD images in their "
                             "order across track")
    gsd_ref = pixel_ground_size(models[ref], sizes[ref], h)
    layout: Dict[str, ImageLayout] = {}
    x0 = {order[0]: 0.0}
    for a, b in zip(order[:-1], order[1:]):
        lon, lat = models[b].localize(sizes[b][0] / 2.0, sizes[b][1] / 2.0, h)
        sa, _ = models[a].project(lon, lat, h)
        ra = pixel_ground_size(models[a], sizes[a], h) / gsd_ref
        x0[b] = x0[a] + (float(sa) - sizes[a][0] / 2.0) * ra
    for k, im in enumerate(order):
        layout[im] = ImageLayout(im, im, k + 1, sizes[im], pixel_ground_size(models[im], sizes[im], h) / gsd_ref,
                                 x0[im] - x0[ref])
    for band, r in bands_of.items():
        if overlap_fraction(models[r], sizes[r], models[band], sizes[band], h) == 0.0:
            raise BlockError(f"--bands-of {band}={r}: {band} does not overlap {r}; give the reference-band image "
                             "of the same CCD")
        lon, lat = models[band].localize(sizes[band][0] / 2.0, sizes[band][1] / 2.0, h)
        sr, _ = models[r].project(lon, lat, h)
        x = layout[r].x0_px + (float(sr) - sizes[r][0] / 2.0) * layout[r].ratio
        layout[band] = ImageLayout(band, r, layout[r].ccd, sizes[band],
                                   pixel_ground_size(models[band], sizes[band], h) / gsd_ref, x)
    return BlockLayout(layout, order, ref, sizes[ref][1] / 2.0)


def view_angle(a, size_a, b, size_b, h: float) -> float:
    """Angle (degrees) between the lines of sight of models ``a`` and ``b`` at the ground point of ``b``'s centre
    (at height ``h``): from each model's ground displacement of that point's pixel per metre of height."""
    lon, lat = b.localize(size_b[0] / 2.0, size_b[1] / 2.0, h)
    sa, la = a.project(lon, lat, h)

    def slope(m, s, l):
        lon0, lat0 = m.localize(s, l, h)
        lon1, lat1 = m.localize(s, l, h + 100.0)
        mx, my = metres_per_degree(float(lat0), h)
        return np.array([(float(lon1) - float(lon0)) * float(mx), (float(lat1) - float(lat0)) * float(my)]) / 100.0

    d = slope(a, float(sa), float(la)) - slope(b, size_b[0] / 2.0, size_b[1] / 2.0)
    return float(np.degrees(np.arctan(np.hypot(d[0], d[1]))))


def check_one_pass(models: Mapping[str, Any], sizes: Mapping[str, Tuple[int, int]], pairs, h: float) -> None:
    """Refuse images that are separate views (:class:`SeparateViewsError`): pairs (adjacent CCDs, a band and its
    reference image) that share ground at some height of ``b``'s RPC range (at ``h``, its lowest or highest: views
    far apart overlap only at the true height) and whose lines of sight differ by more than
    :data:`MAX_VIEW_ANGLE_DEG`."""
    for a, b in pairs:
        heights = (h,) + tuple(float(v) for v in models[b].height_range)
        if all(overlap_fraction(models[a], sizes[a], models[b], sizes[b], hh) == 0.0 for hh in heights):
            continue
        ang = view_angle(models[a], sizes[a], models[b], sizes[b], h)
        if ang > MAX_VIEW_ANGLE_DEG:
            raise SeparateViewsError(
                f"{a} and {b} see the ground from directions {ang:.1f} deg apart: they are separate views (stereo "
                "or different passes), not CCDs or bands of one camera; adjust them with bundle adjustment "
                "(gf4cal bundle-adjust, QGIS gf4cal:bundleadjust)")


def pair_bands(models: Mapping[str, Any], images: Sequence[str], *,
               sizes: Optional[Mapping[str, Tuple[int, int]]] = None, h: Optional[float] = None
               ) -> Tuple[List[str], Dict[str, str]]:
    """The default band-to-CCD pairing from the RPCs: ``(order, bands_of)``. An image whose footprint and an
    earlier-given image's cover at least :data:`SAME_CCD_OVERLAP` of each other is another band of that CCD, whose
    reference-band image is the first given of them; the others are the reference-band CCD images, in the order
    given (across track)."""
    sizes = {k: _model_size(models[k], (sizes or {}).get(k)) for k in images}
    h = _mid_height(models[images[0]]) if h is None else float(h)
    order: List[str] = []
    bands: Dict[str, str] = {}
    for im in images:
        ref = next((r for r in order
                    if min(overlap_fraction(models[r], sizes[r], models[im], sizes[im], h),
                           overlap_fraction(models[im], sizes[im], models[r], sizes[r], h)) >= SAME_CCD_OVERLAP),
                   None)
        if ref is None:
            order.append(im)
        else:
            bands[im] = ref
    return order, bands




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

