"""The engine gdal_gf4cal never imports qgis or PyQt (it must run, and its tests pass, without QGIS).

Two checks: no import statement of qgis/PyQt/sip in the engine's sources, and importing every engine module in a
fresh interpreter leaves no qgis/PyQt module in sys.modules. Runs with or without QGIS installed.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ENGINE = os.path.join(ROOT, "gdal_gf4cal")
FORBIDDEN = re.compile(r"^\s*(?:from|import)\s+(qgis|PyQt\d?|sip|PySide\d?)\b", re.M)


def test_no_qgis_import_statements_in_engine():
    offenders = []
    for folder, _, names in os.walk(ENGINE):
        for name in names:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                with open(path, encoding="utf-8") as fh:
                    for m in FORBIDDEN.finditer(fh.read()):
                        offenders.append(f"{os.path.relpath(path, ROOT)}: {m.group(0).strip()}")
    assert not offenders, offenders


def test_importing_every_engine_module_loads_no_qgis():
    code = r"""
import importlib, json, pkgutil, sys
import gdal_gf4cal
names, failed = [], {}
for m in pkgutil.walk_packages(gdal_gf4cal.__path__, "gdal_gf4cal."):
    if m.name.endswith("__main__"):  # runs the CLI when imported
        continue
    try:
        importlib.import_module(m.name)
        names.append(m.name)
    except Exception as exc:  # another module's own tests report its import errors
        failed[m.name] = repr(exc)
bad = sorted(k for k in sys.modules if k.split(".")[0] in ("qgis", "PyQt5", "PyQt6", "sip", "PySide2", "PySide6"))
print(json.dumps({"imported": names, "failed": failed, "bad": bad}))
"""
    env = dict(os.environ, PYTHONPATH=ROOT)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(out["imported"]) >= 10 and "gdal_gf4cal.report" in out["imported"]
    assert out["bad"] == [], out["bad"]
