"""``gf4cal:collectgcpsbatch`` - automatic GCPs for many scenes against one reference and DEM (issues 7, 14)."""
from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterRasterLayer,
)

from ..batch import BATCH_HELP, BatchAlgorithm
from .collectgcps import add_matching_parameters, matching_options



class CollectGcpsBatch(BatchAlgorithm):
    NAME = "collectgcpsbatch"
    DISPLAY = "Collect GCPs by matching a reference orthophoto (many scenes)"
    GROUP = "Control points"
    GROUP_ID = "gcps"
    HELP = ("Collects GCPs for many raw images (each with its RPC) against one reference orthophoto and DEM, as "
            "'Collect GCPs by matching a reference orthophoto' does for one: <scene>.gpkg per scene (fields id, "
            "lon, lat, h, sample, line, role, sigma + quality), ready for 'Refine RPC (many scenes)'." + BATCH_HELP)

    REFERENCE = "REFERENCE"
    SPACING = "SPACING"
    WINDOW = "WINDOW"
    SEARCH = "SEARCH"
    OUTLIER_MODEL = "OUTLIER_MODEL"
    KEEP_OUTLIERS = "KEEP_OUTLIERS"
    SEED = "SEED"

    def initAlgorithm(self, config=None):
        self.add_scenes_parameter(QgsProcessing.TypeRaster, "Raw images (with RPCs)",
                                  "Raw images, each carrying its RPC (TIFF tags, .RPB or _RPC.TXT beside it, NITF).")
        self._add(QgsProcessingParameterRasterLayer(self.REFERENCE, self.tr("Reference orthophoto")),
                  "Georeferenced reference image covering the scenes (any GDAL raster, any CRS).")
        self._add(QgsProcessingParameterRasterLayer(self.DEM, self.tr("DEM")),
                  "Height model covering the scenes (any GDAL raster, any CRS).")
        self.add_geoid_parameters()
        add_matching_parameters(self)
        self._add(QgsProcessingParameterBoolean(self.KEEP_OUTLIERS, self.tr("Keep flagged outliers"),
                                                defaultValue=False),
                  "Also write the rejected matches (field outlier = true); by default only the inliers.")
        self.add_batch_parameters("Folder receiving <scene>.gpkg per scene.")

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.batch import collect_gcps_batch

        scenes = self.scenes(parameters, context, layers=True)
        ref = self.parameterAsRasterLayer(parameters, self.REFERENCE, context)
        dem = self.parameterAsRasterLayer(parameters, self.DEM, context)
        if ref is None or dem is None:
            raise self.error("Give the reference orthophoto (REFERENCE) and the DEM (DEM).")
        opts = dict(geoid=self.geoid_choice(parameters, context),
                    keep_outliers=self.parameterAsBool(parameters, self.KEEP_OUTLIERS, context),
                    **matching_options(self, parameters, context))
        outputs, _ = self.run_batch_job(parameters, context, feedback, progress, lambda ex, pr, ow, folder:
                                        collect_gcps_batch(scenes, ref.source(), dem.source(), folder, executor=ex,
                                                           overwrite=ow, progress=pr, **opts))
        return outputs
