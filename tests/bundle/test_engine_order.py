"""The bundle's rays are sorted by view, then point, inside the adjustment (``make_rays``; a view's rays one slice,
issue 22's speed goal): the estimate does not depend on the order of the observation table, and every per-ray
output comes back in the table's own order. The grouped elimination takes groups as slices (sorted rays) or as
index arrays in any order, with the same result, points' covariances included."""
from __future__ import annotations

import numpy as np

from gdal_gf4cal.bundle import adjust_views
from gdal_gf4cal.bundle.inputs import check_inputs, make_layout, make_rays, view_sizes
from gdal_gf4cal.bundle.solve import State, linearise
from gdal_gf4cal.bundle.start import base_weights, start_ground
from gdal_gf4cal.estimation.indexed import solve_rows
from gdal_gf4cal.simulate.views import simulate_views


def test_estimate_and_table_do_not_depend_on_the_row_order():
    sim = simulate_views("multi-date", 4, n_ties=300, noise_px=0.2, seed=5)
    obs = sim.observations.reset_index(drop=True)
    blunder = obs.index[::97]
    obs.loc[blunder, "sample"] += 8.0                                      # a few rays for the robust driver
    shuffled = obs.sample(frac=1.0, random_state=2).reset_index(drop=True)
    a = adjust_views(obs, sim.models)
    b = adjust_views(shuffled, sim.models)
    assert np.max(np.abs(a.x - b.x)) < 1e-8 and abs(a.sigma0 - b.sigma0) < 1e-9
    for est, tab in ((a, obs), (b, shuffled)):                            # the table's rows, in its own order
        assert list(est.table["point_id"]) == list(tab["point_id"])
        assert list(est.table["image_id"]) == list(tab["image_id"])
        res = tab[["sample", "line"]].to_numpy() - est.table[["pred_sample_after", "pred_line_after"]].to_numpy()
        assert np.allclose(est.residuals, res, atol=1e-12)
        assert np.array_equal(est.outlier, est.table["outlier"].to_numpy(bool))
    flag_a = a.table.set_index(["point_id", "image_id"])["outlier"]
    flag_b = b.table.set_index(["point_id", "image_id"])["outlier"]
    assert flag_a.sum() >= len(blunder) and flag_a.equals(flag_b.loc[flag_a.index])


def test_grouped_elimination_takes_slices_or_shuffled_index_groups():
    sim = simulate_views("multi-date", 5, n_ties=400, noise_px=0.2, seed=4)
    sizes = view_sizes(sim.models)
    tab = check_inputs(sim.observations, sim.models, sizes)
    layout = make_layout(tab, sim.models, sizes, "affine")
    rays = make_rays(tab, layout)
    ground = start_ground(sim.models, layout, rays)[0]
    wts = base_weights(sim.models, layout, rays, ground)
    s = linearise(sim.models, layout, rays, State(np.zeros(layout.n_params), ground), wts)
    assert all(isinstance(rows, slice) for rows, _ in s.groups)
    rng = np.random.default_rng(0)
    shuffled = [(rng.permutation(np.arange(rows.start, rows.stop)), cols) for rows, cols in s.groups]
    args = (s.point, s.jac_points, s.residuals, s.weights, s.cols, s.vals, rays.n_points, layout.n_params)
    kw = dict(prior=s.prior, extra=s.extra, covariance=True)
    by_slice = solve_rows(*args, groups=s.groups, **kw)
    by_index = solve_rows(*args, groups=shuffled, **kw)
    plain = solve_rows(*args, **kw)                                        # the index-scatter assembly
    scale = np.max(np.abs(plain[3]))
    for sol in (by_slice, by_index):
        assert np.max(np.abs(sol[3] - plain[3])) < 1e-8 * scale
        assert np.max(np.abs(sol[0] - plain[0])) < 1e-8 * np.max(np.abs(plain[0]))
        assert np.max(np.abs(sol[1] - plain[1])) < 1e-8 * np.max(np.abs(plain[1]))
