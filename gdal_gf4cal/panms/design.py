"""Design matrices of the pan-MS model's linear and piecewise terms, their estimation blocks, the terms the
usable cells support (:func:`_term_layout`) and the model <-> parameter vector mapping (METHODS §9)."""
from __future__ import annotations

from typing import List

import numpy as np

from ..basis import piecewise_polynomial
from ..estimation import Block
from .model import AXES, ORDER, PanMSModel


def linear_design(sn, ln) -> np.ndarray:
    """(n, 2, 6) design of ``A1..A6`` in the order A1 A2 A4 A5 (datum: constant and s) then A3 A6 (l)."""
    n = sn.size
    a = np.zeros((n, 2, 6))
    one = np.ones(n)
    a[:, 0, 0], a[:, 0, 1], a[:, 1, 2], a[:, 1, 3] = one, sn, one, sn
    a[:, 0, 4], a[:, 1, 5] = ln, ln
    return a


LINEAR_ORDER = [0, 1, 3, 4, 2, 5]           # design column -> A index


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
    lin = model.linear[LINEAR_ORDER]
    pw = np.concatenate([model.piecewise[:, 0, :].ravel(), model.piecewise[:, 1, :].ravel()])
    return np.concatenate([lin, pw])


def _set_values(model: PanMSModel, x: np.ndarray) -> None:
    lin = np.zeros(6)
    lin[LINEAR_ORDER] = x[:6]
    model.linear = lin
    m = model.n_sub_ccds
    q = m * (ORDER + 1)
    model.piecewise = np.stack([x[6:6 + q].reshape(m, ORDER + 1), x[6 + q:6 + 2 * q].reshape(m, ORDER + 1)], axis=1)
