"""The gf4cal Processing provider: id ``gf4cal``, one algorithm per module under :mod:`.algorithms`."""
from __future__ import annotations

import os

from qgis.core import QgsProcessingProvider
from qgis.PyQt.QtGui import QIcon

from .algorithms import ALGORITHMS

PROVIDER_ID = "gf4cal"


class Gf4calProvider(QgsProcessingProvider):
    """RPC calibration of optical satellite images (gdal_gf4cal) as QGIS Processing algorithms."""

    def id(self) -> str:
        return PROVIDER_ID

    def name(self) -> str:
        return "GF4 RPC calibration"

    def longName(self) -> str:
        import gdal_gf4cal
        return f"GF4 RPC calibration (gdal_gf4cal {gdal_gf4cal.__version__})"

    def icon(self):
        path = os.path.join(os.path.dirname(__file__), "icon.svg")
        return QIcon(path) if os.path.exists(path) else super().icon()

    def svgIconPath(self) -> str:
        path = os.path.join(os.path.dirname(__file__), "icon.svg")
        return path if os.path.exists(path) else super().svgIconPath()

    def loadAlgorithms(self):
        for cls in ALGORITHMS:
            self.addAlgorithm(cls())
