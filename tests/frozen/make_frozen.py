"""Write the frozen reference numbers of tests/frozen (issue 10, item 1). Run once on the reference code:

    PROJ_DATA=/usr/share/proj .venv/bin/python tests/frozen/make_frozen.py [--skip-experiments]

Writes ``tests/frozen/data/{compensation,lookangle,intersection,rpc_fit,experiment_<name>}.json`` atomically.
Re-running on a refactored tree and diffing the JSON is the same check the tests perform.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from frozen import scenes as S  # noqa: E402


def _write(name: str, payload) -> None:
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                                text=True, check=False).stdout.strip()
    except OSError:
        commit = ""
    doc = {"generated_from_commit": commit, "values": payload}
    S.DATA.mkdir(parents=True, exist_ok=True)
    path = S.DATA / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1, sort_keys=True, allow_nan=True) + "\n")
    os.replace(tmp, path)
    print(f"wrote {path}")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    _write("compensation", {f"{k}|{'blunders' if b else 'clean'}": S.compute_compensation(k, b)
                            for k in S.COMP_CASES for b in (False, True)})
    scene = S.gf4_scene()
    _write("lookangle", S.compute_lookangle(scene))
    _write("rpc_fit", S.compute_rpc_fit(scene))
    _write("intersection", S.compute_intersection())
    if "--skip-experiments" not in argv:
        for name in ("gf4", "zy3", "hj1"):
            with tempfile.TemporaryDirectory() as d:
                _write(f"experiment_{name}", S.compute_experiment(name, d))
    return 0


if __name__ == "__main__":
    sys.exit(main())
