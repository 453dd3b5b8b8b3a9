"""``gf4cal:registerpanms`` - register an MS image to its pan for halo-free pan-sharpening (Zhang et al. 2023)."""
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


def _style_limit(rep) -> float:
    """Half-range of the correction's colour ramp: the larger RMS about zero of the cells before the model, x2."""
    st = rep["steps"][0]
    return max(0.05, 2.0 * max(st["rms_sample_px"] or 0.0, st["rms_line_px"] or 0.0))


class RegisterPanMs(Gf4calAlgorithm):
    NAME = "registerpanms"
    DISPLAY = "Register MS to pan (pan-sharpening without halos)"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("Measures how the multispectral image misregisters with the panchromatic image of the same scene "
            "(through their RPCs and the DEM, dense matching averaged per cell), models it (linear + a quartic per "
            "sub-CCD with jumps at the sub-CCD edges + jitter sines; GF-7, Zhang et al. 2023) and writes, in "
            "the output folder: ms_on_pan.tif (the MS bands resampled onto the pan's raw grid at MS resolution: "
            "give it with the pan to GDAL's pansharpening), correction.tif (delta sample / delta line at every MS "
            "pixel), model.json (reusable on cloudy scenes of the same camera), ms_approx.RPB (a smooth refitted "
            "MS RPC, its error in the report), report.json, cells.gpkg (cell residuals as arrows) and plots.")
    REFERENCES = ("zhang",)

    PAN = "PAN"
    MS = "MS"
    SUB_CCDS = "SUB_CCDS"
    BREAKS = "BREAKS"
    CELL = "CELL"
    JITTER = "JITTER"
    REUSE = "REUSE"
    PAN_RPC = "PAN_RPC"
    MS_RPC = "MS_RPC"
    OUTPUT_FOLDER = "OUTPUT_FOLDER"

    def initAlgorithm(self, config=None):
        self._add(QgsProcessingParameterRasterLayer(self.PAN, self.tr("Panchromatic image (with its RPC)")),
                  "The raw panchromatic image of the scene, with its RPC.")
        self._add(QgsProcessingParameterRasterLayer(self.MS, self.tr("Multispectral image (with its RPC)")),
                  "The raw multispectral image of the same scene, with its RPC; its size times an integer ratio "
                  "is the pan's.")
        self.add_dem_parameters(optional=False)
        self._add(QgsProcessingParameterNumber(self.SUB_CCDS, self.tr("Sub-CCDs per MS band (0: from the data)"),
                                               QgsProcessingParameterNumber.Integer, 0, minValue=0),
                  "Number of equal sub-CCDs of each MS band (GF7: 3), counted on the full product when the crop's "
                  "place in it is known; 0: the edges found in the data (jumps that pass a test), else one piece; "
                  "ignored when sub-CCD edges are given.")
        self._add(QgsProcessingParameterString(self.BREAKS, self.tr("Sub-CCD edges (MS columns, optional)"),
                                               optional=True),
                  "MS columns of the sub-CCD edges separated by commas, e.g. 2560,5120 (instead of equal pieces).")
        self._add(QgsProcessingParameterNumber(self.CELL, self.tr("Cell size (MS px, 0: from the image)"),
                                               QgsProcessingParameterNumber.Integer, 0, minValue=0),
                  "The matches are averaged per cell of this size (MS pixels, >= 4); 0 chooses it from the MS size "
                  "and texture (enough usable cells per sub-CCD piece for every term).")
        self._add(QgsProcessingParameterString(self.JITTER, self.tr("Jitter components (auto, none or N)"),
                                               defaultValue="auto"),
                  "auto: sines picked from the residual spectrum while significant; none; or N per axis.")
        self._add(QgsProcessingParameterFile(self.REUSE, self.tr("Reuse model (optional)"), optional=True,
                                             fileFilter="Pan-MS model (*.json)"),
                  "model.json of a clear scene of the same camera: keep its sub-CCD term and solve only the linear "
                  "term from <= 200 sparse matches (for cloudy or watery scenes).")
        for key, label in ((self.PAN_RPC, "Pan RPC file (optional)"), (self.MS_RPC, "MS RPC file (optional)")):
            self._add(QgsProcessingParameterFile(key, self.tr(label), optional=True),
                      "When the image carries no RPC: an OSSIM .geom, DIMAP RPC_*.XML, .RPB, ... (default: the "
                      "image's own, or a .geom named like it beside it). A crop stating its origin in the product "
                      "gets the product's RPC shifted.")
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
        from gdal_gf4cal.report.styles import diverging_raster_qml
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
        n_sub = self.parameterAsInt(parameters, self.SUB_CCDS, context)
        cell = self.parameterAsInt(parameters, self.CELL, context)
        rep = register_pan_ms(pan.source(), ms.source(), dem=dem, out=folder, breaks=breaks,
                              n_sub_ccds=None if breaks or not n_sub else n_sub, cell=cell or None,
                              jitter=self.parameterAsString(parameters, self.JITTER, context).strip() or "auto",
                              reuse=reuse, overwrite=True, progress=progress,
                              pan_rpc=self.parameterAsFile(parameters, self.PAN_RPC, context) or None,
                              ms_rpc=self.parameterAsFile(parameters, self.MS_RPC, context) or None)
        self.push_warnings(feedback, rep)
        for st in rep["steps"]:
            feedback.pushInfo(f"{st['step']}: rms {st['rms_sample_px']:.3f} / {st['rms_line_px']:.3f} MS px, "
                              f"P(<=0.25) {100 * st['p_le_0.25']:.1f} %")
        paths = rep["outputs"]
        self.load_on_completion(paths["ms_on_pan"], "MS on the pan grid", "raster")
        lim = _style_limit(rep)
        for band, what in ((1, "sample"), (2, "line")):
            self.load_on_completion(paths["correction"], f"pan-MS correction, {what} (MS px)", "raster",
                                    style=diverging_raster_qml(band, lim))
        self.load_gpkg_on_completion(paths["cells"])
        last = rep["steps"][-1]
        return {self.OUTPUT_FOLDER: folder, "OUTPUT_MS_ON_PAN": paths["ms_on_pan"],
                "OUTPUT_CORRECTION": paths["correction"], "OUTPUT_MODEL": paths["model"],
                "OUTPUT_REPORT": paths["report"], "RMS_SAMPLE_AFTER": last["rms_sample_px"],
                "RMS_LINE_AFTER": last["rms_line_px"], "P_AFTER": last["p_le_0.25"]}
