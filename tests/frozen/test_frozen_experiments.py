"""Frozen numbers of ``gf4cal experiment gf4|zy3|hj1`` (METHODS §8-10), through the Python entry points.

Every numeric leaf of the report (flattened by ``adapters.experiment_numbers``; timings left out) is compared:
relative 1e-6 with an absolute floor of 1e-8 (px, m; means near zero). gf4 (~5 s) is marked slow; zy3 (~3 s)
and hj1 (~1 s) run by default.
"""
from __future__ import annotations

import pytest

from .compare import assert_close, load
from .scenes import compute_experiment


@pytest.mark.parametrize("name", [pytest.param("gf4", marks=pytest.mark.slow), "zy3", "hj1"])
def test_experiment_frozen(name, tmp_path):
    assert_close(compute_experiment(name, tmp_path), load(f"experiment_{name}"), rel=1e-6, abs_=1e-8, path=name)
