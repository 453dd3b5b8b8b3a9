"""rpc_io as a package (issue 21): readers and writers apart, the public names unchanged, and no process-global
registry of input files: what a writer refuses depends only on what it is given (the RPC's source files)."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from gdal_gf4cal import InputOverwriteError, RPCModel, rpc_io

DATA = Path(__file__).resolve().parents[1] / "data" / "rpc"


def test_public_names_and_package_layout():
    from gdal_gf4cal.rpc_io import readers, writers
    for name in rpc_io.__all__:
        assert getattr(rpc_io, name) is not None, name
    assert rpc_io.read_rpc_metadata is readers.read_rpc_metadata and rpc_io.write_rpb is writers.write_rpb
    for module in (readers, writers):                # no module-level set of paths read or written
        assert not [k for k, v in vars(module).items() if isinstance(v, set)]


def test_writers_refuse_the_sources_they_are_given_and_nothing_else(tmp_path):
    src = tmp_path / "scene_RPC.TXT"
    shutil.copy(DATA / "test_rpc.txt", src)
    md = rpc_io.read_rpc_metadata(src)
    assert isinstance(md, dict) and md.source == str(src) and str(src) in md.files
    with pytest.raises(InputOverwriteError, match="input"):
        rpc_io.write_rpc_txt(md, src, overwrite=True)                   # the metadata knows where it came from
    with pytest.raises(InputOverwriteError, match="input"):
        RPCModel.from_file(src).write_rpc_txt(src, overwrite=True)      # so does the model (its source)
    changed = dict(md, LINE_OFF="7")                                    # a plain dict: no source, no refusal
    rpc_io.write_rpc_txt(changed, src, overwrite=True)
    assert rpc_io.read_rpc_metadata(src)["LINE_OFF"] == "7.0"
