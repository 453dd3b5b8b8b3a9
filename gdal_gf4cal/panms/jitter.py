"""The jitter term of the pan-MS model (METHODS §9 eq. 16): frequencies picked from the residual's row
spectrum while significant, amplitudes and ``B`` by least squares, and what they imply as attitude jitter."""
from __future__ import annotations

import math
from typing import List

import numpy as np
from scipy import optimize, stats

from ..basis import trigonometric
from ..errors import DegenerateGeometryError
from ..estimation import Block, normal_solve, weighted_lsq
from .design import _set_values, _values
from .model import AXES, PanMSError
from .spectrum import _freq_grid, _row_series, _sine_power, _within_row_variance

#: What a singular fit of the jitter series tells the user.
JITTER_HINT = "the jitter sines of the row series; fix their number (--jitter N) or leave them out (--jitter none)"
#: False-alarm probability below which a jitter component is accepted (``jitter="auto"``).
JITTER_FAP = 1e-3
MAX_JITTER_COMPONENTS = 8


def supported_sines(lines, r, w):
    """``(k, rows, span)``: how many sines the residual's row series resolves, from its ``rows`` cell rows over
    ``span`` MS lines. Each sine takes 3 unknowns (sine and cosine amplitudes, frequency) besides the series' mean,
    with 3 rows left to check the fit (``k <= (rows - 4) // 3``), and no more than the independent frequencies
    ``1/span`` apart in the band searched (below 0.45 cycles per row: ``_freq_grid``); 0 without such a band."""
    lc, _, _ = _row_series(lines, r, w)
    freqs, span = _freq_grid(lc)
    if freqs.size == 0:
        return 0, int(lc.size), span
    k = min((lc.size - 4) // 3, int((freqs[-1] - freqs[0]) * span))
    return max(0, int(k)), int(lc.size), span


def _select_frequencies(lines, r, w, limit, n_fixed):
    """Greedy: strongest peak of the residual's row spectrum, refined, kept while significant (F-test with a
    false-alarm probability over the independent frequencies searched) or exactly ``n_fixed``; at most ``limit``
    (:func:`supported_sines`)."""
    lc, y, sw = _row_series(lines, r, w)
    freqs, span = _freq_grid(lc)
    s2, dof = _within_row_variance(lines, r, w)
    chosen: List[float] = []
    if freqs.size == 0:
        return chosen
    n_indep = max(1.0, (freqs[-1] - freqs[0]) * span)
    df = freqs[1] - freqs[0]

    def design(fs):
        return np.stack([np.ones_like(lc)] + [g(2 * np.pi * f * lc) for f in fs for g in (np.sin, np.cos)], axis=1)

    def rss(fs):
        A = design(fs)
        v = (y - A @ normal_solve(A, y, sw, JITTER_HINT)[0]) * np.sqrt(sw)
        return float(v @ v)

    def trial(fs):
        # the optimisers' objective: a trial the design cannot separate (two frequencies clipped to the same
        # band edge: identical columns) is no candidate, not a failure
        try:
            return rss(fs)
        except DegenerateGeometryError:
            return math.inf

    while len(chosen) < limit:
        base = rss(chosen)
        A = design(chosen)
        resid = y - A @ normal_solve(A, y, sw, JITTER_HINT)[0]
        gain, _, _ = _sine_power(lc, resid, sw, freqs)
        f0 = float(freqs[int(np.argmax(gain))])
        opt = optimize.minimize_scalar(lambda f: trial(chosen + [f]), bounds=(max(freqs[0], f0 - 2 * df),
                                                                             min(freqs[-1], f0 + 2 * df)),
                                    method="bounded")
        f_new = float(opt.x)
        new = trial(chosen + [f_new])
        if not math.isfinite(new):
            break                     # the peak is a component already taken
        if n_fixed is None:
            # the noise of the row means from the cells' scatter within their rows (not from the rows left
            # over, which on a short crop -- 12 rows, < 1 jitter cycle -- still hold the next components' signal)
            if s2 is not None:
                F, dof2 = ((base - new) / 3.0) / s2, dof
            else:
                p1 = 1 + 3 * (len(chosen) + 1)          # the mean, then amplitudes and frequency per sine
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
            res = optimize.minimize(lambda fs: trial(list(np.clip(fs, lo, hi))), np.array(chosen),
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


def _frequencies(model, c, inl, w, n_fixed):
    """Each axis' jitter frequencies on the residual of the linear and piecewise terms, as many as the cell rows
    resolve (:func:`supported_sines`): a fixed count beyond that is refused (:class:`PanMSError`, nothing
    solved), ``auto`` stops there with a note; a fixed count the data give fewer of is noted."""
    ps, pl = model.predict(c["sample"], c["line"], terms=("linear", "piecewise"))
    res = np.stack([c["d_sample"] - ps, c["d_line"] - pl], axis=1)
    series = [(c["line"], res[:, k], np.where(inl, w[:, k], 0.0)) for k in range(len(AXES))]
    cap, rows, span = min(supported_sines(*sr) for sr in series)
    if n_fixed is not None and n_fixed > cap:
        use = f"--jitter {cap} or fewer, auto, or" if cap else "--jitter none, auto, or"
        raise PanMSError(f"--jitter {n_fixed}: the usable cells lie on {rows} rows over {span:.0f} MS lines, enough "
                         f"for {cap} sine(s) per axis (3 rows each and 4 for the mean and the fit's check, their "
                         f"frequencies 1/{span:.0f} cycles per line apart); use {use} a smaller --cell")
    limit = MAX_JITTER_COMPONENTS if n_fixed is None else n_fixed
    notes = model.info.setdefault("notes", [])
    for ax, sr in zip(AXES, series):
        fs = _select_frequencies(*sr, min(limit, cap), n_fixed)
        model.jitter[ax] = {"b": 0.0, "components": [{"frequency_cycles_per_line": f, "sin": 0.0, "cos": 0.0}
                                                     for f in fs]}
        if n_fixed is None and cap == 0:
            notes.append(f"jitter {ax}: not estimated: {rows} usable cell rows resolve no sine (7 needed); a "
                         "smaller --cell gives more rows")
        elif n_fixed is None and len(fs) == cap < limit:
            notes.append(f"jitter {ax}: stopped at {cap} sine(s), all that the {rows} usable cell rows resolve "
                         "(the last still significant); a smaller --cell gives more rows")
        elif n_fixed is not None and len(fs) < n_fixed:
            notes.append(f"jitter {ax}: {len(fs)} of the {n_fixed} sines asked for: the next one is not resolved "
                         f"from those taken over {span:.0f} MS lines (or lies at the edge of the band searched)")


def _solve_jitter(model, c, a, y, w, inl, blocks, n_fixed, sn, keep):
    _frequencies(model, c, inl, w, n_fixed)
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
            model.info["notes"].append(f"jitter {ax}: one sine fewer, the amplitudes' solve could not separate it "
                                       "(from the line terms or another sine)")
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
