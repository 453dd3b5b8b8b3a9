"""The QGIS plugin object: registers the Processing provider and nothing else (headless-safe, no GUI code).

QGIS calls ``initProcessing`` (also from ``qgis_process``) and ``initGui`` (desktop only); both only register the
provider, so every algorithm is available wherever Processing is.
"""
from __future__ import annotations

from qgis.core import QgsApplication

from .provider import Gf4calProvider


class Gf4calPlugin:
    """Plugin entry point returned by ``classFactory(iface)``; ``iface`` is unused (may be None headless)."""

    def __init__(self, iface=None):
        self.iface = iface
        self.provider = None

    def initProcessing(self):
        if self.provider is None:
            self.provider = Gf4calProvider()
            QgsApplication.processingRegistry().addProvider(self.provider)

    def initGui(self):
        self.initProcessing()

    def unload(self):
        if self.provider is not None:
            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
