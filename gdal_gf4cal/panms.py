"""Pan-to-multispectral registration compensation (METHODS §9, seed 004, Gaofen-7).

Estimate, then apply:

* :func:`estimate` solves METHODS §9's model ``delta(s, l) = delta_L + delta_I(s) + delta_J(s, l)`` per axis from
  the dense cell observations (``gdal_gf4cal.matching.pan_ms_cells``: MS cell centres ``sample, line`` and
  ``nabla = p' - p''`` as ``d_sample, d_line``), **stepwise** (eqs. 14-16): the linear term (6 parameters) on all
  usable cells, the piecewise quartic per sub-CCD in the MS column (5 x 2 per piece, 30 for 3 sub-CCDs) on what
  remains, the trigonometric jitter series in the line scaled by ``(1 + B s)`` with frequencies picked from the
  residual spectrum (a component is accepted only when significant). Every step is a robust estimate of the
  estimation core (high-breakdown start + data snooping) with the earlier terms' datum frozen. **Reuse mode**
  (eq. 17): the piecewise term of another scene of the same camera is frozen and only the linear term is solved
  from a few sparse cells.
* :class:`PanMSModel` is the plain result: ``predict(sample, line) -> (d_sample, d_line)`` (MS pixels, GDAL
  convention), per-step statistics ``steps``, JSON round trip.
* :func:`write_correction` writes ``correction.tif`` (delta at every MS pixel centre, MS grid, tile by tile),
  :func:`resample_ms_on_pan` writes the MS bands resampled onto the pan's raw grid at MS resolution (what
  ``gdal_pansharpen.py`` needs: same extent as the pan, no halos), :func:`approximate_rpc` refits the MS RPC
  with the model (a smooth approximation: an RPC cannot carry the sub-CCD jumps; its error is reported).

``delta`` is where the MS image shows a ground point minus where the pan, the DEM and the MS RPC predict it: the
MS image shows the ground point predicted at ``p''`` at ``p' = p'' + delta(p')``.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .basis import piecewise_polynomial, trigonometric
from .errors import DegenerateGeometryError, Gf4calError
from .estimation import Block, normal_solve, robust_lsq, weighted_lsq
from .matching import reject_outliers
from .progress import report
from .stats import axis_stats, grouped_trimmed_mean, share_within

__all__ = ["PanMSModel", "estimate", "default_breaks", "screen_matches", "detect_breaks", "column_profile", "pan_edges_in_ms", "merge_breaks", "write_correction", "resample_ms_on_pan",
           "approximate_rpc", "GF7_MS_LINE_TIME_S", "GF7_MS_IFOV_RAD", "GF7_LOOK_TIME_S", "PanMSError"]

AXES = ("sample", "line")
ORDER = 4
#: Nominal GF7 backward-camera MS line period (s), instantaneous field of view (rad) and pan-MS look-time
#: difference (s) (METHODS §9, §10): only used to express jitter in Hz and as attitude angles.
GF7_MS_LINE_TIME_S = 3.65e-4
GF7_MS_IFOV_RAD = 5.105e-6
GF7_LOOK_TIME_S = 0.117
#: Threshold of the P(<= t) statistic (MS px, METHODS §9).
P_THRESHOLD_PX = 0.25
#: False-alarm probability below which a jitter component is accepted (``jitter="auto"``).
JITTER_FAP = 1e-3
MAX_JITTER_COMPONENTS = 8
REUSE_MAX_RMS_PX = 0.1         # reuse mode: refuse a fit worse than this and ...
REUSE_MAX_FLOOR_RATIO = 3.0     # ... this many times the cells' noise floor (another camera's model), or ...
REUSE_MAX_OUTLIER_SHARE = 0.25  # ... with more of its cells rejected as blunders


class PanMSError(Gf4calError, ValueError):
    """Pan-MS registration cannot be done with these inputs (the message says what to do)."""


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


#: Local consistency screen of the window matches (screen_matches): windows of one column in blocks of this many
#: rows, a window off its block's median by more than SCREEN_K robust standard deviations (floored) is a blunder.
SCREEN_ROWS = 16
SCREEN_K = 4.0
SCREEN_FLOOR_PX = 0.05
#: ... and a window farther than this from the scene's affine consensus (RANSAC) is a gross mismatch.
SCREEN_GROSS_PX = 3.0


def screen_matches(sample, line, d_sample, d_line, *, spacing_px: float, seed: int = 0) -> np.ndarray:
    """Blunders among the window matches (bool per window), found without a model of the field (METHODS §9): a
    window farther than :data:`SCREEN_GROSS_PX` from the affine consensus of all (RANSAC, no MAD stage), or off
    the median of the windows of its own column and nearby rows (blocks of :data:`SCREEN_ROWS` rows) by more than
    :data:`SCREEN_K` robust standard deviations (1.4826 MAD, at least :data:`SCREEN_FLOOR_PX`) on either axis.
    A sub-CCD jump runs along whole columns, so a screen within a column never flags one side of it (a global
    low-order model with a MAD cut rejects every column of the smaller side: the jump is then not found). NaN
    offsets are blunders."""
    s, l = np.asarray(sample, float), np.asarray(line, float)
    d = np.stack([np.asarray(d_sample, float), np.asarray(d_line, float)], axis=1)
    ok = np.isfinite(d).all(axis=1) & np.isfinite(s) & np.isfinite(l)
    out = ~ok
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return out
    if idx.size >= 8:
        gross = reject_outliers(s[idx], l[idx], d[idx, 0], d[idx, 1], model="affine", threshold_px=SCREEN_GROSS_PX,
                                mad_k=np.inf, seed=seed).outlier
        out[idx[gross]] = True
        idx = idx[~gross]
    _, col = np.unique(np.round(s[idx], 3), return_inverse=True)
    blk = np.floor((l[idx] - l[idx].min()) / (SCREEN_ROWS * float(spacing_px))).astype(np.int64)
    _, g = np.unique(col.astype(np.int64) * (int(blk.max()) + 1) + blk, return_inverse=True)
    n_g = int(g.max()) + 1
    dev = np.abs(d[idx] - grouped_trimmed_mean(g, d[idx], n_g).median[g])
    sig = np.maximum(1.4826 * grouped_trimmed_mean(g, dev, n_g).median, SCREEN_FLOOR_PX)
    out[idx[np.any(dev > SCREEN_K * sig[g], axis=1)]] = True
    return out


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


def _jump_gain(x, y, w, found, cand, width, span):
    """RSS reduction of both axes from adding a ramp at each candidate in ``cand`` to the smooth model (a
    polynomial of order JUMP_SMOOTH_ORDER per piece between the edges ``found``, plus their ramps), weights ``w``
    per column; and the RSS of the smooth model. Vectorised over the candidates (projection on the orthonormal
    basis of the weighted smooth design)."""
    from .basis import piecewise_polynomial
    base = piecewise_polynomial(x, found, JUMP_SMOOTH_ORDER, domain=span)
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


def _smooth_residual(x, y, w, edges, width, span):
    """Residual (columns, 2) of the per-column profile ``y`` after the smooth model with ramps at ``edges``."""
    from .basis import piecewise_polynomial
    base = piecewise_polynomial(x, edges, JUMP_SMOOTH_ORDER, domain=span)
    if edges:
        base = np.concatenate([base, _ramp(x, edges, width)], axis=1)
    return np.stack([y[:, k] - base @ normal_solve(base, y[:, k], w)[0] for k in range(2)], axis=1)


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


def detect_breaks(sample, line, d_sample, d_line, *, width: float, window_px: float, spacing_px: float,
                  max_breaks: int = 8) -> Tuple[List[float], List[dict]]:
    """Sub-CCD edges found in the data (METHODS §9): jumps of the per-column residual (:func:`column_profile` of
    the window matches) that pass a test. Greedy: the strongest ramp (a jump as ``window_px`` windows see it) over
    the smooth model, placed to 0.25 px then on the nearest pixel boundary, kept while its F statistic's false-alarm probability over the
    independent places searched is below :data:`JUMP_FAP` (neighbouring columns share pixels: the statistic is
    deflated, and its degrees of freedom counted, by the window's effective width over ``spacing_px``). Returns ``(edges in MS columns, [{edge, jump_sample_px,
    jump_line_px, fap}])``."""
    from scipy import stats
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
    corr0 = max(1.0, ramp / float(spacing_px))      # columns per independent one (the window's effective width)
    lo, hi = float(x.min()) + window_px / 2.0, float(x.max()) - window_px / 2.0
    n_indep = max(1.0, (hi - lo) / float(window_px))
    while len(found) < max_breaks:
        cand = np.arange(lo, hi, 1.0)
        cand = cand[np.all(np.abs(cand[:, None] - np.asarray(found + [-1e9])[None, :]) > window_px, axis=1)]
        if cand.size == 0:
            break
        gain, rss, p = _jump_gain(x, y, w, found, cand, ramp, span)
        b0 = float(cand[int(np.argmax(gain))])
        fine = np.arange(b0 - 1.0, b0 + 1.0001, 0.25)
        g2, _, _ = _jump_gain(x, y, w, found, fine, ramp, span)
        b = float(fine[int(np.argmax(g2))])
        if x.size - p - 1 < 4:
            break
        # residual variance per column from every column; its degrees of freedom from the independent ones, as
        # many as the residual's correlation length (at least the window's effective width) leaves
        s2 = (rss - float(g2.max())) / (2.0 * (x.size - p - 1))
        e = _smooth_residual(x, y, w, sorted(found + [b]), ramp, span)
        corr = max(corr0, _correlation_length(e, max_lag=int(round(4.0 * window_px / float(spacing_px)))))
        dof = 2.0 * max(x.size / corr - p - 1, 2.0)
        F = (float(g2.max()) / 2.0) / max(s2, 1e-300) / corr
        fap = min(1.0, float(stats.f.sf(F, 2, dof)) * n_indep)
        if not np.isfinite(fap) or fap >= JUMP_FAP:
            break
        b = float(round(b))             # an edge between two detectors lies between two pixel columns
        found = sorted(found + [b])
        info.append({"edge_ms_px": b, "fap": fap})
    # the jump of each edge found, from the final model
    if found:
        from .basis import piecewise_polynomial
        base = np.concatenate([piecewise_polynomial(x, found, JUMP_SMOOTH_ORDER, domain=span),
                               _ramp(x, found, ramp)], axis=1)
        for k, ax in enumerate(AXES):
            coef = normal_solve(base, y[:, k], w)[0][-len(found):]
            for it in info:
                it[f"jump_{ax}_px"] = float(coef[found.index(it["edge_ms_px"])])
    info.sort(key=lambda d: d["edge_ms_px"])
    return found, info


@dataclass
class PanMSModel:
    """METHODS §9's registration model of one MS image against its pan (all in MS pixels, GDAL convention).

    ``linear`` = ``A1..A6`` of ``A1 + A2 s + A3 l`` (sample), ``A4 + A5 s + A6 l`` (line) with ``s, l``
    normalised to [-1, 1] over the MS image; ``piecewise[k, axis, j]`` the quartic coefficient of ``u_k^j`` in
    sub-CCD ``k`` (``u_k`` in [-1, 1] over the piece between ``breaks``); ``jitter[axis]`` =
    ``{"b": B, "components": [{"frequency_cycles_per_line", "sin", "cos", ...}]}`` for
    ``(1 + B s) sum_i (sin_i sin(2 pi f_i l) + cos_i cos(2 pi f_i l))`` with ``l`` in MS lines.
    """

    ms_size: Tuple[int, int]
    breaks: Tuple[float, ...]
    linear: np.ndarray = field(default_factory=lambda: np.zeros(6))
    piecewise: Optional[np.ndarray] = None
    jitter: Dict[str, dict] = field(default_factory=dict)
    steps: List[dict] = field(default_factory=list)
    mode: str = "solve"
    info: Dict[str, object] = field(default_factory=dict)
    #: Per cell of the estimate: flagged as a blunder by the last robust step (not serialised).
    cell_outlier: Optional[np.ndarray] = field(default=None, repr=False)
    #: The model after each step (``step_residuals`` evaluates the cells on them; not serialised).
    snapshots: List[dict] = field(default_factory=list, repr=False)

    def __post_init__(self):
        self.ms_size = (int(self.ms_size[0]), int(self.ms_size[1]))
        self.breaks = tuple(sorted(float(b) for b in self.breaks))
        self.linear = np.asarray(self.linear, dtype=float).reshape(6)
        if self.piecewise is None:
            self.piecewise = np.zeros((self.n_sub_ccds, 2, ORDER + 1))
        self.piecewise = np.asarray(self.piecewise, dtype=float).reshape(self.n_sub_ccds, 2, ORDER + 1)
        for ax in AXES:
            self.jitter.setdefault(ax, {"b": 0.0, "components": []})

    @property
    def n_sub_ccds(self) -> int:
        return len(self.breaks) + 1

    # -- evaluation -------------------------------------------------------------------------------------
    def _norm(self, sample, line):
        W, H = self.ms_size
        return (np.asarray(sample, float) - W / 2.0) / (W / 2.0), (np.asarray(line, float) - H / 2.0) / (H / 2.0)

    def predict(self, sample, line, *, terms: Sequence[str] = ("linear", "piecewise", "jitter")):
        """``(d_sample, d_line)`` of the model at MS image points (GDAL convention), MS pixels (METHODS §9)."""
        s, l = np.broadcast_arrays(np.asarray(sample, dtype=float), np.asarray(line, dtype=float))
        sn, ln = self._norm(s, l)
        out = [np.zeros(s.shape), np.zeros(s.shape)]
        if "linear" in terms:
            a = self.linear
            out[0] = out[0] + a[0] + a[1] * sn + a[2] * ln
            out[1] = out[1] + a[3] + a[4] * sn + a[5] * ln
        if "piecewise" in terms:
            # = piecewise_polynomial(s, breaks, 4, domain=(0, W)) @ coefficients, by Horner per point (the
            # appliers evaluate it at every MS pixel)
            ends = np.concatenate([[0.0], self.breaks, [float(self.ms_size[0])]])
            mid, half = 0.5 * (ends[1:] + ends[:-1]), 0.5 * (ends[1:] - ends[:-1])
            j = np.searchsorted(np.asarray(self.breaks), s, side="right")
            one = j.size > 0 and int(j.min()) == int(j.max())          # one piece (most tiles): scalars
            jj = int(j.flat[0]) if one else j
            u = (s - mid[jj]) / half[jj]
            for k in range(2):
                coef = self.piecewise[:, k, :]
                v = np.full(u.shape, coef[jj, ORDER]) if one else np.take(coef[:, ORDER], j)
                for p in range(ORDER - 1, -1, -1):
                    v *= u
                    v += coef[jj, p] if one else np.take(coef[:, p], j)
                out[k] = out[k] + v
        if "jitter" in terms:
            for k, ax in enumerate(AXES):
                comps = self.jitter[ax]["components"]
                if comps:
                    out[k] = out[k] + self._jitter_series(ax, l) * (1.0 + self.jitter[ax]["b"] * sn)
        return out[0], out[1]

    def _jitter_series(self, ax: str, l):
        """``sum_i (sin_i sin(2 pi f_i l) + cos_i cos(2 pi f_i l))`` (basis.trigonometric). Many points: from a
        table every MS line, linearly interpolated (the jitter is < 0.01 cycle per line: error < 1e-6 px)."""
        comps = self.jitter[ax]["components"]
        f = [c["frequency_cycles_per_line"] for c in comps]
        coef = np.ravel([(c["sin"], c["cos"]) for c in comps])
        if l.size < 20000 or not np.all(np.isfinite(l)) or max(f) > 0.02:
            return trigonometric(l, f) @ coef
        lo, hi = math.floor(float(l.min())) - 1, math.ceil(float(l.max())) + 2
        if hi - lo > l.size:
            return trigonometric(l, f) @ coef
        grid = np.arange(lo, hi, dtype=float)
        return np.interp(l, grid, trigonometric(grid, f) @ coef)

    def compatible_with(self, ms_size, breaks=None) -> None:
        """Refuse reuse on another camera: another MS width or sub-CCD layout (METHODS §9 reuse mode)."""
        if int(ms_size[0]) != self.ms_size[0]:
            raise PanMSError(f"the reuse model is for an MS image {self.ms_size[0]} px wide but this MS image is "
                             f"{int(ms_size[0])} px wide: reuse only a model of the same camera and product")
        if breaks is not None and (len(breaks) != len(self.breaks)
                                   or not np.allclose(sorted(breaks), self.breaks, atol=0.5)):
            raise PanMSError(f"the reuse model has sub-CCD edges {list(self.breaks)} but {list(breaks)} were "
                             "asked: reuse only a model of the same camera (drop --sub-ccds/--breaks)")

    # -- serialisation ------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"model": "gf4cal-panms", "version": 1, "mode": self.mode, "ms_size": list(self.ms_size),
                "n_sub_ccds": self.n_sub_ccds, "breaks_ms_px": list(self.breaks),
                "linear": dict(zip(["A1", "A2", "A3", "A4", "A5", "A6"], self.linear.tolist())),
                "piecewise": self.piecewise.tolist(), "jitter": self.jitter, "steps": self.steps,
                "info": self.info, "pixel_convention": "gdal",
                "definition": "delta = MS image point - (pan point -> pan RPC on the DEM -> MS RPC), MS px "
                              "(METHODS §9); s_n = (s - W/2)/(W/2), l_n = (l - H/2)/(H/2); linear: sample A1 + "
                              "A2 s_n + A3 l_n, line A4 + A5 s_n + A6 l_n; piecewise[k][axis][j] u_k^j, u_k = "
                              "(s - mid_k)/half_k over sub-CCD k between 0, breaks, W; jitter[axis]: (1 + b s_n) "
                              "sum (sin sin(2 pi f l) + cos cos(2 pi f l)), l in MS lines"}

    @classmethod
    def from_dict(cls, d: dict) -> "PanMSModel":
        if d.get("model") != "gf4cal-panms":
            raise PanMSError("not a pan-MS registration model (model.json of gf4cal register-pan-ms expected)")
        lin = d["linear"]
        return cls(ms_size=tuple(d["ms_size"]), breaks=tuple(d["breaks_ms_px"]),
                   linear=[lin[k] for k in ("A1", "A2", "A3", "A4", "A5", "A6")],
                   piecewise=np.asarray(d["piecewise"], float), jitter=d.get("jitter", {}),
                   steps=d.get("steps", []), mode=d.get("mode", "solve"), info=d.get("info", {}))

    def to_json(self, path) -> str:
        path = os.fspath(path)
        with open(path, "w") as fh:
            json.dump(self.to_dict(), fh, indent=1, default=_json_default)
        return path

    @classmethod
    def from_json(cls, path) -> "PanMSModel":
        try:
            with open(os.fspath(path)) as fh:
                d = json.load(fh)
        except (OSError, ValueError) as exc:
            raise PanMSError(f"cannot read the reuse model {path}: {exc}") from None
        return cls.from_dict(d)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


# ------------------------------------------------------------------------------------------- designs
def _linear_design(sn, ln) -> np.ndarray:
    """(n, 2, 6) design of ``A1..A6`` in the order A1 A2 A4 A5 (datum: constant and s) then A3 A6 (l)."""
    n = sn.size
    a = np.zeros((n, 2, 6))
    one = np.ones(n)
    a[:, 0, 0], a[:, 0, 1], a[:, 1, 2], a[:, 1, 3] = one, sn, one, sn
    a[:, 0, 4], a[:, 1, 5] = ln, ln
    return a


_LIN_ORDER = [0, 1, 3, 4, 2, 5]           # design column -> A index


def _piecewise_design(s, breaks, width) -> np.ndarray:
    """(n, 2, 2 m 5) design: sample-axis pieces then line-axis pieces."""
    b = piecewise_polynomial(s, breaks, ORDER, domain=(0.0, float(width)))
    n, q = b.shape
    a = np.zeros((n, 2, 2 * q))
    a[:, 0, :q], a[:, 1, q:] = b, b
    return a


def _blocks(m: int, keep=None):
    """The estimation blocks of the design columns (``keep``: the columns estimated, :func:`_term_layout`)."""
    names = ["A1", "A2", "A4", "A5", "A3", "A6"] + [f"{ax}_k{k + 1}_u{j}" for ax in AXES for k in range(m)
                                                    for j in range(ORDER + 1)]
    keep = np.ones(len(names), bool) if keep is None else np.asarray(keep, bool)
    names = [nm for nm, k in zip(names, keep) if k]
    groups = (("linear_datum", ("A1", "A2", "A4", "A5")), ("linear_time", ("A3", "A6")))
    out = [Block(g, tuple(nm for nm in names if nm in members)) for g, members in groups]
    out.append(Block("piecewise", tuple(nm for nm in names if nm[0] in "sl" and "_k" in nm)))
    return [b for b in out if b.names]


def _piece_orders(keep, m: int) -> List[int]:
    """Polynomial order estimated per sub-CCD (-1: none) from the kept design columns."""
    pw = np.asarray(keep[6:6 + m * (ORDER + 1)], bool).reshape(m, ORDER + 1)
    return [int(np.flatnonzero(r).max()) if r.any() else -1 for r in pw]


def _term_layout(sample, line, usable, breaks, width):
    """Which terms the usable cells support: ``(keep, notes)``, ``keep`` a mask over the design columns (linear
    A1 A2 A4 A5 A3 A6, then per axis and sub-CCD the ``u^0..u^4`` coefficients), ``notes`` one sentence per
    term dropped. A polynomial of order ``q`` in a sub-CCD needs usable cells in ``q + 2`` columns (one more than
    its coefficients, so that its fit is checked) and, beyond a straight line, cells over half the piece; the linear term's ``s`` / ``l`` slopes need two columns / rows;
    and all the terms together at least 2 observations more than parameters (two per cell)."""
    m = len(breaks) + 1
    s, l = np.asarray(sample, float)[usable], np.asarray(line, float)[usable]
    piece = np.searchsorted(np.asarray(breaks, float), s, side="right")
    n_cols = [np.unique(np.round(s[piece == k], 3)).size for k in range(m)]
    orders = [min(ORDER, n - 2) if n >= 2 else (0 if n == 1 else -1) for n in n_cols]
    # a polynomial is not extrapolated far beyond the columns its cells cover: below half the piece covered,
    # at most a straight line
    ends = np.r_[0.0, sorted(float(b) for b in breaks), float(width)]
    for k in range(m):
        sk = s[piece == k]
        if sk.size and orders[k] > 1:
            step = float(np.min(np.diff(np.unique(sk)))) if np.unique(sk).size > 1 else 0.0
            cover = (float(sk.max() - sk.min()) + step) / float(ends[k + 1] - ends[k])
            if cover < 0.5:
                orders[k] = 1
    notes = []
    lin = np.ones(6, bool)
    n_rows, n_all_cols = np.unique(np.round(l, 3)).size, np.unique(np.round(s, 3)).size
    if n_all_cols < 2:
        lin[[1, 3]] = False
        notes.append(f"usable cells in {n_all_cols} column: the linear term's sample slopes (A2, A5) are not "
                     "estimated")
    if n_rows < 2:
        lin[[4, 5]] = False
        notes.append(f"usable cells in {n_rows} row: the linear term's line slopes (A3, A6) are not estimated")
    n_obs = 2 * s.size

    def n_par():
        return int(lin.sum()) + 2 * sum(q + 1 for q in orders)
    while n_par() + 2 > n_obs and max(orders) >= 0:
        k = int(np.argmax(orders))
        orders[k] -= 1
    for k, (n, q) in enumerate(zip(n_cols, orders)):
        if q < ORDER:
            what = "no sub-CCD term" if q < 0 else f"order {q} instead of {ORDER}"
            notes.append(f"sub-CCD {k + 1} of {m}: usable cells in {n} column(s) ({s.size} cells in all): {what} "
                         "(the data cannot support more)")
    pw = np.zeros((m, ORDER + 1), bool)
    for k, q in enumerate(orders):
        pw[k, :q + 1] = True
    keep = np.concatenate([lin, pw.ravel(), pw.ravel()])
    return keep, notes


def _values(model: PanMSModel) -> np.ndarray:
    lin = model.linear[_LIN_ORDER]
    pw = np.concatenate([model.piecewise[:, 0, :].ravel(), model.piecewise[:, 1, :].ravel()])
    return np.concatenate([lin, pw])


def _set_values(model: PanMSModel, x: np.ndarray) -> None:
    lin = np.zeros(6)
    lin[_LIN_ORDER] = x[:6]
    model.linear = lin
    m = model.n_sub_ccds
    q = m * (ORDER + 1)
    model.piecewise = np.stack([x[6:6 + q].reshape(m, ORDER + 1), x[6 + q:6 + 2 * q].reshape(m, ORDER + 1)], axis=1)


# ------------------------------------------------------------------------------------------- statistics
def _row_series(l, r, w, n_rows: Optional[int] = None):
    """Weighted means of residuals ``r`` per cell row (``l`` value; binned when the cells are not on rows)."""
    ok = np.isfinite(r) & (w > 0)
    l, r, w = l[ok], r[ok], w[ok]
    if l.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    ul, inv = np.unique(np.round(l, 3), return_inverse=True)
    if ul.size > max(8, l.size // 3):
        nb = n_rows or max(8, int(math.sqrt(l.size)))
        edges = np.linspace(l.min(), l.max() + 1e-9, nb + 1)
        inv = np.clip(np.searchsorted(edges, l, side="right") - 1, 0, nb - 1)
        ul = 0.5 * (edges[1:] + edges[:-1])
    sw = np.bincount(inv, w, ul.size)
    keep = sw > 0
    y = np.bincount(inv, w * r, ul.size)[keep] / sw[keep]
    lc = np.bincount(inv, w * l, ul.size)[keep] / sw[keep]
    return lc, y, sw[keep]


def _freq_grid(lines, oversample: int = 10):
    span = float(lines.max() - lines.min()) if lines.size else 0.0
    if lines.size < 8 or span <= 0:
        return np.zeros(0), span
    dl = np.median(np.diff(np.sort(lines)))
    f_max = 0.45 / dl                 # short of Nyquist, where a sine fit on the rows is ill-conditioned
    f_min = 1.0 / span
    n = int(max(16, oversample * (f_max - f_min) * span))
    return np.linspace(f_min, f_max, n), span


def _sine_power(lines, y, w, freqs):
    """Weighted LS fit of ``c + a sin + b cos`` at each frequency: RSS reduction and amplitude (vectorised)."""
    ph = 2.0 * np.pi * freqs[:, None] * lines[None, :]
    S, C = np.sin(ph), np.cos(ph)
    one = np.ones_like(S)
    cols = np.stack([one, S, C], axis=-1)                     # (nf, n, 3)
    N = np.einsum("fni,n,fnj->fij", cols, w, cols)
    b = np.einsum("fni,n,n->fi", cols, w, y)
    x = np.linalg.solve(N + 1e-12 * np.eye(3), b[..., None])[..., 0]
    ym = np.sum(w * y) / np.sum(w)
    rss0 = np.sum(w * (y - ym) ** 2)
    rss1 = np.sum(w * y * y) - np.einsum("fi,fi->f", x, b)
    return rss0 - rss1, np.hypot(x[:, 1], x[:, 2]), rss0


def row_means(lines, residual):
    """``(lines, means)``: the residual's mean per cell row along the MS line (plots, METHODS §9)."""
    r = np.asarray(residual, float)
    lc, y, _ = _row_series(np.asarray(lines, float), r, np.isfinite(r).astype(float))
    return lc, y


def residual_spectrum(lines, residual, *, line_time_s: Optional[float] = None):
    """``(frequencies, amplitudes)`` of the residual row means: least-squares sine amplitude (px) per frequency
    (cycles per MS line, or Hz with ``line_time_s``)."""
    r = np.asarray(residual, float)
    lc, y, w = _row_series(np.asarray(lines, float), r, np.isfinite(r).astype(float))
    freqs, _ = _freq_grid(lc)
    if freqs.size == 0:
        return freqs, freqs
    _, amp, _ = _sine_power(lc, y, w, freqs)
    return (freqs / line_time_s if line_time_s else freqs), amp


def spectrum_peaks(lines, residual, weights, *, n_peaks: int = 3, line_time_s: Optional[float] = None):
    """The ``n_peaks`` largest peaks of the residual spectrum along the line (row means; METHODS §9)."""
    lc, y, sw = _row_series(np.asarray(lines, float), np.asarray(residual, float), np.asarray(weights, float))
    freqs, _ = _freq_grid(lc)
    if freqs.size == 0:
        return []
    gain, amp, _ = _sine_power(lc, y, sw, freqs)
    is_peak = np.r_[False, (gain[1:-1] >= gain[:-2]) & (gain[1:-1] >= gain[2:]), False]
    idx = np.flatnonzero(is_peak)
    idx = idx[np.argsort(gain[idx])[::-1][:n_peaks]]
    return [{"frequency_cycles_per_line": float(freqs[i]),
             "frequency_hz": float(freqs[i] / line_time_s) if line_time_s else None,
             "amplitude_px": float(amp[i])} for i in idx]


def _snapshot(model: PanMSModel, name: str, terms) -> dict:
    import copy
    return {"name": name, "terms": tuple(terms), "linear": model.linear.copy(),
            "piecewise": model.piecewise.copy(), "jitter": copy.deepcopy(model.jitter)}


def step_residuals(model: PanMSModel, snap: dict, sample, line, d_sample, d_line):
    """Residuals ``nabla - model`` (MS px) of the cells after one step (a :func:`_snapshot` of the model)."""
    m = PanMSModel(ms_size=model.ms_size, breaks=model.breaks, linear=snap["linear"], piecewise=snap["piecewise"],
                   jitter=snap["jitter"])
    ps, pl = m.predict(sample, line, terms=snap["terms"])
    return np.asarray(d_sample) - ps, np.asarray(d_line) - pl


def _step_stats(model, snap, c, inlier, line_time_s):
    rs, rl = step_residuals(model, snap, c["sample"], c["line"], c["d_sample"], c["d_line"])
    u = inlier & np.isfinite(rs) & np.isfinite(rl)
    w = u.astype(float)
    return {"step": snap["name"], "terms": list(snap["terms"]), "n_cells": int(u.sum()),
            "sample": axis_stats(rs[u]), "line": axis_stats(rl[u]),
            "rms_sample_px": axis_stats(rs[u])["rms"], "rms_line_px": axis_stats(rl[u])["rms"],
            "p_le_0.25": share_within(rs[u], rl[u], P_THRESHOLD_PX),
            "spectrum_peaks": {"sample": spectrum_peaks(c["line"], rs, w, line_time_s=line_time_s),
                               "line": spectrum_peaks(c["line"], rl, w, line_time_s=line_time_s)}}


# ------------------------------------------------------------------------------------------- estimation
def _cell_arrays(cells) -> dict:
    need = ("sample", "line", "d_sample", "d_line")
    missing = [c for c in need if c not in cells]
    if missing:
        raise PanMSError(f"the cell table lacks the columns {', '.join(missing)}")
    out = {c: np.asarray(cells[c], dtype=float) for c in need}
    n = out["sample"].size
    for c in ("sigma_sample", "sigma_line"):
        v = np.asarray(cells[c], dtype=float) if c in cells else np.full(n, np.nan)
        out[c] = np.where(np.isfinite(v) & (v > 0), v, np.nan)
    usable = np.asarray(cells["usable"], dtype=bool) if "usable" in cells else np.ones(n, bool)
    out["usable"] = usable & np.isfinite(out["d_sample"]) & np.isfinite(out["d_line"])
    return out


def _weights(c) -> np.ndarray:
    sig = np.stack([c["sigma_sample"], c["sigma_line"]], axis=1)
    med = np.nanmedian(sig) if np.isfinite(sig).any() else 1.0
    sig = np.where(np.isfinite(sig), np.maximum(sig, 0.25 * med), med)
    return np.where(c["usable"][:, None], 1.0 / sig ** 2, 0.0)


def _robust_step(a, y, w, usable, blocks, frozen, values, hint):
    y = np.where(np.isfinite(y), y, 0.0)
    return robust_lsq(a, y, w, blocks=blocks, frozen=frozen, values=values, candidates=usable, hint=hint,
                      n_subsets=200)


def estimate(cells, *, ms_size, breaks=None, n_sub_ccds: int = 3, jitter="auto", reuse=None,
             line_time_s: float = GF7_MS_LINE_TIME_S, look_time_s: float = GF7_LOOK_TIME_S,
             ifov_rad: float = GF7_MS_IFOV_RAD, progress=None) -> PanMSModel:
    """Solve METHODS §9's pan-MS registration model from cell observations, stepwise (eqs. 14-16) or in reuse
    mode (eq. 17).

    Parameters
    ----------
    cells : DataFrame or mapping of arrays
        ``sample, line`` (MS cell centre, GDAL convention), ``d_sample, d_line`` (nabla, MS px), optional
        ``sigma_sample, sigma_line`` (weights ``1/sigma^2``) and ``usable`` (cells mostly cloud/water/texture-less
        are left out of the estimate but keep their residuals).
    ms_size : (width, height) of the MS image.
    breaks : list of MS samples of the sub-CCD edges; default ``n_sub_ccds`` equal pieces of the MS width.
    jitter : ``"auto"`` (components while significant, false-alarm probability < 1e-3), ``"none"`` or an int
        (exactly that many per axis).
    reuse : :class:`PanMSModel` or path of its JSON: keep its piecewise term, solve only the linear term.
    line_time_s, look_time_s, ifov_rad : MS line period, pan-MS look-time difference and MS IFOV, to report the
        jitter in Hz and the attitude jitter it implies (gain ``2 |sin(pi f dt)|``).

    Returns
    -------
    PanMSModel
        ``steps``: per step RMS per axis about zero, P(<= 0.25 px) over usable cells, residual spectrum peaks.

    Raises
    ------
    PanMSError
        No usable cell, a reuse model of another camera, bad breakpoints.
    """
    c = _cell_arrays(cells)
    W, H = int(ms_size[0]), int(ms_size[1])
    if reuse is not None and not isinstance(reuse, PanMSModel):
        reuse = PanMSModel.from_json(reuse)
    if reuse is not None:
        reuse.compatible_with((W, H), breaks)
        breaks = list(reuse.breaks)
    if breaks is None:
        breaks = default_breaks(W, n_sub_ccds)
    breaks = sorted(float(b) for b in breaks)
    if any(not (0.0 < b < W) for b in breaks):
        raise PanMSError(f"sub-CCD breakpoints {breaks} must lie inside the MS image (0..{W} px)")
    usable = c["usable"]
    n_use = int(usable.sum())
    n_all = usable.size
    if n_use == 0:
        raise PanMSError(f"no usable cell: all {n_all} cells are cloud, water or texture-less; register a clearer "
                         "scene and reuse its model with --reuse MODEL.json")
    w = _weights(c)
    model = PanMSModel(ms_size=(W, H), breaks=tuple(breaks), mode="solve" if reuse is None else "reuse")
    model.info = {"n_cells": n_all, "n_usable": n_use, "line_time_s": line_time_s, "look_time_s": look_time_s,
                  "ifov_rad": ifov_rad,
                  "noise_floor_px": {"sample": _floor(c["sigma_sample"][usable]),
                                     "line": _floor(c["sigma_line"][usable])}}
    y = np.stack([c["d_sample"], c["d_line"]], axis=1)
    sn, ln = model._norm(c["sample"], c["line"])
    m = model.n_sub_ccds
    a = np.concatenate([_linear_design(sn, ln), _piecewise_design(c["sample"], breaks, W)], axis=2)
    blocks = _blocks(m)
    snaps = [_snapshot(model, "before", ())]
    report(progress, 0.05, "pan-MS: linear term")
    if reuse is not None:
        model.piecewise = reuse.piecewise.copy()
        est = _robust_step(a, y, w, usable, blocks, ["piecewise"], _values(model),
                           " (reuse mode: the linear term from the sparse cells)")
        _set_values(model, est.x)
        model.info["reused_from"] = reuse.info.get("source", "")
        snaps.append(_snapshot(model, "linear (reuse: piecewise term of the reused model)", ("linear", "piecewise")))
        model = _finish(model, c, snaps, est.outlier, line_time_s, progress)
        _check_reuse_fit(model)
        return model
    keep, notes = _term_layout(c["sample"], c["line"], usable, breaks, W)
    model.info["notes"] = notes
    model.info["piece_orders"] = _piece_orders(keep, m)
    a = a[:, :, keep]
    blocks = _blocks(m, keep)
    x_full = np.zeros(keep.size)

    def put(x):
        x_full[keep] = x
        _set_values(model, x_full)
    # Blunders first, on the model that fits (linear + piecewise, robust: high-breakdown start + snooping), so
    # that the sub-CCD structure the linear step cannot model is not mistaken for blunders.
    yy = np.where(np.isfinite(y), y, 0.0)
    if n_use >= a.shape[2] // 2 + 3:
        est = _robust_step(a, y, w, usable, blocks, ["linear_datum"], np.zeros(a.shape[2]), " (blunder detection)")
        outlier = est.outlier
    else:
        outlier = np.zeros(n_all, bool)
        notes.append(f"{n_use} usable cells for {a.shape[2] // 2} parameters per axis: too few to test for blunders")
    w_in = np.where((usable & ~outlier)[:, None], w, 0.0)
    # Step 1 (eq. 14): linear on all cells (usable, not blunders).
    n_lin = int(keep[:6].sum())
    est = weighted_lsq(a[:, :, :n_lin].reshape(-1, n_lin), yy.ravel(), w_in.ravel(), blocks=_blocks(0, keep[:6]),
                       hint=" (linear term)")
    put(np.r_[est.x, np.zeros(a.shape[2] - n_lin)])
    snaps.append(_snapshot(model, "linear", ("linear",)))
    report(progress, 0.3, "pan-MS: piecewise term")
    # Step 2 (eq. 15): piecewise on what remains; the linear datum (constant, s) stays frozen (the pieces'
    # constant and linear terms duplicate it), the l terms are refined with it.
    if any(b.name != "linear_datum" for b in blocks):
        est = weighted_lsq(a.reshape(-1, a.shape[2]), yy.ravel(), w_in.ravel(), blocks=blocks,
                           frozen=["linear_datum"], values=_values(model)[keep], hint=" (piecewise term)")
        put(est.x)
    snaps.append(_snapshot(model, "piecewise", ("linear", "piecewise")))
    # Step 3 (eq. 16): jitter on what remains.
    report(progress, 0.6, "pan-MS: jitter term")
    if str(jitter) != "none":
        n_fixed = None if str(jitter) == "auto" else int(jitter)
        inl = usable & ~outlier
        _solve_jitter(model, c, a, y, w, inl, blocks, n_fixed, sn, keep)
        _describe_jitter(model, line_time_s, look_time_s, ifov_rad)
        snaps.append(_snapshot(model, "jitter", ("linear", "piecewise", "jitter")))
    return _finish(model, c, snaps, outlier, line_time_s, progress)


def _finish(model, c, snaps, outlier, line_time_s, progress):
    """Step statistics over the same cells (usable, not flagged as blunders by the last robust step)."""
    inlier = c["usable"] & ~outlier
    model.steps = [_step_stats(model, sn, c, inlier, line_time_s) for sn in snaps]
    model.info["n_outliers"] = int(np.sum(outlier & c["usable"]))
    model.cell_outlier = outlier
    model.snapshots = snaps
    report(progress, 1.0, "pan-MS: model solved")
    return model


def _check_reuse_fit(model) -> None:
    """Reuse mode (METHODS §9 eq. 17) refuses a model that does not fit: the sparse cells' RMS after the linear
    term must stay within ``REUSE_MAX_FLOOR_RATIO`` x their noise floor or below ``REUSE_MAX_RMS_PX``, with at
    most ``REUSE_MAX_OUTLIER_SHARE`` of them rejected as blunders (else the robust fit kept the half that fits,
    as on scene seed 14 / camera 21 with scene seed 11 / camera 9's model). A model of another camera of the
    same design (same size and layout, other sub-CCD truth) otherwise passes every layout
    check and leaves ~0.2 px with P(<= 0.25 px) ~ 55 %."""
    st, fl = model.steps[-1], model.info["noise_floor_px"]
    n_out, n_use = model.info["n_outliers"], model.info["n_usable"]
    if n_out > REUSE_MAX_OUTLIER_SHARE * n_use:
        raise PanMSError(f"the reuse model does not fit this scene: {n_out} of {n_use} cells rejected as blunders; "
                         "reuse only a model of the same camera, or register this scene without --reuse")
    for ax in AXES:
        rms, floor = st[f"rms_{ax}_px"], fl.get(ax)
        if rms > REUSE_MAX_RMS_PX and (floor is None or rms > REUSE_MAX_FLOOR_RATIO * floor):
            raise PanMSError(f"the reuse model does not fit this scene: {ax} RMS {rms:.3f} px after the linear "
                             f"term (cell noise {floor or float('nan'):.3f} px); reuse only a model of the same "
                             "camera, or register this scene without --reuse")


def _floor(sig) -> Optional[float]:
    sig = sig[np.isfinite(sig)]
    return float(np.sqrt(np.mean(sig ** 2))) if sig.size else None


def _within_row_variance(lines, r, w):
    """Reduced chi-square of the cells about their row means (weights ``w``), and its degrees of freedom; None
    when the cells are not on rows with several cells each."""
    ok = np.isfinite(r) & (w > 0)
    l, r, w = lines[ok], r[ok], w[ok]
    ul, inv = np.unique(np.round(l, 3), return_inverse=True)
    dof = l.size - ul.size
    if ul.size < 8 or dof < 2 * ul.size:
        return None, 0
    ym = np.bincount(inv, w * r, ul.size) / np.bincount(inv, w, ul.size)
    return float(np.sum(w * (r - ym[inv]) ** 2) / dof), dof


def _select_frequencies(lines, r, w, n_fixed):
    """Greedy: strongest peak of the residual's row spectrum, refined, kept while significant (F-test with a
    false-alarm probability over the independent frequencies searched) or exactly ``n_fixed``."""
    from scipy import optimize, stats
    lc, y, sw = _row_series(lines, r, w)
    freqs, span = _freq_grid(lc)
    s2, dof = _within_row_variance(lines, r, w)
    chosen: List[float] = []
    if freqs.size == 0:
        return chosen
    n_indep = max(1.0, (freqs[-1] - freqs[0]) * span)
    limit = MAX_JITTER_COMPONENTS if n_fixed is None else int(n_fixed)
    df = freqs[1] - freqs[0]

    def design(fs):
        return np.stack([np.ones_like(lc)] + [g(2 * np.pi * f * lc) for f in fs for g in (np.sin, np.cos)], axis=1)

    def rss(fs):
        A = design(fs)
        v = (y - A @ normal_solve(A, y, sw)[0]) * np.sqrt(sw)
        return float(v @ v)

    while len(chosen) < limit:
        p1 = 1 + 2 * (len(chosen) + 1) + len(chosen) + 1
        if lc.size - p1 < 3:
            break
        base = rss(chosen)
        A = design(chosen)
        resid = y - A @ normal_solve(A, y, sw)[0]
        gain, _, _ = _sine_power(lc, resid, sw, freqs)
        f0 = float(freqs[int(np.argmax(gain))])
        opt = optimize.minimize_scalar(lambda f: rss(chosen + [f]), bounds=(max(freqs[0], f0 - 2 * df),
                                                                             min(freqs[-1], f0 + 2 * df)),
                                    method="bounded")
        f_new = float(opt.x)
        new = rss(chosen + [f_new])
        if n_fixed is None:
            # the noise of the row means from the cells' scatter within their rows (not from the rows left
            # over, which on a short crop -- 12 rows, < 1 jitter cycle -- still hold the next components' signal)
            if s2 is not None:
                F, dof2 = ((base - new) / 3.0) / s2, dof
            else:
                F, dof2 = ((base - new) / 3.0) / (new / (lc.size - p1)), lc.size - p1
            p = float(stats.f.sf(F, 3, dof2))
            fap = 1.0 - (1.0 - p) ** n_indep if p > 1e-12 else p * n_indep
            if fap >= JITTER_FAP:
                break
        if chosen and min(abs(f_new - f) for f in chosen) < 0.5 / span:
            break                     # not resolved from a component already taken
        chosen.append(f_new)
        if len(chosen) > 1:           # joint refinement of every frequency, kept inside the searched band
            lo, hi = freqs[0], freqs[-1]
            res = optimize.minimize(lambda fs: rss(list(np.clip(fs, lo, hi))), np.array(chosen),
                                    method="Nelder-Mead", options={"xatol": df * 1e-3, "fatol": 1e-12,
                                                                   "maxiter": 400})
            refined = sorted(float(v) for v in np.clip(res.x, lo, hi))
            if np.min(np.diff(refined)) < 0.5 / span or refined[0] <= lo or refined[-1] >= hi:
                chosen.pop()          # the refinement merged two components or ran to the band's edge: stop
                break
            chosen = refined
    return chosen


def _jitter_design(model, l, sn):
    """(n, 2, q) design of the jitter amplitudes with the current frequencies and B."""
    n = l.size
    parts = []
    for k, ax in enumerate(AXES):
        f = [cc["frequency_cycles_per_line"] for cc in model.jitter[ax]["components"]]
        if not f:
            continue
        t = trigonometric(l, f, s=sn, b=model.jitter[ax]["b"])
        blk = np.zeros((n, 2, t.shape[1]))
        blk[:, k, :] = t
        parts.append(blk)
    return np.concatenate(parts, axis=2) if parts else np.zeros((n, 2, 0))


def _solve_jitter(model, c, a, y, w, inl, blocks, n_fixed, sn, keep):
    ps, pl = model.predict(c["sample"], c["line"], terms=("linear", "piecewise"))
    res = np.stack([c["d_sample"] - ps, c["d_line"] - pl], axis=1)
    for k, ax in enumerate(AXES):
        fs = _select_frequencies(c["line"], res[:, k], np.where(inl, w[:, k], 0.0), n_fixed)
        model.jitter[ax] = {"b": 0.0, "components": [{"frequency_cycles_per_line": f, "sin": 0.0, "cos": 0.0}
                                                     for f in fs]}
    if not any(model.jitter[ax]["components"] for ax in AXES):
        return
    yy = np.where(np.isfinite(y), y, 0.0)
    ww = np.where(inl[:, None], w, 0.0)
    done = 0
    while done < 3:                            # amplitudes (with the l terms and pieces refined), then B
        aj = _jitter_design(model, c["line"], sn)
        full = np.concatenate([a, aj], axis=2)
        names = tuple(f"{ax}_{i}_{g}" for ax in AXES for i, _ in enumerate(model.jitter[ax]["components"])
                      for g in ("sin", "cos"))
        bl = blocks + [Block("jitter", names)]
        try:
            est = weighted_lsq(full.reshape(-1, full.shape[2]), yy.ravel(), ww.ravel(), blocks=bl,
                               frozen=["linear_datum"],
                               values=np.concatenate([_values(model)[keep], np.zeros(len(names))]),
                               hint=" (jitter term)")
        except DegenerateGeometryError:
            # a component the design cannot separate (from the l terms or another one): drop the last one found
            # on the axis with the most components and solve again
            ax = max(AXES, key=lambda x_: len(model.jitter[x_]["components"]))
            model.jitter[ax]["components"].pop()
            if not any(model.jitter[a]["components"] for a in AXES):
                return
            continue
        p0 = a.shape[2]
        x_full = np.zeros(keep.size)
        x_full[keep] = est.x[:p0]
        _set_values(model, x_full)
        xj = est.x[p0:]
        i = 0
        for ax in AXES:
            for comp in model.jitter[ax]["components"]:
                comp["sin"], comp["cos"] = float(xj[i]), float(xj[i + 1])
                i += 2
        ps, pl = model.predict(c["sample"], c["line"], terms=("linear", "piecewise"))
        # cells left out (weight 0) have no nabla (NaN): 0 * NaN would make B, then the whole design, NaN
        res = np.where(ww > 0, yy - np.stack([ps, pl], axis=1), 0.0)
        for k, ax in enumerate(AXES):
            comps = model.jitter[ax]["components"]
            if not comps:
                continue
            f = [cc["frequency_cycles_per_line"] for cc in comps]
            j0 = trigonometric(c["line"], f) @ np.ravel([(cc["sin"], cc["cos"]) for cc in comps])
            g = sn * j0
            num = np.sum(ww[:, k] * g * (res[:, k] - j0))
            den = np.sum(ww[:, k] * g * g)
            b = float(num / den) if den > 0 else 0.0
            model.jitter[ax]["b"] = b if math.isfinite(b) else 0.0
        done += 1


def _describe_jitter(model, line_time_s, look_time_s, ifov_rad):
    """Each component's amplitude, phase, frequency in Hz and the attitude jitter it implies (METHODS §9:
    a(t) - a(t - dt) has gain ``2 |sin(pi f dt)|``)."""
    for ax in AXES:
        for comp in model.jitter[ax]["components"]:
            amp = math.hypot(comp["sin"], comp["cos"])
            comp["amplitude_px"] = amp
            comp["phase_rad"] = math.atan2(comp["cos"], comp["sin"])
            if line_time_s:
                f_hz = comp["frequency_cycles_per_line"] / line_time_s
                gain = 2.0 * abs(math.sin(math.pi * f_hz * look_time_s)) if look_time_s else float("nan")
                comp["frequency_hz"] = f_hz
                comp["gain"] = gain
                comp["attitude_amplitude_px"] = amp / gain if gain > 1e-9 else None
                comp["attitude_amplitude_urad"] = (amp / gain * ifov_rad * 1e6
                                                   if gain > 1e-9 and ifov_rad else None)


# ---------------------------------------------------------------------------------------------- appliers
def _tiles(W: int, H: int, tile: int) -> List[Tuple[int, int, int, int]]:
    """``(x0, y0, w, h)`` of the ``tile`` x ``tile`` blocks of a ``W`` x ``H`` grid, row by row."""
    return [(x0, y0, min(tile, W - x0), min(tile, H - y0)) for y0 in range(0, H, tile) for x0 in range(0, W, tile)]


def write_correction(model: PanMSModel, path, *, tile: int = 512, progress=None, rpc=None,
                     band_models: Optional[Dict[str, PanMSModel]] = None) -> str:
    """Write ``correction.tif``: float32 bands delta sample / delta line (MS px) at every MS pixel centre (GDAL
    convention), on the MS image grid as given, tile by tile (METHODS §9): the model's, then a pair per entry of
    ``band_models`` (``{label: model}``: bands with their own correction). ``rpc``: the MS image's RPC, written in
    the RPC metadata domain (no geotransform) so that GDAL and QGIS place the grid on the ground."""
    from osgeo import gdal
    from ._gdal import gdal_exceptions
    W, H = model.ms_size
    path = os.fspath(path)
    pairs = [("", model)] + [(f" {k}", m) for k, m in (band_models or {}).items()]
    with gdal_exceptions():
        ds = gdal.GetDriverByName("GTiff").Create(path, W, H, 2 * len(pairs), gdal.GDT_Float32, [
            "TILED=YES", f"BLOCKXSIZE={tile}", f"BLOCKYSIZE={tile}", "COMPRESS=DEFLATE", "PREDICTOR=3",
            "BIGTIFF=IF_SAFER", "INTERLEAVE=BAND"])
        for i, (label, _) in enumerate(pairs):
            ds.GetRasterBand(2 * i + 1).SetDescription(f"delta_sample_ms_px{label}")
            ds.GetRasterBand(2 * i + 2).SetDescription(f"delta_line_ms_px{label}")
        ds.SetMetadataItem("GF4CAL_PANMS", "delta = MS image point - pan/DEM/MS-RPC prediction (METHODS §9), MS "
                           "pixels, at MS pixel centres, GDAL convention")
        if rpc is not None:
            ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
        tiles = _tiles(W, H, tile)
        for done, (x0, y0, w, h) in enumerate(tiles, start=1):
            s, l = np.meshgrid(x0 + np.arange(w) + 0.5, y0 + np.arange(h) + 0.5)
            for i, (_, m) in enumerate(pairs):
                ds_, dl_ = m.predict(s, l)
                ds.GetRasterBand(2 * i + 1).WriteArray(ds_.astype(np.float32), x0, y0)
                ds.GetRasterBand(2 * i + 2).WriteArray(dl_.astype(np.float32), x0, y0)
            report(progress, done / len(tiles), f"correction.tif tile {done}/{len(tiles)}")
        ds.FlushCache()
        ds = None
    return path


def _predicted_grid(pan_rpc, ms_rpc, dem, ratio, x0, y0, w, h, step):
    """MS points ``p''`` predicted for the ms_on_pan pixels ``[x0, x0+w) x [y0, y0+h)``: pan pixel centre ->
    pan RPC on the DEM -> MS RPC, on a coarse node grid (every ``step`` px) interpolated bilinearly (the mapping
    is smooth; the pan-MS ray angle makes the DEM's fine structure negligible, METHODS §9)."""
    from scipy import ndimage
    xs = np.unique(np.r_[np.arange(x0, x0 + w, step), x0 + w]).astype(float)
    ys = np.unique(np.r_[np.arange(y0, y0 + h, step), y0 + h]).astype(float)
    X, Y = np.meshgrid(xs, ys)
    lon, lat, hh = pan_rpc.localize_dem(X * ratio, Y * ratio, dem)
    s2, l2 = ms_rpc.project(lon, lat, hh)
    # fractional node index of every pixel centre (nodes are regular but for the last one)
    fx = np.interp(x0 + np.arange(w) + 0.5, xs, np.arange(xs.size))
    fy = np.interp(y0 + np.arange(h) + 0.5, ys, np.arange(ys.size))
    FY, FX = np.meshgrid(fy, fx, indexing="ij")
    return tuple(ndimage.map_coordinates(np.asarray(v, float), [FY, FX], order=1, mode="nearest")
                 for v in (s2, l2))


def resample_ms_on_pan(model, pan_path, ms_path, path, *, pan_rpc, ms_rpc, dem, ratio: int,
                       tile: int = 512, node_step: int = 8, progress=None, band_names=None) -> str:
    """Write ``ms_on_pan.tif``: every MS band resampled onto the pan's raw grid at MS resolution (pan size /
    ``ratio``, same extent as the pan) so that ``gdal_pansharpen.py PAN ms_on_pan.tif fused.tif`` fuses without
    halos (METHODS §9). Output pixel ``(x, y)`` covers pan pixels ``[x r, (x+1) r)``: its centre, localised with
    the pan RPC on the DEM and projected with the MS RPC, is ``p''``; the MS shows that ground at ``p' = p'' +
    delta(p')`` (fixed point, 2 iterations: the field's gradient is ~1e-4 px/px), sampled bicubically. ``model``:
    one :class:`PanMSModel` for every band, a list of one per band, or None (through the RPCs only: the
    uncorrected product). The grid covers the pan's extent (``ceil(size / ratio)``). ``band_names``: per band
    ``(description, GDAL colour interpretation)`` (default: the MS file's, Alpha never). Tile by tile, each tile
    reads only its MS window."""
    from osgeo import gdal
    from ._gdal import gdal_exceptions
    path = os.fspath(path)
    with gdal_exceptions():
        pan = gdal.Open(os.fspath(pan_path))
        ms = gdal.Open(os.fspath(ms_path))
        PW, PH = pan.RasterXSize, pan.RasterYSize
        MW, MH, nb = ms.RasterXSize, ms.RasterYSize, ms.RasterCount
        W, H = -(-PW // ratio), -(-PH // ratio)
        models = list(model) if isinstance(model, (list, tuple)) else [model] * nb
        dt = ms.GetRasterBand(1).DataType
        out = gdal.GetDriverByName("GTiff").Create(path, W, H, nb, dt, [
            "TILED=YES", f"BLOCKXSIZE={tile}", f"BLOCKYSIZE={tile}", "COMPRESS=DEFLATE", "INTERLEAVE=BAND",
            "BIGTIFF=IF_SAFER"])
        nodata = ms.GetRasterBand(1).GetNoDataValue()
        fill = 0.0 if nodata is None else nodata
        for b in range(nb):
            ob = out.GetRasterBand(b + 1)
            ob.SetNoDataValue(fill)
            if band_names is not None:
                desc, ci = band_names[b]
            else:
                desc, ci = ms.GetRasterBand(b + 1).GetDescription(), ms.GetRasterBand(b + 1).GetColorInterpretation()
                ci = gdal.GCI_Undefined if ci == gdal.GCI_AlphaBand else ci
            ob.SetDescription(desc)
            ob.SetColorInterpretation(ci)
        out.SetMetadataItem("GF4CAL_PANMS", f"MS resampled onto the pan raw grid at 1/{ratio} of its size "
                            f"({'pan-MS registration model applied' if models[0] else 'RPCs only'}; METHODS §9)")
        _set_ms_on_pan_rpc(out, pan, ratio, pan_rpc)
        tiles = _tiles(W, H, tile)
        for done, (x0, y0, w, h) in enumerate(tiles, start=1):
            s2, l2 = _predicted_grid(pan_rpc, ms_rpc, dem, ratio, x0, y0, w, h, node_step)
            arrs = [np.full((h, w), fill, dtype=np.float64) for _ in range(nb)]
            done_models: dict = {}
            for b in range(nb):
                key = id(models[b])
                if key not in done_models:
                    done_models[key] = _apply_model(models[b], s2, l2)
                sp, lp = done_models[key]
                _sample_band(ms, b, sp, lp, MW, MH, arrs[b])
            for b in range(nb):
                a = arrs[b]
                if np.issubdtype(_np_dtype(dt), np.integer):
                    info = np.iinfo(_np_dtype(dt))
                    a = np.clip(np.round(a), max(info.min, 1 if nodata == 0 else info.min), info.max)
                    a = np.where(np.isfinite(arrs[b]) & (arrs[b] != fill), a, fill)
                out.GetRasterBand(b + 1).WriteArray(a.astype(_np_dtype(dt)), x0, y0)
            report(progress, done / len(tiles), f"ms_on_pan.tif tile {done}/{len(tiles)}")
        out.FlushCache()
        out = None
    return path


def _np_dtype(gdal_type):
    from osgeo import gdal_array
    return np.dtype(gdal_array.GDALTypeCodeToNumericTypeCode(gdal_type))


def _apply_model(model, s2, l2):
    """``p' = p'' + delta(p')`` by fixed point (2 iterations); ``p''`` itself when ``model`` is None."""
    sp, lp = s2.copy(), l2.copy()
    if model is not None:
        for _ in range(2):
            ds_, dl_ = model.predict(sp, lp)
            sp, lp = s2 + ds_, l2 + dl_
    return sp, lp


def _sample_band(ms, b, sp, lp, MW, MH, into, margin: int = 3) -> None:
    """Bicubic samples of MS band ``b`` (0-based) at ``(sp, lp)`` (GDAL convention) into ``into`` where inside,
    reading only the window they need."""
    from scipy import ndimage
    ok = np.isfinite(sp) & np.isfinite(lp)
    inside = ok & (sp >= 0) & (sp <= MW) & (lp >= 0) & (lp <= MH)
    if not inside.any():
        return
    wx0 = int(max(0, math.floor(np.min(sp[inside])) - margin))
    wy0 = int(max(0, math.floor(np.min(lp[inside])) - margin))
    wx1 = int(min(MW, math.ceil(np.max(sp[inside])) + margin))
    wy1 = int(min(MH, math.ceil(np.max(lp[inside])) + margin))
    if wx1 <= wx0 or wy1 <= wy0:
        return
    src = ms.GetRasterBand(b + 1).ReadAsArray(wx0, wy0, wx1 - wx0, wy1 - wy0)
    into[inside] = ndimage.map_coordinates(src.astype(np.float64), [lp[inside] - 0.5 - wy0, sp[inside] - 0.5 - wx0],
                                           order=3, mode="nearest", prefilter=True)


def _set_ms_on_pan_rpc(out, pan, ratio, pan_rpc=None):
    """Give ms_on_pan the pan's RPC (``pan_rpc``: the RPC of the pan's own pixels, e.g. a crop's shifted product
    RPC; else the pan file's) rescaled to its grid (GDAL: x_out = x_pan / r, i.e. RPC convention
    ``(x + 0.5) / r - 0.5``), and the pan's geotransform scaled by ``r`` when the pan has a map georeference
    (a pixel-unit geotransform without CRS -- a crop's origin in its product -- is not one: QGIS would place the
    image at pixel coordinates instead of through the RPC)."""
    md = dict(pan_rpc.to_gdal_metadata()) if hasattr(pan_rpc, "to_gdal_metadata") else pan.GetMetadata("RPC")
    if md:
        md = dict(md)
        for off, scale in (("SAMP_OFF", "SAMP_SCALE"), ("LINE_OFF", "LINE_SCALE")):
            md[off] = repr((float(md[off]) + 0.5) / ratio - 0.5)
            md[scale] = repr(float(md[scale]) / ratio)
        out.SetMetadata(md, "RPC")
    gt = pan.GetGeoTransform(can_return_null=True)
    srs = pan.GetSpatialRef()
    if gt is not None and srs is not None and not srs.IsLocal():
        out.SetGeoTransform((gt[0], gt[1] * ratio, gt[2] * ratio, gt[3], gt[4] * ratio, gt[5] * ratio))
        out.SetProjection(pan.GetProjection())


def approximate_rpc(model: PanMSModel, ms_rpc, *, n: int = 41, n_heights: int = 7,
                    terms: Sequence[str] = ("linear", "piecewise", "jitter")):
    """Refit the MS RPC so that it predicts ``p' = p'' + delta(p')`` (METHODS §9): a smooth approximation of
    the model, which an RPC cannot carry exactly (the sub-CCD jumps). Returns ``(rpc, errors)`` with the refit's
    RMS and max error (MS px) against the full model on an ``n x n`` grid x ``n_heights`` heights. ``terms``: the
    model terms the RPC is fitted to (the errors are always against the full model)."""
    from .rpc_fit import fit_rpc
    W, H = model.ms_size
    s, l = np.meshgrid((np.arange(n) + 0.5) * W / n, (np.arange(n) + 0.5) * H / n)
    s, l = s.ravel(), l.ravel()
    h0, h1 = ms_rpc.height_range
    lons, lats, hs, ss, ls = [], [], [], [], []
    ds_, dl_ = model.predict(s, l, terms=terms)
    for h in np.linspace(h0, h1, n_heights):
        lon, lat = ms_rpc.localize(s - ds_, l - dl_, np.full(s.shape, h))
        lons.append(lon), lats.append(lat), hs.append(np.full(s.shape, h)), ss.append(s), ls.append(l)
    lon, lat, hh, S, L = (np.concatenate(v) for v in (lons, lats, hs, ss, ls))
    ok = np.isfinite(lon) & np.isfinite(lat)
    rpc, fit = fit_rpc(lon[ok], lat[ok], hh[ok], S[ok], L[ok])
    ps, pl = rpc.project(lon[ok], lat[ok], hh[ok])
    es, el = S[ok] - ps, L[ok] - pl
    if tuple(terms) != ("linear", "piecewise", "jitter"):       # errors against the full model
        fs, fl = model.predict(s, l)
        ks, kl = model.predict(s, l, terms=terms)
        es = es + np.tile(fs - ks, n_heights)[ok]
        el = el + np.tile(fl - kl, n_heights)[ok]
    r = np.hypot(es, el)
    errors = {"rms_sample_px": float(np.sqrt(np.mean(es ** 2))), "rms_line_px": float(np.sqrt(np.mean(el ** 2))),
              "rms_px": float(np.sqrt(np.mean(r ** 2))), "max_px": float(np.max(r)), "n_points": int(ok.sum()),
              "note": "an RPC cannot carry the sub-CCD jumps: use correction.tif / ms_on_pan.tif for the exact "
                      "registration (METHODS §9)"}
    return rpc, errors


def edge_misregistration(pan_path, image_path, *, band: int = 1, ratio: int = 4, window: int = 64,
                         region=None, min_ncc: float = 0.5) -> dict:
    """Measured misregistration (MS px) of an image on the pan's grid (``ms_on_pan.tif`` at 1/``ratio``, or a
    fused product at the pan's size) against the pan's edges (METHODS §9's halos): both are reduced to MS
    resolution (block means), cut into ``window`` x ``window`` MS-px windows and phase-correlated; returns the
    mean and RMS per axis and the planar RMS of the window shifts (``image`` minus pan), over windows whose
    correlation ``ncc >= min_ncc`` (textured, cloud-free). ``region = (x0, y0, w, h)`` in MS px limits it."""
    from osgeo import gdal
    from ._gdal import gdal_exceptions
    from .matching.correlate import block_reduce, phase_correlate
    with gdal_exceptions():
        pan = gdal.Open(os.fspath(pan_path))
        img = gdal.Open(os.fspath(image_path))
        W, H = pan.RasterXSize // ratio, pan.RasterYSize // ratio
        x0, y0, w, h = region if region is not None else (0, 0, W, H)
        p = block_reduce(pan.GetRasterBand(1).ReadAsArray(x0 * ratio, y0 * ratio, w * ratio, h * ratio), ratio)
        f = img.RasterXSize // W
        a = img.GetRasterBand(band).ReadAsArray(x0 * f, y0 * f, w * f, h * f)
        m = block_reduce(a, f) if f > 1 else a.astype(np.float64)
    ny, nx = h // window, w // window
    if nx == 0 or ny == 0:
        raise PanMSError(f"the region is smaller than one {window} px window")
    cut = (slice(0, ny * window), slice(0, nx * window))

    def stack(v):
        return v[cut].reshape(ny, window, nx, window).transpose(0, 2, 1, 3).reshape(-1, window, window)
    r = phase_correlate(stack(p), stack(m))
    ok = np.isfinite(r.dx) & np.isfinite(r.dy) & (r.ncc >= min_ncc)
    dx, dy = r.dx[ok], r.dy[ok]
    return {"n_windows": int(ok.sum()), "mean_sample_px": float(np.mean(dx)) if dx.size else None,
            "mean_line_px": float(np.mean(dy)) if dy.size else None,
            "rms_sample_px": float(np.sqrt(np.mean(dx ** 2))) if dx.size else None,
            "rms_line_px": float(np.sqrt(np.mean(dy ** 2))) if dy.size else None,
            "rms_px": float(np.sqrt(np.mean(dx ** 2 + dy ** 2))) if dx.size else None}
