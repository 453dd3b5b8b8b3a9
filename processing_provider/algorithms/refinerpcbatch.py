"""``gf4cal:refinerpcbatch`` - refine the RPCs of many scenes, each with its own GCP table (issue 14)."""
from __future__ import annotations

from qgis.core import QgsProcessing, QgsProcessingParameterEnum, QgsProcessingParameterFile

from ..batch import BATCH_HELP, BatchAlgorithm
from .refinerpc import MODEL_LABELS, MODELS

OUT_EXTS = [".RPB", "_RPC.TXT", ".vrt"]


class RefineRpcBatch(BatchAlgorithm):
    NAME = "refinerpcbatch"
    DISPLAY = "Refine RPC with GCPs (many scenes)"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("Refines the RPC of many scenes as 'Refine RPC with GCPs' does for one, each with its own GCP table "
            "<scene>.gpkg from the GCP folder (what 'Collect GCPs ... (many scenes)' writes): <scene>.RPB (or "
            "_RPC.TXT, or a VRT over the untouched image) and <scene>.report.json per scene, the accuracy before "
            "and after in the summary." + BATCH_HELP)
    REFERENCES = ("grodecki", "fraser", "huang", "tao")

    GCP_FOLDER = "GCP_FOLDER"
    MODEL = "MODEL"
    FORMAT = "FORMAT"

    def initAlgorithm(self, config=None):
        self.add_scenes_parameter(QgsProcessing.TypeRaster, "Images (with RPCs)",
                                  "Images, each carrying its RPC; each needs <scene>.gpkg in the GCP folder.")
        self._add(QgsProcessingParameterFile(self.GCP_FOLDER, self.tr("GCP folder"),
                                             behavior=QgsProcessingParameterFile.Folder),
                  "Folder holding one GCP table <scene>.gpkg per scene (fields sample, line, h, id, role).")
        self._add(QgsProcessingParameterEnum(self.MODEL, self.tr("Compensation model"), MODEL_LABELS,
                                             defaultValue=MODELS.index("auto")),
                  "Image-space correction estimated per scene, as in 'Refine RPC with GCPs' (same models, same "
                  "default: Automatic, the simplest model the leave-one-out error supports).")
        self._add(QgsProcessingParameterEnum(self.FORMAT, self.tr("Refined RPC format"), OUT_EXTS, defaultValue=0),
                  "RPB, _RPC.TXT or a VRT over the untouched image carrying the refined RPC.")
        self.add_plausibility_parameter()
        self.add_batch_parameters("Folder receiving the refined RPC and report.json per scene.")

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.batch import refine_batch

        scenes = self.scenes(parameters, context, layers=True)
        gcps_dir = self.parameterAsFile(parameters, self.GCP_FOLDER, context)
        model = MODELS[self.parameterAsEnum(parameters, self.MODEL, context)]
        ext = OUT_EXTS[self.parameterAsEnum(parameters, self.FORMAT, context)]
        check = self.check_plausibility(parameters, context)
        outputs, _ = self.run_batch_job(parameters, context, feedback, progress, lambda ex, pr, ow, folder:
                                        refine_batch(scenes, gcps_dir, model, folder, out_ext=ext, executor=ex,
                                                     overwrite=ow, progress=pr, check_plausibility=check))
        return outputs
