"""``gf4cal:applycalibrationbatch`` - recalibrate the RPCs of many scenes for a calibrated camera, resumable, on
threads or a Dask scheduler (issue 14)."""
from __future__ import annotations

from qgis.core import QgsProcessing, QgsProcessingParameterFile

from ..batch import BATCH_HELP, BatchAlgorithm


class ApplyCalibrationBatch(BatchAlgorithm):
    NAME = "applycalibrationbatch"
    DISPLAY = "Apply a camera calibration to an archive (many scenes, resumable)"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("Recalibrates the RPC of every scene made with the current camera for the new camera, as 'Apply a "
            "camera calibration to other scenes' does, scene by scene: <scene>.RPB (and <scene>.vrt over each "
            "untouched image) with, in the summary, how far each image moved and each refit's error." + BATCH_HELP)
    REFERENCES = ("pi", "tao")

    CURRENT_CAMERA = "CURRENT_CAMERA"
    NEW_CAMERA = "NEW_CAMERA"

    def initAlgorithm(self, config=None):
        self.add_scenes_parameter(QgsProcessing.TypeFile, "Scenes (images or RPC files)",
                                  "Images with an RPC or RPC files of scenes made with the current camera.")
        self._add(QgsProcessingParameterFile(self.CURRENT_CAMERA, self.tr("Current camera file (JSON)"),
                                             extension="json"),
                  "The camera the scenes' RPCs were made with.")
        self._add(QgsProcessingParameterFile(self.NEW_CAMERA, self.tr("New camera file (JSON)"), extension="json"),
                  "The recalibrated camera (camera_new.json of the calibration).")
        self.add_batch_parameters("Folder receiving <scene>.RPB (and <scene>.vrt) per scene.")

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.batch import apply_calibration_batch

        scenes = self.scenes(parameters, context, layers=False)
        current = self.parameterAsFile(parameters, self.CURRENT_CAMERA, context)
        new = self.parameterAsFile(parameters, self.NEW_CAMERA, context)
        outputs, _ = self.run_batch_job(parameters, context, feedback, progress, lambda ex, pr, ow, folder:
                                        apply_calibration_batch(current, new, scenes, folder, executor=ex,
                                                                overwrite=ow, progress=pr))
        return outputs
