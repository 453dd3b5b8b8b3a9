"""Checking a bundle adjustment's inputs and turning them into the problem's arrays (METHODS §11).

Refusals are one line each (:class:`~gdal_gf4cal.bundle.model.BundleError`): fewer than 2 views, ties naming an
image that is not a view, a tie seen by one view only, observations outside their image, a view sharing no tie
with the others (or views falling into groups that share none).
"""
from __future__ import annotations

from typing import Dict, List, Mapping, Tuple

import numpy as np
import pandas as pd

from ..compensation import CompensationModel
from ..observations import validate_observations
from .model import BUNDLE_MODELS, MIN_SPAN, PAIR_FOLLOWER_FACTOR, BundleError, Rays, ViewLayout, prior_sigma_px

__all__ = ["check_inputs", "make_layout", "make_rays", "view_sizes"]


def _short(items, n: int = 5) -> str:
    items = [str(i) for i in items]
    return ", ".join(items[:n]) + (", ..." if len(items) > n else "")


def view_sizes(models: Mapping[str, object], sizes=None) -> Dict[str, Tuple[int, int]]:
    """``view -> (width, height)``: ``sizes`` where given, else the RPC's own image size."""
    out = {}
    for v, m in models.items():
        given = None if sizes is None else sizes.get(v)
        size = given if given is not None else getattr(m, "image_size", None)
        if size is None:
            raise BundleError(f"view {v!r}: no image size (give sizes={{view: (width, height)}})")
        out[v] = (int(size[0]), int(size[1]))
    return out


def check_inputs(observations, models: Mapping[str, object], sizes, dem=None, return_codes: bool = False):
    """The validated observation table restricted to nothing: refuses bad input (module docstring). With
    ``return_codes``: ``(table, codes)``, ``codes`` the ids' (:func:`~gdal_gf4cal.observations.validate_observations`)
    for :func:`make_rays`."""
    if models is None or len(models) < 2:
        raise BundleError(f"a bundle adjustment needs 2 or more views; got {0 if models is None else len(models)}")
    try:
        tab, codes = validate_observations(observations, source="ties", dem=dem, need_height=True,
                                           return_codes=True)
    except BundleError:
        raise
    except Exception as exc:                                   # GCPError: one line already; re-raise as ours
        raise BundleError(str(exc)) from None
    img = codes["image_id"]
    unknown = sorted(set(tab["image_id"].to_numpy()[_first_rows(img)]) - set(models))   # per image, not per row
    if unknown:
        raise BundleError(f"the ties name {len(unknown)} image(s) that are not among the views: {_short(unknown)}; "
                          f"views are {_short(models)} (give their RPCs or drop those rows)")
    _check_inside(tab, sizes, img)
    _check_connected(tab, list(models), codes)
    return (tab, codes) if return_codes else tab


def _first_rows(codes: np.ndarray) -> np.ndarray:
    """The first row of each code ``0..max`` (codes in order of first appearance, as ``pd.factorize`` gives)."""
    first = np.empty(int(codes.max()) + 1 if codes.size else 0, int)
    first[codes[::-1]] = np.arange(codes.size - 1, -1, -1)                      # the first row written last
    return first


def _view_codes(tab: pd.DataFrame, views: List[str], codes) -> np.ndarray:
    """Each row's view index (-1: not a view) from the image ids' codes (one look-up per image, not per row)."""
    img = codes["image_id"]
    names = tab["image_id"].to_numpy()[_first_rows(img)]                         # code k's name
    vi = {v: i for i, v in enumerate(views)}
    return np.array([vi.get(n, -1) for n in names], int)[img]


def _check_inside(tab: pd.DataFrame, sizes, codes: np.ndarray) -> None:
    names = tab["image_id"].to_numpy()[_first_rows(codes)]
    wh = np.array([sizes[v] for v in names], float)
    w, h = wh[codes, 0], wh[codes, 1]
    s, l = tab["sample"].to_numpy(float), tab["line"].to_numpy(float)
    out = (s < 0) | (s > w) | (l < 0) | (l > h)
    if out.any():
        i = int(np.flatnonzero(out)[0])
        r = tab.iloc[i]
        raise BundleError(f"{int(out.sum())} observation(s) lie outside their image, e.g. point {r['point_id']!r} "
                          f"in {r['image_id']!r} at ({s[i]:.1f}, {l[i]:.1f}) of a {int(w[i])} x {int(h[i])} image; "
                          "check the image ids and the pixel convention (GDAL: first pixel centre at 0.5)")


def _check_connected(tab: pd.DataFrame, views: List[str], codes) -> None:
    """Every view shares ties with the others, and the views form one group through their ties."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    tie = (tab["kind"] == "tie").to_numpy()
    img = _view_codes(tab, views, codes)[tie]                                 # arrays, not a copied table
    counts = np.bincount(img[img >= 0], minlength=len(views))
    lonely = [v for j, v in enumerate(views) if counts[j] == 0]
    if lonely:
        raise BundleError(f"view(s) {_short(lonely)} share no tie point with the others; give ties in them "
                          "(--ties / --match-ties) or leave them out")
    vi = {v: i for i, v in enumerate(views)}
    pinv = codes["point_id"][tie]                            # GCPs' columns stay empty: no link
    inc = sp.csr_matrix((np.ones(pinv.size), (img, pinv)), shape=(len(views), int(codes["point_id"].max()) + 1))
    n, label = connected_components(inc @ inc.T, directed=False)
    if n > 1:
        groups = [[v for v in views if label[vi[v]] == g] for g in range(n)]
        names = "; ".join(_short(g, 3) for g in groups)
        raise BundleError(f"the views fall into {n} groups that share no tie point ({names}); add ties linking them "
                          "or adjust the groups separately")


def _span(s, l, size) -> Tuple[float, float]:
    if len(s) < 2:
        return 0.0, 0.0
    qs, ql = np.percentile(s, [5, 95]), np.percentile(l, [5, 95])
    return float(qs[1] - qs[0]) / size[0], float(ql[1] - ql[0]) / size[1]


def make_layout(tab: pd.DataFrame, models: Mapping[str, object], sizes, model: str = "affine",
                prior=None, codes=None) -> ViewLayout:
    """Views, the correction model each can support (affine/shift-drift fall back to translation where the ties do
    not span :data:`MIN_SPAN` of the image on both axes) and the prior σ of each parameter; ``codes``: the ids'
    codes (:func:`check_inputs` ``return_codes``), else the image ids are looked up here."""
    base = CompensationModel.from_name(model)
    if base.name not in BUNDLE_MODELS:
        raise BundleError(f"bundle adjustment model must be one of {', '.join(BUNDLE_MODELS)}, not {model!r}")
    views = list(models)
    used: Dict[str, CompensationModel] = {}
    offset: Dict[str, int] = {}
    priors: List[np.ndarray] = []
    notes: List[str] = []
    ctrl = (tab["role"] == "control").to_numpy()
    code = (pd.Categorical(tab["image_id"], categories=views).codes if codes is None    # one pass, not per view
            else _view_codes(tab, views, codes))
    order = np.argsort(np.where(ctrl, code, -1), kind="stable")
    bounds = np.searchsorted(np.where(ctrl, code, -1)[order], np.arange(len(views) + 1))
    s_all, l_all = tab["sample"].to_numpy(float), tab["line"].to_numpy(float)
    pos = 0
    for j, v in enumerate(views):
        m = base
        if base.name != "translation":
            rows = order[bounds[j]:bounds[j + 1]]
            su, sv = _span(s_all[rows], l_all[rows], sizes[v])
            if min(su, sv) < MIN_SPAN:
                m = CompensationModel.from_name("translation")
                notes.append(f"{v}: {base.name} needs ties over {MIN_SPAN:.0%} of the image on both axes, they span "
                             f"{su:.0%} x {sv:.0%}: translation estimated instead")
        given = prior.get(v) if isinstance(prior, Mapping) else prior
        sig, source = prior_sigma_px(models[v], sizes[v], given)
        if len(views) == 2 and v == views[1] and given is None:
            sig *= PAIR_FOLLOWER_FACTOR
            source = f"{source}, x {PAIR_FOLLOWER_FACTOR:g}: the pair follows its first view, {views[0]}"
        notes.append(f"{v}: prior sigma {sig:.3g} px ({source})")
        used[v], offset[v] = m, pos
        priors.append(np.full(m.n_params, sig))
        pos += m.n_params
    return ViewLayout(views, dict(sizes), used, offset, pos, np.concatenate(priors), notes)


def make_rays(tab: pd.DataFrame, layout: ViewLayout, codes=None) -> Rays:
    """The table's rows as :class:`Rays` (points in order of first appearance), sorted by view then point
    (``Rays.row``: each ray's table row): a view's rays are one slice, its sample and line rows each a group of the
    grouped elimination in point order; ``codes``: the ids' codes (:func:`check_inputs` ``return_codes``), else
    factorised here."""
    if codes is None:
        codes = {c: pd.factorize(tab[c])[0] for c in ("point_id", "image_id")}
    point = codes["point_id"]
    counts = np.bincount(point)
    order = np.argsort(point, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
    slot = np.empty(len(tab), int)
    slot[order] = np.arange(len(tab)) - np.repeat(starts, counts)
    is_gcp = (tab["kind"] == "gcp").to_numpy()
    control = (tab["role"] == "control").to_numpy()
    first = order[starts]
    pids = tab["point_id"].to_numpy(object)[first]
    ground = np.full((pids.size, 3), np.nan)
    g = np.stack([tab[c].to_numpy(float) for c in ("lon", "lat", "h")], axis=1)
    ground[:] = g[first]
    p_gcp = is_gcp[first]
    p_ctrl = np.ones(pids.size, bool)
    p_ctrl[p_gcp] = control[first][p_gcp]
    view = _view_codes(tab, layout.views, codes)
    by = np.lexsort((point, view))                          # by view, then point
    return Rays(view=view[by], point=point[by], slot=slot[by],
                meas=np.stack([tab["sample"].to_numpy(float)[by], tab["line"].to_numpy(float)[by]], axis=1),
                sigma=tab["sigma"].to_numpy(float)[by], is_gcp=is_gcp[by], control=control[by], ground=ground,
                point_ids=pids, point_is_gcp=p_gcp, point_control=p_ctrl, k=int(counts.max()), row=by)
