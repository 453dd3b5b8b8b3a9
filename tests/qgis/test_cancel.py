"""QGIS cancel while the residual GeoPackage is being written (issue 11 "Faults: QGIS cancel"): the run stops inside
report/gpkg.py, says so in one line, and leaves no file behind: no output, no temporary of the output policy
(``.gf4cal-*``), no temporary GeoPackage of the writer (``.res.*.tmp.gpkg`` and its -journal/-wal)."""
from __future__ import annotations

import os
import sys

import pytest

GPKG_WRITER = os.path.join("gdal_gf4cal", "report", "gpkg.py")


def _writing_the_gpkg() -> bool:
    """True when report/gpkg.py is on the call stack (the GeoPackage is being written)."""
    f = sys._getframe(1)
    while f is not None:
        if f.f_code.co_filename.endswith(GPKG_WRITER):
            return True
        f = f.f_back
    return False


@pytest.mark.parametrize("alg", ["refinerpc", "assessaccuracy"])
def test_cancel_during_the_gpkg_write_leaves_nothing(qgis_app, scene, tmp_path, alg):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingException, QgsProcessingFeedback, QgsProject

    class CancelInGpkgWrite(QgsProcessingFeedback):
        """The user presses Cancel once the GeoPackage writer runs: isCanceled() turns true inside it."""

        def __init__(self):
            super().__init__()
            self.asked_in_writer = 0

        def isCanceled(self):
            if _writing_the_gpkg():
                self.asked_in_writer += 1
                return True
            return False

    files, _ = scene
    out = tmp_path / "out"                     # a folder the run creates: removed again
    params = {"INPUT": files["image"], "GCPS": files["gcps"], "OUTPUT_GPKG": str(out / "res.gpkg"),
              "OUTPUT_PLOT": str(out / "res.png"), "OUTPUT_REPORT": str(out / "report.json")}
    if alg == "refinerpc":
        params.update(MODEL=2, OUTPUT_RPC=str(out / "refined.RPB"))
    fb = CancelInGpkgWrite()
    ctx = QgsProcessingContext()
    ctx.setProject(QgsProject.instance())
    with pytest.raises(QgsProcessingException, match="[Cc]ancel"):
        processing.run(f"gf4cal:{alg}", params, feedback=fb, context=ctx)
    assert fb.asked_in_writer >= 1                # the cancel really came while the GeoPackage was written
    assert not out.exists(), sorted(os.listdir(out))
    assert os.listdir(tmp_path) == []
    assert not [n for n in os.listdir(os.path.dirname(files["image"])) if n.startswith(".")]
