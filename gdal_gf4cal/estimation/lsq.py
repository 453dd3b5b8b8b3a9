"""Weighted linear least squares with named parameter blocks that can be frozen (METHODS §4, §5).

``A x ~ y`` with weights ``w`` (``1/sigma^2``; 0 leaves an observation out). Columns are scaled to unit weighted
norm before the SVD solve, so the condition number reported (and tested against ``max_condition``) is that of the
equilibrated design: parameters of very different units (pixels and pixels per normalised coordinate cubed) do
not make a well-determined problem look degenerate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Sequence, Tuple

import numpy as np

from ..errors import DegenerateGeometryError
from ..threads import BLAS_SERIAL_SIZE, rows_times
from .result import Estimate, names_and_blocks

#: Largest condition number of the column-scaled design accepted as a determined layout.
MAX_CONDITION = 1e8


@dataclass(frozen=True)
class Block:
    """A named group of parameters (``names``), e.g. ``Block('exterior', ('omega', 'phi', 'kappa'))``."""

    name: str
    names: Tuple[str, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))

    @property
    def size(self) -> int:
        return len(self.names)


def gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a.T @ b`` of two tall matrices with few columns (e.g. ``A^T W A`` of 20,000 observation rows) summed over
    row chunks that BLAS computes on the calling thread (:data:`~gdal_gf4cal.threads.BLAS_SERIAL_SIZE`): on a
    loaded machine OpenBLAS's threads made the one product 5-7x slower; the chunks depend on the shapes only, so
    the numbers do not depend on the cores."""
    n = a.shape[0]
    step = max(1, BLAS_SERIAL_SIZE // max(a.shape[1] * b.shape[1], 1))
    if n <= step:
        return a.T @ b
    out = a[:step].T @ b[:step]
    for i in range(step, n, step):
        out += a[i:i + step].T @ b[i:i + step]
    return out


def _free_mask(blocks: Dict[str, slice], frozen: Sequence[str], p: int) -> np.ndarray:
    free = np.ones(p, bool)
    for name in frozen:
        if name not in blocks:
            raise DegenerateGeometryError(f"cannot freeze unknown parameter block {name!r}; blocks are "
                                          f"{', '.join(blocks)}")
        free[blocks[name]] = False
    return free


def solve_normal_scaled(a: np.ndarray, y: np.ndarray, w: np.ndarray, hint: str = "",
                        max_condition: float = MAX_CONDITION,
                        solver: str = "svd") -> Tuple[np.ndarray, np.ndarray, float]:
    """``(x, N^-1, cond)`` of the weighted LS ``a x ~ y`` through the SVD of the column-scaled ``sqrt(w) a``.

    ``solver="normal"``: through the eigen-decomposition of its ``p x p`` normal matrix instead of the SVD of the
    ``n x p`` design, the same numbers to rounding (for the iterations of a robust loop over many points); a
    condition number above :data:`NORMAL_CONDITION`, where the normal matrix loses the small singular values,
    goes back to the SVD, so both solvers refuse the same layouts.
    Raises :class:`DegenerateGeometryError` (with the condition number) when the layout does not determine ``x``.
    """
    (x,), n_inv, cond = _solve_scaled_many(a, [y], w, hint, max_condition, solver)
    return x, n_inv, cond


def _solve_scaled_many(a: np.ndarray, ys, w: np.ndarray, hint: str, max_condition: float, solver: str):
    """:func:`solve_normal_scaled` of several right-hand sides ``ys`` on one decomposition of ``a`` and ``w``:
    ``([x per y], N^-1, cond)``, each ``x`` bit for bit the one of its own call."""
    if solver not in ("svd", "normal"):
        raise ValueError(f"solver must be 'svd' or 'normal', not {solver!r}")
    s = np.zeros(0)
    if solver == "normal":
        s, vt, project, scale = _scaled_normal_eig(a, np.where(w > 0, w, 0.0))
    if not (s.size and s[-1] > 0 and s[0] / s[-1] <= NORMAL_CONDITION):
        sw = np.sqrt(np.maximum(w, 0.0))
        aw = a * sw[:, None]
        scale = np.linalg.norm(aw, axis=0)
        scale = np.where(scale > 0, scale, 1.0)
        u, s, vt = np.linalg.svd(aw / scale, full_matrices=False)

        def project(y):
            return u.T @ (y * sw)
    cond = float(s[0] / s[-1]) if s.size and s[-1] > 0 else math.inf
    if not s.size or cond > max_condition:
        raise DegenerateGeometryError(
            f"the observations do not determine the parameters (condition number {cond:.3g}){hint}; add "
            "observations spread over the image or estimate fewer parameters")
    xs = [((vt.T / s) @ project(y)) / scale for y in ys]
    vs = vt.T / s
    n_inv = (vs @ vs.T) / np.outer(scale, scale)
    return xs, n_inv, cond


#: Largest condition number (of the column-scaled design) solved through the normal matrix by
#: ``solver="normal"``; above it the SVD (the normal matrix squares it).
NORMAL_CONDITION = 1e4


def _scaled_normal_eig(a: np.ndarray, w: np.ndarray):
    """``(s, vt, project, scale)`` of the thin SVD ``sqrt(w) a / scale = u diag(s) vt`` (columns scaled to unit
    weighted norm, singular values in decreasing order) from the eigen-decomposition of its normal matrix
    ``A^T W A`` (:func:`gram`: rows of weight 0 drop out, no copy of the rows in the fit); ``project(y)`` is
    ``u^T sqrt(w) y``."""
    wa = a * w[:, None]
    nmat = gram(wa, a)
    scale = np.sqrt(np.maximum(np.diag(nmat), 0.0))
    scale = np.where(scale > 0, scale, 1.0)
    ev, v = np.linalg.eigh(nmat / np.outer(scale, scale))
    ev, v = ev[::-1], v[:, ::-1]
    s = np.sqrt(np.maximum(ev, 0.0))

    def project(y):
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(s > 0, (v.T @ ((wa.T @ y) / scale)) / s, 0.0)
    return s, v.T, project, scale


def weighted_lsq(design, obs, weights=None, *, blocks: Sequence[Block] = (), frozen: Sequence[str] = (),
                 values=None, prior=None, apriori: bool = False, hint: str = "",
                 max_condition: float = MAX_CONDITION, solver: str = "svd") -> Estimate:
    """Weighted least squares ``design @ x ~ obs`` with freezable named blocks (METHODS §4).

    Parameters
    ----------
    design : ndarray (n_obs, p)
    obs : ndarray (n_obs,)
    weights : ndarray (n_obs,), optional
        ``1 / sigma^2`` per observation; 0 leaves it out of the estimate (its residual is still computed).
    blocks : sequence of Block
        Named parameter groups in column order (sizes must add up to ``p``); default one block ``x``.
    frozen : sequence of str
        Blocks held at ``values`` (default 0): their columns move to the right-hand side.
    values : ndarray (p,), optional
        Current parameter values (used for frozen blocks only).
    prior : ndarray (n_obs,), optional
        A-priori weights of the observations left out (``weights == 0``), to normalise their residuals
        (default 1).
    apriori : bool
        Covariance from the a-priori weights (``N^-1``) instead of ``sigma0^2 N^-1``.
    solver : ``"svd"`` or ``"normal"``
        See :func:`solve_normal_scaled` (the same diagnostics either way).

    Returns
    -------
    Estimate
        With redundancy numbers ``r_i = 1 - w_i a_i^T N^-1 a_i`` and normalised residuals
        ``v_i / (sigma0 sqrt(r_i / w_i))`` (``v_i / (sigma0 sqrt(1/w_i + a_i^T N^-1 a_i))`` when left out).

    Raises
    ------
    DegenerateGeometryError
        The layout does not determine the free parameters (the message gives the condition number).
    """
    return weighted_lsq_many(design, [obs], weights, blocks=blocks, frozen=frozen, values=values, prior=prior,
                             apriori=apriori, hint=hint, max_condition=max_condition, solver=solver)[0]


def weighted_lsq_many(design, obs_seq, weights=None, *, blocks: Sequence[Block] = (), frozen: Sequence[str] = (),
                      values=None, prior=None, apriori: bool = False, hint: str = "",
                      max_condition: float = MAX_CONDITION, solver: str = "svd") -> List[Estimate]:
    """:func:`weighted_lsq` of one design and weights with several observation vectors (e.g. the sample and the
    line axis of a compensation on the same terms): one decomposition, one set of redundancy numbers; each
    Estimate bit for bit the one of its own :func:`weighted_lsq` call."""
    a = np.asarray(design, dtype=float)
    ys = [np.asarray(obs, dtype=float).ravel() for obs in obs_seq]
    n, p = a.shape
    w = np.ones(n) if weights is None else np.broadcast_to(np.asarray(weights, dtype=float), (n,)).copy()
    names, sl = names_and_blocks(blocks, p)
    if len(names) != p:
        raise DegenerateGeometryError(f"blocks name {len(names)} parameters but the design has {p} columns")
    free = _free_mask(sl, frozen, p)
    x0 = np.zeros(p) if values is None else np.asarray(values, dtype=float).copy()
    ys_free = [y - a[:, ~free] @ x0[~free] if (~free).any() else y for y in ys]
    af = a if free.all() else a[:, free]
    used = w > 0
    n_used = int(np.count_nonzero(used))
    pf = int(free.sum())
    if n_used < pf:
        raise DegenerateGeometryError(f"{n_used} observations cannot determine {pf} parameters{hint}; add "
                                      "observations or freeze/estimate fewer parameters")
    if solver == "normal":          # the rows out of the fit (weight 0) drop out of its normal matrix: no copies
        xfs, n_inv, cond = _solve_scaled_many(af, ys_free, w, hint, max_condition, solver)
    else:
        xfs, n_inv, cond = _solve_scaled_many(af[used], [y[used] for y in ys_free], w[used], hint, max_condition,
                                              solver)
    dof = n_used - pf
    q = np.sum(rows_times(af, n_inv) * af, axis=1)
    red = np.where(used, 1.0 - w * q, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        w_out = np.ones(n) if prior is None else np.broadcast_to(np.asarray(prior, dtype=float), (n,))
        qv = np.where(used, red / np.where(used, w, 1.0), 1.0 / np.where(used, 1.0, w_out) + q)
        sq = np.sqrt(np.abs(qv))
    out = []
    for y, xf in zip(ys, xfs):
        x = x0.copy()
        x[free] = xf
        v = y - rows_times(a, x)
        sigma0 = float(math.sqrt(np.sum(w * v * v) / dof)) if dof > 0 else 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            norm = np.where(qv > 1e-12, v / (max(sigma0, 1e-300) * sq), np.nan)
        cov = np.zeros((p, p))
        cov[np.ix_(free, free)] = n_inv if apriori else sigma0 ** 2 * n_inv
        out.append(Estimate(names=list(names), x=x, cov=cov, sigma0=sigma0, dof=dof, redundancy=red, residuals=v,
                            normalised=norm, weights=w, blocks=dict(sl), frozen=tuple(frozen),
                            condition_number=cond))
    return out


def sigma0_and_cov(normal, vtpv: float, dof: int, *, apriori: bool = False) -> Tuple[float, np.ndarray]:
    """``(sigma0, cov)`` from a normal matrix ``N = A^T W A``, the weighted residual square sum ``v^T W v`` and the
    degrees of freedom (METHODS §4, §6): ``sigma0 = sqrt(v^T W v / dof)`` (NaN without redundancy) and
    ``cov = sigma0^2 N^-1`` (``N^-1`` when ``apriori`` or without redundancy), ``N`` inverted column-scaled.

    The one place besides :func:`weighted_lsq` where an a-posteriori covariance is built: every estimator that
    solves its own normal equations (look-angle, block, bundle, intersection) reports through it.
    """
    n_mat = np.asarray(normal, dtype=float)
    d = np.sqrt(np.diag(n_mat))
    n_inv = np.linalg.inv(n_mat / d[:, None] / d[None, :]) / d[:, None] / d[None, :]
    sigma0 = float(unit_weight_sigma(float(vtpv), dof))
    return sigma0, (n_inv if apriori or dof <= 0 else sigma0 ** 2 * n_inv)


def unit_weight_sigma(vtpv, dof):
    """A-posteriori standard deviation of unit weight ``sqrt(v^T W v / dof)``, NaN without redundancy; vectorised
    (e.g. one per intersected point)."""
    vtpv, dof = np.asarray(vtpv, dtype=float), np.asarray(dof)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(dof > 0, np.sqrt(vtpv / np.maximum(dof, 1)), np.nan)


def normal_solve(design, obs, weights, hint: str = "") -> Tuple[np.ndarray, np.ndarray]:
    """Fast weighted LS ``design @ x ~ obs`` by the column-scaled normal equations: ``(x, N)`` (METHODS §4, §5).

    For IRLS loops over many observations (look-angle calibration, 10,000 GCPs): one ``A^T W A`` product per call,
    no SVD and no per-observation diagnostics (use :func:`weighted_lsq` for the final :class:`Estimate`).
    Raises :class:`DegenerateGeometryError` ``"condition number inf: {hint}"`` when a column carries no weight or
    ``N`` is singular.
    """
    a = np.asarray(design, dtype=float)
    aw = a * np.asarray(weights, dtype=float)[:, None]
    n_mat = aw.T @ a
    b = aw.T @ np.asarray(obs, dtype=float)
    d = np.sqrt(np.diag(n_mat))
    if not np.all(d > 0):
        raise DegenerateGeometryError(f"condition number inf: {hint}")
    try:
        x = np.linalg.solve(n_mat / d[:, None] / d[None, :], b / d) / d
    except np.linalg.LinAlgError:
        raise DegenerateGeometryError(f"condition number inf (singular normal matrix): {hint}") from None
    return x, n_mat
