"""Sub-CCD edges of the MS image (METHODS §9): equal pieces, the pan's edges mapped into the MS, and the jumps
of the per-column residual of the window matches that pass a test (:func:`detect_breaks`)."""
from __future__ import annotations

from typing import List, Tuple

import numpy as np
from scipy import stats

from ..basis import piecewise_polynomial
from ..estimation import normal_solve
from ..stats import grouped_trimmed_mean
from .model import AXES, PanMSError

# ------------------------------------------------------------------------------------------------ the model
def default_breaks(ms_width: float, n_sub_ccds: int = 3) -> List[float]:
    """Equal sub-CCD edges of an MS band ``ms_width`` px wide: ``W k / n``, k = 1..n-1 (MS samples)."""
    n = int(n_sub_ccds)
    if n < 1:
        raise PanMSError(f"--sub-ccds must be at least 1 (got {n})")
    return [float(ms_width) * k / n for k in range(1, n)]


def pan_edges_in_ms(pan_model, ms_model, dem, pan_size, n_sub_ccds: int = 3, n_lines: int = 9) -> List[float]:
    """The pan's equal sub-CCD edges (pan samples ``W_pan k / n``) mapped into MS samples (METHODS §9: the pan's
    jumps show in the pan-MS misregistration too): each edge column is localised on the DEM with the pan model at
    ``n_lines`` lines and projected with the MS model; the median MS sample is the edge. NaN-free or an error."""
    pw, ph = pan_size
    edges = default_breaks(pw, n_sub_ccds)
    if not edges:
        return []
    s = np.repeat(np.asarray(edges, float), n_lines)
    l = np.tile((np.arange(n_lines) + 0.5) * float(ph) / n_lines, len(edges))
    with np.errstate(all="ignore"):
        lon, lat, h = pan_model.localize_dem(s, l, dem)
        ms_s, _ = ms_model.project(lon, lat, h)
    ms_s = np.asarray(ms_s, float).reshape(len(edges), n_lines)
    if not np.isfinite(ms_s).any(axis=1).all():
        raise PanMSError("cannot map the pan's sub-CCD edges into the MS image (no DEM height or no MS projection "
                         "there): give --breaks as MS columns")
    return [float(v) for v in np.nanmedian(ms_s, axis=1)]


def merge_breaks(*lists, width: float, tol_px: float = 1.0) -> List[float]:
    """Sorted union of breakpoint lists inside ``(0, width)``; edges closer than ``tol_px`` are one (their mean)."""
    b = np.sort(np.asarray([float(v) for lst in lists for v in lst if 0.0 < float(v) < float(width)], float))
    out: List[List[float]] = []
    for v in b:
        if out and v - out[-1][-1] < tol_px:
            out[-1].append(float(v))
        else:
            out.append([float(v)])
    return [float(np.mean(g)) for g in out]


#: False-alarm probability below which a jump in the per-column residual is taken for a sub-CCD edge.
JUMP_FAP = 1e-3
#: Width of the transition a jump leaves in the window offsets, as a share of the window: the correlator's taper
#: weights the window's central half (measured on the GF7 simulator: 16 px for 32 px windows).
RAMP_SHARE = 0.5
#: Order of the smooth part of the per-column residual on each side of the edges found (detect_breaks).
JUMP_SMOOTH_ORDER = 3
#: Order of the sub-CCD pieces themselves (METHODS §9: quartics): the order an edge is confirmed, placed and its
#: jump read with (a cubic leaves their bending, which a jump test takes for small jumps: detect_breaks).
PIECE_ORDER = 4
#: What a singular fit of the per-column profile tells the user.
HINT = ("the sub-CCD edge model of the per-column misregistration profile; give the edges (--breaks) or "
        "a denser matching (smaller --cell)")


def column_profile(sample, line, d_sample, d_line):
    """The misregistration along the MS line of sensor columns: ``(x, y, n)`` with ``x`` the window columns at
    their measured position (sorted), ``y[:, axis]`` the median over the lines of each window's offset minus its row's median (what
    varies along the line -- attitude, jitter -- removed), ``n`` windows per column."""
    s, l = np.round(np.asarray(sample, float), 3), np.round(np.asarray(line, float), 3)
    d = np.stack([np.asarray(d_sample, float), np.asarray(d_line, float)], axis=1)
    ok = np.isfinite(d).all(axis=1) & np.isfinite(s) & np.isfinite(l)
    s, l, d = s[ok], l[ok], d[ok]
    if s.size == 0:
        return np.zeros(0), np.zeros((0, 2)), np.zeros(0, int)
    _, ri = np.unique(l, return_inverse=True)
    ux, ci = np.unique(s, return_inverse=True)
    rowm = grouped_trimmed_mean(ri, d, int(ri.max()) + 1).mean
    m = grouped_trimmed_mean(ci, d - rowm[ri], ux.size)
    # a window shows the MS around its centre moved by its offset (the matcher re-reads it there): place each
    # column at its windows' mean measured position, not at the predicted one (else a jump lands ~1 px aside)
    pos = grouped_trimmed_mean(ci, (s + d[:, 0])[:, None], ux.size).mean[:, 0]
    order = np.argsort(pos, kind="stable")
    return pos[order], m.mean[order], m.n[order]


def _ramp(x, b, width):
    """A jump at ``b`` as matching windows ``width`` wide see it: 0 left of ``b - width/2``, 1 right of
    ``b + width/2``, linear between (a window straddling the edge measures the mix of both sides)."""
    return np.clip((np.asarray(x, float)[:, None] - np.asarray(b, float)[None, :]) / float(width) + 0.5, 0.0, 1.0)


def _jump_gain(x, y, w, found, cand, width, span, order=JUMP_SMOOTH_ORDER):
    """RSS reduction of both axes from adding a ramp at each candidate in ``cand`` to the smooth model (a
    polynomial of order JUMP_SMOOTH_ORDER per piece between the edges ``found``, plus their ramps), weights ``w``
    per column; and the RSS of the smooth model. Vectorised over the candidates (projection on the orthonormal
    basis of the weighted smooth design)."""
    base = piecewise_polynomial(x, found, order, domain=span)
    if found:
        base = np.concatenate([base, _ramp(x, found, width)], axis=1)
    sw = np.sqrt(w)
    q, _ = np.linalg.qr(base * sw[:, None])
    rw = _ramp(x, cand, width) * sw[:, None]
    mr = rw - q @ (q.T @ rw)
    den = np.einsum("ij,ij->j", mr, mr)
    gain = np.zeros(len(cand))
    rss = 0.0
    for k in range(2):
        e = y[:, k] * sw - q @ (q.T @ (y[:, k] * sw))
        gain = gain + np.where(den > 1e-12, (mr.T @ e) ** 2 / np.maximum(den, 1e-12), 0.0)
        rss += float(e @ e)
    return gain, rss, base.shape[1]


def _smooth_residual(x, y, w, edges, width, span, order=JUMP_SMOOTH_ORDER):
    """Residual (columns, 2) of the per-column profile ``y`` after the smooth model with ramps at ``edges``."""
    base = piecewise_polynomial(x, edges, order, domain=span)
    if edges:
        base = np.concatenate([base, _ramp(x, edges, width)], axis=1)
    return np.stack([y[:, k] - base @ normal_solve(base, y[:, k], w, HINT)[0] for k in range(2)], axis=1)


def _correlation_length(e, *, max_lag: int) -> float:
    """Columns per independent one in a residual profile ``e`` (columns, axes): the integrated autocorrelation
    ``1 + 2 sum_j rho_j`` over lags up to the first non-positive ``rho_j`` (or ``max_lag``), the larger over the
    axes. Neighbouring columns share the matching windows' pixels and the texture's bias: the profile is smoother
    than its per-column scatter says, and a jump test that counts every column as independent finds jumps in it."""
    out = 1.0
    for k in range(e.shape[1]):
        v = e[:, k] - np.mean(e[:, k])
        var = float(v @ v)
        if var <= 0.0:
            continue
        tau = 1.0
        for j in range(1, min(int(max_lag), v.size // 4) + 1):
            rho = float(v[:-j] @ v[j:]) / var
            if rho <= 0.0:
                break
            tau += 2.0 * rho
        out = max(out, tau)
    return out


def _supported(x, found, cand, ramp: float) -> np.ndarray:
    """Candidate edges the model can resolve: their two new intervals (between the neighbouring edges ``found``)
    each hold at least ``JUMP_SMOOTH_ORDER + 2`` columns ``x`` and a column lies inside their ramp (``|x - b| <
    ramp / 2``): else the ramp is a step, the same as the intervals' constants, or the side's polynomial fits its
    columns exactly and absorbs the ramp (a singular fit). On a sparse profile, e.g. columns every 32 px of a full
    scene, neither holds everywhere."""
    xs = np.sort(np.asarray(x, float))
    bounds = np.concatenate([[-np.inf], np.sort(np.asarray(found, float)), [np.inf]])
    k = np.searchsorted(bounds, cand, side="right")
    at = np.searchsorted(xs, cand, side="left")
    left = at - np.searchsorted(xs, bounds[k - 1], side="left")
    right = np.searchsorted(xs, bounds[k], side="left") - at
    in_ramp = np.searchsorted(xs, cand + 0.5 * ramp, side="left") > np.searchsorted(xs, cand - 0.5 * ramp,
                                                                                     side="right")
    return (left >= JUMP_SMOOTH_ORDER + 2) & (right >= JUMP_SMOOTH_ORDER + 2) & in_ramp


def _edge_fit(x, y, w, b, lo, hi, ramp):
    """The edge model at ``b`` on the columns strictly between ``lo`` and ``hi``: a polynomial of order
    PIECE_ORDER on each side, mixed over the ramp as a window straddling the edge sees it (``(1 - r) P_left
    + r P_right``, ``r`` = :func:`_ramp`; the jump is tied to the sides, not a free column). Returns ``(weighted RSS
    of both axes, jump per axis P_right(b) - P_left(b))``, or ``(inf, None)`` when a side has too few columns."""
    sel = (x > lo) & (x < hi)
    xs, ys, ws = x[sel], y[sel], w[sel]
    k = PIECE_ORDER + 1
    if np.count_nonzero(xs < b) < k + 1 or np.count_nonzero(xs > b) < k + 1:
        return np.inf, None
    r = _ramp(xs, [b], ramp)[:, 0]
    u = (xs - b) / max(float(np.ptp(xs)), 1.0)
    powers = u[:, None] ** np.arange(k)[None, :]
    design = np.concatenate([(1.0 - r)[:, None] * powers, r[:, None] * powers], axis=1)
    rss, jump = 0.0, []
    for a in range(ys.shape[1]):
        coef = normal_solve(design, ys[:, a], ws, HINT)[0]
        e = ys[:, a] - design @ coef
        rss += float(ws @ (e * e))
        jump.append(float(coef[k] - coef[0]))
    return rss, jump


def _place(x, y, w, others, b, ramp, reach, min_gap):
    """Where the edge found near ``b`` lies on a sparse profile (at most one column inside a ramp): the place
    within ``reach`` px (0.25 px steps, more than ``min_gap`` from the ``others`` edges, a column inside the ramp)
    whose :func:`_edge_fit` between the neighbouring edges fits best. The test's place is set there by one column's
    value and by the misfit of one smooth polynomial across the edge, which can favour the next column gap (the
    full GF7 scene: 5147 for 5120). Returns ``b`` itself when no place can be fitted."""
    others = np.asarray(others, float)
    lo, hi = _between(others, b, ramp)
    cand = np.arange(b - reach, b + reach + 1e-9, 0.25)
    cand = cand[np.all(np.abs(cand[:, None] - np.append(others, -1e9)[None, :]) > min_gap, axis=1)]
    cand = cand[_supported(x, others, cand, ramp)]
    rss = np.array([_edge_fit(x, y, w, c, lo, hi, ramp)[0] for c in cand])
    if not np.isfinite(rss).any():
        return b
    return float(cand[int(np.argmin(rss))])


def _between(others, b, ramp):
    """The span an edge at ``b`` is fitted on: from the ramp's end of the nearest other edge on each side."""
    others = np.asarray(others, float)
    return (float(others[others < b].max(initial=-np.inf)) + 0.5 * ramp,
            float(others[others > b].min(initial=np.inf)) - 0.5 * ramp)


def _jump_fap(x, y, w, found, b, ramp, span, spacing_px, n_indep, order=JUMP_SMOOTH_ORDER) -> float:
    """False-alarm probability of a jump at ``b`` over the smooth model of ``order`` (edges ``found``): its F
    statistic, residual variance per column from every column, degrees of freedom from the independent ones, as
    many as the residual's correlation length (at least the window's effective width ``2 ramp``) leaves; times the
    ``n_indep`` places searched. Neighbouring columns share pixels: the statistic is deflated by that length."""
    gain, rss, p = _jump_gain(x, y, w, found, np.array([b]), ramp, span, order)
    if x.size - p - 1 < 4:
        return 1.0
    s2 = (rss - float(gain[0])) / (2.0 * (x.size - p - 1))
    e = _smooth_residual(x, y, w, sorted(found + [b]), ramp, span, order)
    corr = max(1.0, ramp / float(spacing_px), _correlation_length(e, max_lag=int(round(8.0 * ramp / spacing_px))))
    dof = 2.0 * max(x.size / corr - p - 1, 2.0)
    F = (float(gain[0]) / 2.0) / max(s2, 1e-300) / corr
    return min(1.0, float(stats.f.sf(F, 2, dof)) * n_indep)


def detect_breaks(sample, line, d_sample, d_line, *, width: float, window_px: float, spacing_px: float,
                  max_breaks: int = 8) -> Tuple[List[float], List[dict]]:
    """Sub-CCD edges found in the data (METHODS §9): jumps of the per-column residual (:func:`column_profile` of
    the window matches) that pass a test. Greedy: the strongest ramp (a jump as ``window_px`` windows see it) over
    the smooth model, kept while its F statistic's false-alarm probability over the independent places searched is
    below :data:`JUMP_FAP` (neighbouring columns share pixels: the statistic is deflated, and its degrees of
    freedom counted, by the residual's correlation length, at least the window's effective width over
    ``spacing_px``), and confirmed over pieces of their own order (:data:`PIECE_ORDER`). Placed to 0.25 px by the
    test, or on a sparse profile (at most one column inside a ramp) by :func:`_place` (a polynomial on each side
    mixed over the ramp, within a window and a column gap; again between the final neighbours), then on the
    nearest pixel boundary; the jumps from :func:`_edge_fit`. Returns ``(edges in MS columns, [{edge_ms_px,
    jump_sample_px, jump_line_px, fap}])``."""
    x, y, n = column_profile(sample, line, d_sample, d_line)
    keep = n >= 3
    x, y, n = x[keep], y[keep], n[keep]
    found: List[float] = []
    info: List[dict] = []
    ramp = RAMP_SHARE * float(window_px)
    if x.size < 4 * (JUMP_SMOOTH_ORDER + 2):
        return found, info
    span = (0.0, float(width))
    w = n.astype(float)
    lo, hi = float(x.min()) + window_px / 2.0, float(x.max()) - window_px / 2.0
    n_indep = max(1.0, (hi - lo) / float(window_px))
    reach = float(window_px) + float(spacing_px)       # the test's place may be a column gap off (_place)
    sparse = float(spacing_px) >= ramp                  # at most one column inside a ramp
    while len(found) < max_breaks:
        cand = np.arange(lo, hi, 1.0)
        cand = cand[np.all(np.abs(cand[:, None] - np.asarray(found + [-1e9])[None, :]) > window_px, axis=1)]
        cand = cand[_supported(x, found, cand, ramp)]
        if cand.size == 0:
            break
        gain, rss, p = _jump_gain(x, y, w, found, cand, ramp, span)
        b0 = float(cand[int(np.argmax(gain))])
        fine = np.arange(b0 - 1.0, b0 + 1.0001, 0.25)
        ok = _supported(x, found, fine, ramp)
        fine = fine[ok] if ok.any() else np.array([b0])
        g2, _, _ = _jump_gain(x, y, w, found, fine, ramp, span)
        b = float(fine[int(np.argmax(g2))])
        if x.size - p - 1 < 4:
            break
        fap = _jump_fap(x, y, w, found, b, ramp, span, spacing_px, n_indep)
        if fap < JUMP_FAP:              # confirmed over the pieces' own order (else a bend, not a jump)
            fap = max(fap, _jump_fap(x, y, w, found, b, ramp, span, spacing_px, n_indep, PIECE_ORDER))
        if not np.isfinite(fap) or fap >= JUMP_FAP:
            break
        if sparse:
            b = _place(x, y, w, found, b, ramp, reach, window_px)
        b = float(round(b))             # an edge between two detectors lies between two pixel columns
        found = sorted(found + [b])
        info.append({"edge_ms_px": b, "fap": fap})
    # on a sparse profile each edge placed again between its final neighbours; the jumps from the two sides
    for it in info:
        others = [e for e in found if e != it["edge_ms_px"]]
        if sparse:
            it["edge_ms_px"] = float(round(_place(x, y, w, others, it["edge_ms_px"], ramp, reach, window_px)))
            found = sorted(others + [it["edge_ms_px"]])
        jump = _edge_fit(x, y, w, it["edge_ms_px"], *_between(others, it["edge_ms_px"], ramp), ramp)[1]
        it.update({f"jump_{ax}_px": float(j) for ax, j in zip(AXES, jump or [np.nan, np.nan])})
    info.sort(key=lambda d: d["edge_ms_px"])
    return found, info
