"""``gf4cal:applycalibration`` - recalibrate the RPCs of other scenes for a calibrated camera."""
from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingOutputFile,
    QgsProcessingOutputMultipleLayers,
    QgsProcessingOutputNumber,
    QgsProcessingParameterFile,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterMultipleLayers,
)

from ..base import Gf4calAlgorithm


class ApplyCalibration(Gf4calAlgorithm):
    NAME = "applycalibration"
    DISPLAY = "Apply a camera calibration to other scenes"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("Recalibrates the RPC of every scene made with the current camera for the new camera (from 'Calibrate "
            "camera look angles'): for ground grid points the old RPC gives the old image point, the two cameras "
            "give the new one, and a new RPC is fitted (Pi et al. 2023). Writes <scene>.RPB (and <scene>.vrt "
            "over each untouched image) and report.json with each fit error and how far the image moved.")
    REFERENCES = ("pi", "tao")

    CURRENT_CAMERA = "CURRENT_CAMERA"
    NEW_CAMERA = "NEW_CAMERA"
    OUTPUT_FOLDER = "OUTPUT_FOLDER"

    def initAlgorithm(self, config=None):
        self._add(QgsProcessingParameterMultipleLayers(self.INPUT, self.tr("Scenes (images or RPC files)"),
                                                       QgsProcessing.TypeFile),
                  "Images with an RPC or RPC files of scenes made with the current camera.")
        self.add_rpc_pairs_parameter()
        self._add(QgsProcessingParameterFile(self.CURRENT_CAMERA, self.tr("Current camera file (JSON)"),
                                             extension="json"),
                  "The camera the scenes' RPCs were made with.")
        self._add(QgsProcessingParameterFile(self.NEW_CAMERA, self.tr("New camera file (JSON)"), extension="json"),
                  "The recalibrated camera (camera_new.json of the calibration).")
        self._add(QgsProcessingParameterFolderDestination(self.OUTPUT_FOLDER, self.tr("Output folder")),
                  "Folder receiving the recalibrated RPCs, VRTs and report.json.")
        self.addOutput(QgsProcessingOutputMultipleLayers("OUTPUT_RPCS", self.tr("Recalibrated RPC files")))
        self.addOutput(QgsProcessingOutputFile(self.OUTPUT_REPORT, self.tr("Report (JSON)")))
        self.addOutput(QgsProcessingOutputNumber("MAX_SHIFT_PX", self.tr("Largest image shift (px)")))
        self.addOutput(QgsProcessingOutputNumber("MAX_FIT_ERROR_PX", self.tr("Largest RPC fit error (px)")))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.workflows import apply_calibration

        scenes = self.parameterAsFileList(parameters, self.INPUT, context)
        if not scenes:
            raise self.error("Give at least one scene (INPUT).")
        current = self.parameterAsFile(parameters, self.CURRENT_CAMERA, context)
        new = self.parameterAsFile(parameters, self.NEW_CAMERA, context)
        folder = self.output_folder(parameters, self.OUTPUT_FOLDER, context)
        rep = apply_calibration(current, new, scenes, folder, overwrite=True, progress=progress,
                                rpcs=self.rpc_pairs(parameters, context))
        self.push_warnings(feedback, rep)
        rpcs, shift, fit_err = [], 0.0, 0.0
        for e in rep["scenes"]:
            fit = e["fit"]["check"] or e["fit"]["fit"]
            feedback.pushInfo(f"{e['scene']}: image moved by up to {e['image_shift_px']['max']:.2f} px; "
                              f"RPC fit max {fit['max_px']:.2e} px -> {e['rpb']}")
            rpcs.append(e["rpb"])
            shift, fit_err = max(shift, e["image_shift_px"]["max"]), max(fit_err, fit["max_px"])
            if e["vrt"]:
                self.load_on_completion(e["vrt"], f"{e['rpb']} (VRT)", "raster")
        return {self.OUTPUT_FOLDER: folder, "OUTPUT_RPCS": rpcs, self.OUTPUT_REPORT: rep["outputs"]["report"],
                "MAX_SHIFT_PX": shift, "MAX_FIT_ERROR_PX": fit_err}
