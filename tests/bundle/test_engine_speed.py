"""The bundle's fast reduced system (issue 22's speed goal, METHODS §11): the rows eliminated by views and axes
(:func:`gdal_gf4cal.estimation.indexed.solve_rows` with groups) give the same step as one plain sparse solve of the
full normal equations (points and corrections together), and the reduced system keeps its size whatever the ties.
No timing here: ``bench/bench_bundle.py`` measures."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from gdal_gf4cal.bundle import adjust_views
from gdal_gf4cal.bundle.inputs import check_inputs, make_layout, make_rays, view_sizes
from gdal_gf4cal.bundle.solve import State, linearise
from gdal_gf4cal.bundle.start import base_weights, start_ground
from gdal_gf4cal.estimation.indexed import solve_rows
from gdal_gf4cal.simulate.views import simulate_views


def _system(n_ties: int, model: str, seed: int = 3):
    sim = simulate_views("multi-date", 10, n_ties=n_ties, noise_px=0.2, seed=seed)
    sizes = view_sizes(sim.models)
    tab = check_inputs(sim.observations, sim.models, sizes)
    layout = make_layout(tab, sim.models, sizes, model)
    rays = make_rays(tab, layout)
    ground = start_ground(sim.models, layout, rays)[0]
    wts = base_weights(sim.models, layout, rays, ground)
    rng = np.random.default_rng(seed)
    wts.rays = wts.rays * rng.uniform(0.2, 1.0, wts.rays.size)            # robust factors, some rays out
    many = np.flatnonzero((rays.slot == 0) & (np.bincount(rays.point)[rays.point] >= 4))
    wts.rays[rng.choice(many, many.size // 10, replace=False)] = 0.0        # rejected: one ray of some points
    state = State(rng.normal(0.0, 0.5, layout.n_params), ground)
    return linearise(sim.models, layout, rays, state, wts), rays.n_points, layout.n_params


def _dense_reference(s, n_pts: int, p: int):
    """The full normal equations of points (3 each) and corrections, assembled from the plain Jacobian row by
    row, one sparse direct solve."""
    m = s.point.size
    c = s.cols.shape[1]
    rows = np.concatenate([np.repeat(np.arange(m), 3), np.repeat(np.arange(m), c)])
    cols = np.concatenate([(3 * s.point[:, None] + np.arange(3)).ravel(), 3 * n_pts + s.cols.ravel()])
    jac = sp.csr_matrix((np.concatenate([s.jac_points.ravel(), s.vals.ravel()]), (rows, cols)),
                        shape=(m, 3 * n_pts + p))
    ground = sp.hstack([sp.identity(3 * n_pts), sp.csr_matrix((3 * n_pts, p))])
    datum = sp.hstack([sp.csr_matrix((p, 3 * n_pts)), s.extra[0]])
    a = sp.vstack([jac, ground, datum]).tocsc()
    w = np.concatenate([s.weights, s.prior[0].ravel(), s.extra[2]])
    r = np.concatenate([s.residuals, s.prior[1].ravel(), np.nan_to_num(s.extra[1])])
    normal = (a.T @ sp.diags(w) @ a).tocsc()
    d = 1.0 / np.sqrt(normal.diagonal())                                 # equilibrated, one refinement
    eq = (sp.diags(d) @ normal @ sp.diags(d)).tocsc()
    rhs = d * (a.T @ (w * r))
    lu = spla.splu(eq)
    z = lu.solve(rhs)
    z += lu.solve(rhs - eq @ z)
    dx = d * z
    return dx[:3 * n_pts].reshape(n_pts, 3), dx[3 * n_pts:]


#: Relative agreement of two correct solvers of these systems: the datum held by the priors alone leaves the
#: equilibrated reduced system a condition number of ~1e6, so solutions differ by ~1e-9 (measured 2e-10 to 9e-10).
REL_TOL = 5e-9


@pytest.mark.parametrize("model", ["affine", "translation"])
def test_grouped_elimination_equals_the_full_normal_equations(model):
    s, n_pts, p = _system(2000, model)
    sol = s.solve(n_pts, p)
    ref_points, ref_global = _dense_reference(s, n_pts, p)
    assert sol.ok.all() and sol.cov_global.shape == (p, p)
    assert np.max(np.abs(sol.dx_global - ref_global)) < REL_TOL * np.max(np.abs(ref_global))
    assert np.max(np.abs(sol.dx_points - ref_points)) < REL_TOL * np.max(np.abs(ref_points))
    plain = solve_rows(s.point, s.jac_points, s.residuals, s.weights, s.cols, s.vals, n_pts, p, prior=s.prior,
                       extra=s.extra)                                      # the index-scatter assembly
    assert np.max(np.abs(plain[3] - ref_global)) < REL_TOL * np.max(np.abs(ref_global))


def test_reduced_system_is_six_per_view_whatever_the_ties():
    sizes = set()
    for n_ties in (300, 3000):
        sim = simulate_views("multi-date", 10, n_ties=n_ties, noise_px=0.2, seed=1)
        est = adjust_views(sim.observations, sim.models, robust=False)
        assert est.converged and est.cov.shape == (60, 60)
        sizes.add(est.reduced_size)
    assert sizes == {60}
