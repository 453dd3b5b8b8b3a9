"""The QGIS algorithms run the engine's point kernels under QGIS's own thread setting (issue 23): QGIS's "max
cores" (QgsApplication.maxThreads; the Processing context's maximum threads where QGIS has one), all cores when QGIS
says -1. A probe algorithm built on the provider's base class reports what the kernels would use."""
from __future__ import annotations

import threading


def _probe_class():
    from processing_provider.base import Gf4calAlgorithm
    from gdal_gf4cal import threads

    class Probe(Gf4calAlgorithm):
        NAME = "threadprobe"
        DISPLAY = "Thread probe"

        def initAlgorithm(self, config=None):
            pass

        def run_algorithm(self, parameters, context, feedback, progress):
            return {"THREADS": threads.num_threads()}

    return Probe


def test_algorithms_use_qgis_thread_setting(qgis_app, monkeypatch):
    from qgis.core import QgsApplication, QgsProcessingContext, QgsProcessingFeedback
    from gdal_gf4cal import threads
    monkeypatch.delenv(threads.ENV, raising=False)
    probe = _probe_class()()
    previous = QgsApplication.maxThreads()
    got = {}
    try:
        for setting in (1, 2, -1):              # QGIS caps a setting at the machine's cores
            QgsApplication.setMaxThreads(setting)
            got[setting] = probe.processAlgorithm({}, QgsProcessingContext(), QgsProcessingFeedback())["THREADS"]
            # The setting is the algorithm's thread's only: another thread keeps the environment's.
            other = []
            t = threading.Thread(target=lambda: other.append(threads.num_threads()))
            t.start()
            t.join()
            assert other == [threads.machine_cores()]
    finally:
        QgsApplication.setMaxThreads(previous)
    assert got == {1: 1, 2: min(2, threads.machine_cores()), -1: threads.machine_cores()}
    assert threads.num_threads() == threads.machine_cores()     # nothing left behind in the caller
