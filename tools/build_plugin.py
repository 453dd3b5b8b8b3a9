#!/usr/bin/env python3
"""Build the QGIS plugin ``gdal_gf4cal_plugin`` (``make plugin``).

Creates ``build/plugin/gdal_gf4cal_plugin/`` and ``dist/gdal_gf4cal_plugin.zip`` (installable from QGIS's Plugin
Manager, "Install from ZIP"), laid out as::

    gdal_gf4cal_plugin/
        __init__.py            classFactory(iface); puts libs/ on sys.path
        plugin.py              the plugin object: initProcessing registers the provider (no GUI code)
        metadata.txt           copied from the repository root
        processing_provider/   the provider (copied)
        libs/gdal_gf4cal/      a vendored copy of the engine

The build is reproducible: files are sorted and stamped with a fixed date in the zip. The folder is assembled
next to its destination and swapped in with os.replace, so a failed build leaves the previous one intact.
"""
from __future__ import annotations

import argparse
import configparser
import os
import shutil
import sys
import tempfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PLUGIN = "gdal_gf4cal_plugin"
IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "*.pyo", ".*", "*.egg-info")
ZIP_DATE = (2024, 1, 1, 0, 0, 0)

INIT_PY = '''"""QGIS plugin gdal_gf4cal_plugin: the gf4cal Processing provider with its bundled engine (gdal_gf4cal)."""
import os
import sys

# The engine is vendored under libs/; put it first so the provider always gets the engine it was built with.
_LIBS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "libs")
if _LIBS not in sys.path:
    sys.path.insert(0, _LIBS)


def classFactory(iface):  # noqa: N802 (QGIS API)
    """QGIS entry point."""
    from .plugin import Gf4calPlugin
    return Gf4calPlugin(iface)
'''

PLUGIN_PY = '''"""Plugin object: ``initProcessing`` registers the gf4cal Processing provider; no GUI code."""
from .processing_provider.plugin import Gf4calPlugin

__all__ = ["Gf4calPlugin"]
'''


def check_metadata(path: Path) -> dict:
    """Parse metadata.txt and check the keys QGIS's plugin repository requires."""
    cp = configparser.ConfigParser(interpolation=None)
    cp.read(path, encoding="utf-8")
    if "general" not in cp:
        raise SystemExit(f"{path}: no [general] section")
    md = dict(cp["general"])
    required = ("name", "qgisminimumversion", "description", "about", "version", "author", "email", "repository")
    missing = [k for k in required if not md.get(k)]
    if missing:
        raise SystemExit(f"{path}: missing {', '.join(missing)}")
    return md


def build(build_dir: Path, dist_dir: Path) -> Path:
    md = check_metadata(ROOT / "metadata.txt")
    build_dir.mkdir(parents=True, exist_ok=True)
    dist_dir.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{PLUGIN}.", dir=build_dir))
    try:
        dest = staging / PLUGIN
        dest.mkdir()
        (dest / "__init__.py").write_text(INIT_PY, encoding="utf-8")
        (dest / "plugin.py").write_text(PLUGIN_PY, encoding="utf-8")
        shutil.copy2(ROOT / "metadata.txt", dest / "metadata.txt")
        shutil.copytree(ROOT / "processing_provider", dest / "processing_provider", ignore=IGNORE)
        shutil.copytree(ROOT / "gdal_gf4cal", dest / "libs" / "gdal_gf4cal", ignore=IGNORE)
        for name in ("LICENSE", "LICENSE.txt", "COPYING", "README.md"):
            if (ROOT / name).exists():
                shutil.copy2(ROOT / name, dest / name)
        # zip (deterministic order and timestamps)
        tmp_zip = dist_dir / f".{PLUGIN}.zip.tmp"
        with zipfile.ZipFile(tmp_zip, "w", zipfile.ZIP_DEFLATED) as zf:
            for path in sorted(p for p in dest.rglob("*") if p.is_file()):
                info = zipfile.ZipInfo(str(path.relative_to(staging)), ZIP_DATE)
                info.external_attr = 0o644 << 16
                info.compress_type = zipfile.ZIP_DEFLATED
                zf.writestr(info, path.read_bytes())
        final = build_dir / PLUGIN
        old = None
        if final.exists():
            old = build_dir / f".{PLUGIN}.old"
            shutil.rmtree(old, ignore_errors=True)
            os.replace(final, old)
        os.replace(dest, final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        zip_path = dist_dir / f"{PLUGIN}.zip"
        os.replace(tmp_zip, zip_path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    print(f"built {final} and {zip_path} (version {md['version']})")
    return zip_path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--build-dir", default=str(ROOT / "build" / "plugin"), help="default: build/plugin")
    ap.add_argument("--dist-dir", default=str(ROOT / "dist"), help="default: dist")
    args = ap.parse_args(argv)
    build(Path(args.build_dir), Path(args.dist_dir))
    return 0


if __name__ == "__main__":
    sys.exit(main())
