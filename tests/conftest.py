"""Shared fixtures: paths of the real test data (tests/data/*, each folder with a PROVENANCE.txt)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"
os.environ.setdefault("PROJ_DATA", "/usr/share/proj")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA


@pytest.fixture(scope="session")
def srtm_path() -> Path:
    """Real SRTM3 tile N44E005 (Mont Ventoux), heights above EGM96."""
    return DATA / "dem" / "N44E005.hgt"


@pytest.fixture(scope="session")
def ventoux_rpc_path() -> Path:
    """Real Pleiades-1B DIMAP v2 RPC of the Ventoux left image (covers the SRTM tile)."""
    return DATA / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML"
