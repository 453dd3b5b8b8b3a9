"""What the batch algorithms share (issue 14): many scenes, an output folder, a resumable batch summary, threads
or a Dask scheduler. Thin: parameters -> one :mod:`gdal_gf4cal.batch` call -> outputs and feedback."""
from __future__ import annotations

import os
import sys

from qgis.core import (
    QgsProcessingOutputFile,
    QgsProcessingOutputNumber,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterMultipleLayers,
    QgsProcessingParameterNumber,
    QgsProcessingParameterString,
)

from gdal_gf4cal.errors import CancelledError

from .base import Gf4calAlgorithm

BATCH_HELP = (" One output per scene is written to the output folder, named after the scene, and "
              "batch_summary.csv/.json there says for each scene ok, failed (with the reason), skipped (finished "
              "by an earlier run) or cancelled. A failing scene does not stop the others; running again skips "
              "the finished scenes unless 'Redo finished scenes' is checked. Cancelling keeps the finished "
              "scenes; the running ones leave nothing behind.")


class BatchAlgorithm(Gf4calAlgorithm):
    """Base of the batch algorithms: ``INPUT`` (many scenes), ``OUTPUT_FOLDER``, ``THREADS``, ``DASK``,
    ``OVERWRITE``; outputs ``SUMMARY``, ``N_OK``, ``N_FAILED``, ``N_SKIPPED``."""

    OUTPUT_FOLDER = "OUTPUT_FOLDER"
    THREADS = "THREADS"
    DASK = "DASK"
    OVERWRITE = "OVERWRITE"
    SUMMARY = "SUMMARY"

    def add_scenes_parameter(self, layer_type, description, help_text):
        self._add(QgsProcessingParameterMultipleLayers(self.INPUT, self.tr(description), layer_type), help_text)

    def add_batch_parameters(self, output_help: str):
        Num = QgsProcessingParameterNumber
        self._add(QgsProcessingParameterFolderDestination(self.OUTPUT_FOLDER, self.tr("Output folder")),
                  output_help + " Also receives batch_summary.csv and batch_summary.json.")
        p = self._add(Num(self.THREADS, self.tr("Scenes in parallel (threads)"), Num.Integer, 2, minValue=1),
                      "Scenes run at the same time in QGIS's process (1: one after the other).")
        p.setFlags(p.flags() | p.FlagAdvanced)
        p = self._add(QgsProcessingParameterString(self.DASK, self.tr("Dask scheduler (optional)"), optional=True),
                      "Address of a running Dask scheduler (tcp://HOST:PORT, started with `dask scheduler` and "
                      "`dask worker` on machines that see the same files): the scenes run on its workers "
                      "instead of QGIS's threads. Empty: threads.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        self._add(QgsProcessingParameterBoolean(self.OVERWRITE, self.tr("Redo finished scenes"), defaultValue=False),
                  "Run the scenes whose outputs already exist again (replacing them) instead of skipping them.")
        self.addOutput(QgsProcessingOutputFile(self.SUMMARY, self.tr("Batch summary (CSV)")))
        for key, label in (("N_OK", "Scenes done"), ("N_FAILED", "Scenes failed"),
                           ("N_SKIPPED", "Scenes already done")):
            self.addOutput(QgsProcessingOutputNumber(key, self.tr(label)))

    def scenes(self, parameters, context, layers: bool):
        """The scene paths of INPUT (raster layers' sources or file paths)."""
        if layers:
            items = [lyr.source() for lyr in self.parameterAsLayerList(parameters, self.INPUT, context)]
        else:
            items = self.parameterAsFileList(parameters, self.INPUT, context)
        if not items:
            raise self.error("Give at least one scene (INPUT).")
        return items

    def executor_spec(self, parameters, context) -> str:
        spec = (self.parameterAsString(parameters, self.DASK, context) or "").strip()
        if not spec:
            return f"threads:{self.parameterAsInt(parameters, self.THREADS, context)}"
        if spec.startswith("local") and not os.path.basename(sys.executable).startswith("python"):
            # A LocalCluster starts worker processes from sys.executable: inside QGIS that is QGIS itself.
            raise self.error("A local Dask cluster cannot be started from inside QGIS; start one with `dask "
                             "scheduler` and `dask worker` and give its tcp://HOST:PORT address (DASK).")
        return spec

    def run_batch_job(self, parameters, context, feedback, progress, job):
        """Run ``job(executor, progress, overwrite)`` (a :mod:`gdal_gf4cal.batch` call returning its report) and
        turn its rows into feedback and outputs."""
        from gdal_gf4cal.batch import SUMMARY_CSV
        from gdal_gf4cal.executors import get_executor
        folder = self.output_folder(parameters, self.OUTPUT_FOLDER, context)
        overwrite = self.parameterAsBool(parameters, self.OVERWRITE, context)
        try:
            with get_executor(self.executor_spec(parameters, context)) as ex:
                rep = job(ex, progress, overwrite, folder)
        except CancelledError:
            raise self.error(f"Cancelled; the finished scenes are kept in {folder}, {SUMMARY_CSV} there says "
                             "which were cancelled; run again to finish them.") from None
        for r in rep["scenes"]:
            if r["status"] == "failed":
                feedback.reportError(f"{r['scene']}: {r['error']}", False)
            else:
                figures = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                    for k, v in r.items() if k not in ("scene", "status", "outputs", "error",
                                                                       "seconds"))
                feedback.pushInfo(f"{r['scene']}: {r['status']} ({figures})")
        c = rep["counts"]
        feedback.pushInfo(f"{c['ok']} scenes done, {c['failed']} failed, {c['skipped']} already done; summary: "
                          f"{rep['summary']['csv']}")
        return {self.OUTPUT_FOLDER: folder, self.SUMMARY: rep["summary"]["csv"], "N_OK": c["ok"],
                "N_FAILED": c["failed"], "N_SKIPPED": c["skipped"]}, rep
