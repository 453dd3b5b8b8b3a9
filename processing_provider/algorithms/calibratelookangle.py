"""``gf4cal:calibratelookangle`` - calibrate an area-array camera's look angles from a scene's RPC and GCPs
(Pi et al. 2023) and write the new camera file and the recalibrated RPC."""
from __future__ import annotations

import os

from qgis.core import (
    QgsProcessingOutputFile,
    QgsProcessingOutputNumber,
    QgsProcessingOutputRasterLayer,
    QgsProcessingOutputVectorLayer,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterFile,
    QgsProcessingParameterFolderDestination,
)

from ..base import Gf4calAlgorithm, planar_rms


class CalibrateLookAngle(Gf4calAlgorithm):
    NAME = "calibratelookangle"
    DISPLAY = "Calibrate camera look angles from the RPC (GF4 method)"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("On-orbit calibration of an area-array camera's detector look-angle model (cubic in the detector "
            "numbers) from one scene's RPC, the camera file the RPC was made with and GCPs (Pi et al. 2023). Writes "
            "camera_new.json, the recalibrated RPC (<scene>.RPB, and <scene>.vrt over the untouched image when "
            "INPUT is an image), residuals.gpkg (styled GCPs and residual arrows), residuals.png, report.json and "
            "the GCPs used (gcps_used.csv). Without a vendor camera file, a nominal one (focal length, pixel size) "
            "gives an equally good recalibrated RPC.")
    REFERENCES = ("pi", "tao")

    CAMERA = "CAMERA"
    ROBUST = "ROBUST"
    OUTPUT_FOLDER = "OUTPUT_FOLDER"

    def initAlgorithm(self, config=None):
        self.add_input_image("Scene image (with the RPC made with the camera)")
        self.add_rpc_parameter()
        self.add_gcp_parameters()
        self._add(QgsProcessingParameterFile(self.CAMERA, self.tr("Current camera file (JSON)"),
                                             behavior=QgsProcessingParameterFile.File, extension="json"),
                  'The look-angle camera the RPC was made with: {"model": "lookangle-cubic", "size": [W, H], '
                  '"x": [...], "y": [...]}.')
        self.add_dem_parameters()
        p = self._add(QgsProcessingParameterBoolean(self.ROBUST, self.tr("Robust estimation (flag blunders)"),
                                                    defaultValue=True),
                      "Reweight iteratively and flag blunders; off = plain least squares.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        self.add_plausibility_parameter()
        self._add(QgsProcessingParameterFolderDestination(self.OUTPUT_FOLDER, self.tr("Output folder")),
                  "Folder receiving camera_new.json, the recalibrated RPC, residuals and report.")
        self.addOutput(QgsProcessingOutputFile("OUTPUT_CAMERA", self.tr("New camera file")))
        self.addOutput(QgsProcessingOutputFile(self.OUTPUT_RPC, self.tr("Recalibrated RPC (.RPB)")))
        self.addOutput(QgsProcessingOutputRasterLayer("OUTPUT_VRT", self.tr("Image with the recalibrated RPC")))
        self.addOutput(QgsProcessingOutputVectorLayer(self.OUTPUT_GPKG, self.tr("Residuals GeoPackage")))
        self.addOutput(QgsProcessingOutputFile(self.OUTPUT_PLOT, self.tr("Residual plot")))
        self.addOutput(QgsProcessingOutputFile(self.OUTPUT_REPORT, self.tr("Report (JSON)")))
        for key, label in (("CONTROL_RMS_BEFORE", "Control RMS before (px, planar)"),
                           ("CONTROL_RMS_AFTER", "Control RMS after (px, planar)"),
                           ("CHECK_RMS_BEFORE", "Check RMS before (px, planar)"),
                           ("CHECK_RMS_AFTER", "Check RMS after (px, planar)"),
                           ("N_OUTLIERS", "Number of flagged outliers"), ("ITERATIONS", "Iterations"),
                           ("CONDITION_NUMBER", "Condition number of the GCP layout")):
            self.addOutput(QgsProcessingOutputNumber(key, self.tr(label)))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.describe import image_size_of
        from gdal_gf4cal.workflows import calibrate_lookangle_files

        source = self.input_path(parameters, context)
        camera = self.parameterAsFile(parameters, self.CAMERA, context)
        if not camera or not os.path.exists(camera):
            raise self.error("Give the camera file the RPC was made with (CAMERA).")
        dem = self.read_dem(parameters, context)
        gcps = self.read_gcps(parameters, context, feedback, dem=dem)  # heights filled from the DEM here
        folder = self.output_folder(parameters, self.OUTPUT_FOLDER, context)
        image = source if image_size_of(source) is not None else None
        rpc = self.rpc_file(parameters, context)
        if rpc and image is None:
            raise self.error("An RPC file (RPC) pairs with an image: give the scene's image as INPUT.")
        rep = calibrate_lookangle_files(rpc or source, gcps, camera, folder, image=image, robust=self.parameterAsBool(
            parameters, self.ROBUST, context), overwrite=True, progress=progress,
            check_plausibility=self.check_plausibility(parameters, context))
        self.push_warnings(feedback, rep)
        cal, paths = rep["calibration"], rep["outputs"]
        feedback.pushInfo(f"{cal['n_control']} control GCPs, {cal['n_outliers']} outliers, {cal['iterations']} "
                          f"iterations, condition number {cal['condition_number']:.3g}")
        for ident in cal.get("outlier_ids", []):
            feedback.pushWarning(f"outlier {ident}")
        self.load_gpkg_on_completion(paths["residuals_gpkg"])
        if paths.get("vrt"):
            self.load_on_completion(paths["vrt"], "Recalibrated image (VRT)", "raster")
        out = {self.OUTPUT_FOLDER: folder, "OUTPUT_CAMERA": paths["camera"], self.OUTPUT_RPC: paths["rpb"],
               "OUTPUT_VRT": paths.get("vrt"), self.OUTPUT_GPKG: paths["residuals_gpkg"],
               self.OUTPUT_PLOT: paths["residuals_png"], self.OUTPUT_REPORT: paths["report"],
               "N_OUTLIERS": cal["n_outliers"], "ITERATIONS": cal["iterations"],
               "CONDITION_NUMBER": cal["condition_number"]}
        for role in ("control", "check"):
            st = cal.get(role) or {}
            out[f"{role.upper()}_RMS_BEFORE"] = planar_rms(dict(st.get("before", {}), n=st.get("n")))
            out[f"{role.upper()}_RMS_AFTER"] = planar_rms(dict(st.get("after", {}), n=st.get("n")))
        return out
