"""Frozen numbers of :func:`fit_compensation` (METHODS §4, §6) for every model, with and without blunders.

Tolerances: parameters, their standard deviations, sigma0 and RMS are px-sized (0.01-10 px) least-squares results
whose float noise is ~1e-12 px: relative 1e-6 with an absolute floor of 1e-9 px (for values near zero).
Redundancy and outlier flags are exact.
"""
from __future__ import annotations

import pytest

from .compare import assert_close, load
from .scenes import COMP_CASES, compute_compensation

FROZEN = load("compensation")
REL, ABS_PX = 1e-6, 1e-9


@pytest.mark.parametrize("blunders", [False, True], ids=["clean", "blunders"])
@pytest.mark.parametrize("key", list(COMP_CASES))
def test_compensation_frozen(key, blunders):
    want = FROZEN[f"{key}|{'blunders' if blunders else 'clean'}"]
    got = compute_compensation(key, blunders)
    assert got["redundancy"] == want["redundancy"]
    assert got["outliers"] == want["outliers"]
    if blunders:   # the planted blunders (control rows 3, 11, 27) are what is flagged
        assert [i for i, f in enumerate(got["outliers"]) if f] == [3, 11, 27]
    else:
        assert not any(got["outliers"])
    for q in ("params", "param_std", "sigma0", "rms"):
        assert_close(got[q], want[q], rel=REL, abs_=ABS_PX, path=q)
