"""``gf4cal:registerpanms`` - register an MS image to its pan for halo-free pan-sharpening (METHODS §9)."""
from __future__ import annotations

from qgis.core import (
    QgsProcessingOutputFile,
    QgsProcessingOutputNumber,
    QgsProcessingParameterFile,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterLayer,
    QgsProcessingParameterString,
)

from ..base import Gf4calAlgorithm


class RegisterPanMs(Gf4calAlgorithm):
    NAME = "registerpanms"
    DISPLAY = "Register MS to pan (pan-sharpening without halos)"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("Measures how the multispectral image misregisters with the panchromatic image of the same scene "
            "(through their RPCs and the DEM, dense matching averaged per cell), models it (linear + a quartic per "
            "sub-CCD with jumps at the sub-CCD edges + jitter sines, METHODS §9 of the GF7 method) and writes, in "
            "the output folder: ms_on_pan.tif (the MS bands resampled onto the pan's raw grid at MS resolution: "
            "give it with the pan to GDAL's pansharpening), correction.tif (delta sample / delta line at every MS "
            "pixel), model.json (reusable on cloudy scenes of the same camera), ms_approx.RPB (a smooth refitted "
            "MS RPC, its error in the report), report.json, cells.gpkg (cell residuals as arrows) and plots.")

    PAN = "PAN"
    MS = "MS"
    SUB_CCDS = "SUB_CCDS"
    BREAKS = "BREAKS"
    CELL = "CELL"
    JITTER = "JITTER"
    REUSE = "REUSE"
    OUTPUT_FOLDER = "OUTPUT_FOLDER"

    def initAlgorithm(self, config=None):
        self._add(QgsProcessingParameterRasterLayer(self.PAN, self.tr("Panchromatic image (with its RPC)")),
                  "The raw panchromatic image of the scene, with its RPC.")
        self._add(QgsProcessingParameterRasterLayer(self.MS, self.tr("Multispectral image (with its RPC)")),
                  "The raw multispectral image of the same scene, with its RPC; its size times an integer ratio "
                  "is the pan's.")
        self.add_dem_parameters(optional=False)
        self._add(QgsProcessingParameterNumber(self.SUB_CCDS, self.tr("Sub-CCDs per MS band"),
                                               QgsProcessingParameterNumber.Integer, 3, minValue=1),
                  "Number of equal sub-CCDs of each MS band (GF7: 3); ignored when sub-CCD edges are given.")
        self._add(QgsProcessingParameterString(self.BREAKS, self.tr("Sub-CCD edges (MS columns, optional)"),
                                               optional=True),
                  "MS columns of the sub-CCD edges separated by commas, e.g. 2560,5120 (instead of equal pieces).")
        self._add(QgsProcessingParameterNumber(self.CELL, self.tr("Cell size (MS px)"),
                                               QgsProcessingParameterNumber.Integer, 64, minValue=8),
                  "The matches are averaged per cell of this size (MS pixels).")
        self._add(QgsProcessingParameterString(self.JITTER, self.tr("Jitter components (auto, none or N)"),
                                               defaultValue="auto"),
                  "auto: sines picked from the residual spectrum while significant; none; or N per axis.")
        self._add(QgsProcessingParameterFile(self.REUSE, self.tr("Reuse model (optional)"), optional=True,
                                             fileFilter="Pan-MS model (*.json)"),
                  "model.json of a clear scene of the same camera: keep its sub-CCD term and solve only the linear "
                  "term from <= 200 sparse matches (for cloudy or watery scenes).")
        self._add(QgsProcessingParameterFolderDestination(self.OUTPUT_FOLDER, self.tr("Output folder")),
                  "Folder receiving ms_on_pan.tif, correction.tif, model.json, ms_approx.RPB, report.json, "
                  "cells.gpkg and the plots.")
        for key, label in (("OUTPUT_MS_ON_PAN", "MS resampled onto the pan grid"),
                           ("OUTPUT_CORRECTION", "Correction grid"), ("OUTPUT_MODEL", "Model (JSON)"),
                           ("OUTPUT_REPORT", "Report (JSON)")):
            self.addOutput(QgsProcessingOutputFile(key, self.tr(label)))
        for key, label in (("RMS_SAMPLE_AFTER", "Cell RMS after the model, sample (MS px)"),
                           ("RMS_LINE_AFTER", "Cell RMS after the model, line (MS px)"),
                           ("P_AFTER", "Share of cells within 0.25 MS px after the model")):
            self.addOutput(QgsProcessingOutputNumber(key, self.tr(label)))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.workflows import register_pan_ms
        pan = self.parameterAsRasterLayer(parameters, self.PAN, context)
        ms = self.parameterAsRasterLayer(parameters, self.MS, context)
        if pan is None or ms is None:
            raise self.error("Choose the panchromatic (PAN) and multispectral (MS) images.")
        dem = self.read_dem(parameters, context)
        if dem is None:
            raise self.error("Choose a DEM covering the scene (DEM).")
        breaks = self.parameterAsString(parameters, self.BREAKS, context).strip() or None
        reuse = self.parameterAsFile(parameters, self.REUSE, context) or None
        folder = self.output_folder(parameters, self.OUTPUT_FOLDER, context)
        rep = register_pan_ms(pan.source(), ms.source(), dem=dem, out=folder, breaks=breaks,
                              n_sub_ccds=None if breaks else self.parameterAsInt(parameters, self.SUB_CCDS, context),
                              cell=self.parameterAsInt(parameters, self.CELL, context),
                              jitter=self.parameterAsString(parameters, self.JITTER, context).strip() or "auto",
                              reuse=reuse, overwrite=True, progress=progress)
        self.push_warnings(feedback, rep)
        for st in rep["steps"]:
            feedback.pushInfo(f"{st['step']}: rms {st['rms_sample_px']:.3f} / {st['rms_line_px']:.3f} MS px, "
                              f"P(<=0.25) {100 * st['p_le_0.25']:.1f} %")
        paths = rep["outputs"]
        self.load_gpkg_on_completion(paths["cells"])
        self.load_on_completion(paths["ms_on_pan"], "MS on the pan grid", "raster")
        last = rep["steps"][-1]
        return {self.OUTPUT_FOLDER: folder, "OUTPUT_MS_ON_PAN": paths["ms_on_pan"],
                "OUTPUT_CORRECTION": paths["correction"], "OUTPUT_MODEL": paths["model"],
                "OUTPUT_REPORT": paths["report"], "RMS_SAMPLE_AFTER": last["rms_sample_px"],
                "RMS_LINE_AFTER": last["rms_line_px"], "P_AFTER": last["p_le_0.25"]}
