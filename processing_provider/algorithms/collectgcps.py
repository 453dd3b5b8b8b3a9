"""``gf4cal:collectgcps`` - automatic GCPs: sub-pixel matching of the raw image against a reference orthophoto and
a DEM (issue 7). The output feeds refinerpc and calibratelookangle directly."""
from __future__ import annotations

from qgis.core import (
    QgsProcessingOutputNumber,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterLayer,
)

from ..base import Gf4calAlgorithm

OUTLIER_MODELS = ["translation", "affine", "poly2", "poly3"]


def add_matching_parameters(alg) -> None:
    """The matching parameters (SPACING, WINDOW, SEARCH, OUTLIER_MODEL, SEED) of ``alg``: one declaration for the
    single-scene and the batch algorithm."""
    Num = QgsProcessingParameterNumber
    alg._add(Num(alg.SPACING, alg.tr("Grid spacing (px)"), Num.Integer, None, optional=True, minValue=8),
             "Distance between window centres in raw image pixels. Empty: 256, finer on images under ~1,900 px "
             "(eight windows across the shorter side, never closer than a window).")
    alg._add(Num(alg.WINDOW, alg.tr("Window size (px)"), Num.Integer, 64, minValue=16, maxValue=1024),
             "Matching window size in raw image pixels (even).")
    for p, text in ((Num(alg.SEARCH, alg.tr("Largest initial offset (px)"), Num.Double, 64.0, minValue=1.0),
                     "Largest offset between the RPC's prediction and the truth to search for."),
                    (QgsProcessingParameterEnum(alg.OUTLIER_MODEL, alg.tr("Outlier rejection model"), OUTLIER_MODELS,
                                                defaultValue=1),
                     "Low-order image model for RANSAC + MAD outlier rejection."),
                    (Num(alg.SEED, alg.tr("RANSAC seed"), Num.Integer, 0, minValue=0),
                     "Seed of the RANSAC outlier filter (same seed, same result).")):
        alg._add(p, text).setFlags(p.flags() | p.FlagAdvanced)


def matching_options(alg, parameters, context) -> dict:
    """The engine keywords of the parameters :func:`add_matching_parameters` declared."""
    return dict(spacing_px=alg.parameterAsInt(parameters, alg.SPACING, context) or None,   # unset: 0, the default
                window_px=alg.parameterAsInt(parameters, alg.WINDOW, context),
                search_px=alg.parameterAsDouble(parameters, alg.SEARCH, context),
                outlier_model=OUTLIER_MODELS[alg.parameterAsEnum(parameters, alg.OUTLIER_MODEL, context)],
                seed=alg.parameterAsInt(parameters, alg.SEED, context))


class CollectGcps(Gf4calAlgorithm):
    NAME = "collectgcps"
    DISPLAY = "Collect GCPs by matching a reference orthophoto"
    GROUP = "Control points"
    GROUP_ID = "gcps"
    HELP = ("Finds GCPs automatically: on a grid of windows of the raw image, the reference orthophoto (any raster, "
            "any CRS and resolution) is resampled into the raw image's geometry through the RPC and the DEM and "
            "matched by sub-pixel phase correlation (coarse to fine, so initial offsets of 50 px and more are "
            "found). Windows on no-data, water, clouds or featureless texture are skipped; outliers are rejected "
            "against a low-order model (RANSAC + MAD, seeded). The GCP table (fields id, lon, lat, h, sample, line, "
            "role, sigma + quality: peak, peak_ratio, ncc, precision_px) feeds 'Refine RPC' directly.")

    REFERENCE = "REFERENCE"
    SPACING = "SPACING"
    WINDOW = "WINDOW"
    SEARCH = "SEARCH"
    OUTLIER_MODEL = "OUTLIER_MODEL"
    KEEP_OUTLIERS = "KEEP_OUTLIERS"
    THREADS = "THREADS"
    SEED = "SEED"
    OUTPUT = "OUTPUT"

    def initAlgorithm(self, config=None):
        Num = QgsProcessingParameterNumber
        self.add_input_image("Raw image (with RPC)", rpc_file=False)
        self.add_rpc_parameter()
        self._add(QgsProcessingParameterRasterLayer(self.REFERENCE, self.tr("Reference orthophoto")),
                  "Georeferenced reference image (any GDAL raster, any CRS); overviews are used when it is finer.")
        self.add_dem_parameters(optional=False)
        add_matching_parameters(self)
        p = self._add(Num(self.THREADS, self.tr("Threads"), Num.Integer, 2, minValue=1),
                      "Matching threads (QGIS runs the tiles in a thread pool).")
        p.setFlags(p.flags() | p.FlagAdvanced)
        self._add(QgsProcessingParameterBoolean(self.KEEP_OUTLIERS, self.tr("Keep flagged outliers"),
                                                defaultValue=False),
                  "Also write the rejected matches (field outlier = true); by default only the inliers.")
        self._add(QgsProcessingParameterFileDestination(
            self.OUTPUT, self.tr("GCPs"), self.tr("GeoPackage (*.gpkg);;CSV (*.csv);;GeoJSON (*.geojson)")),
            "GCP table written in the project's GCP schema.")
        for key, label in (("N_GCPS", "GCPs written"), ("N_WINDOWS", "Windows tried"),
                           ("N_OUTLIERS", "Outliers rejected"), ("MEAN_DSAMPLE", "Mean offset sample (px)"),
                           ("MEAN_DLINE", "Mean offset line (px)")):
            self.addOutput(QgsProcessingOutputNumber(key, self.tr(label)))

    def run_algorithm(self, parameters, context, feedback, progress):
        from concurrent.futures import ThreadPoolExecutor

        from gdal_gf4cal.workflows import collect_gcps_file

        image = self.input_path(parameters, context)
        ref_layer = self.parameterAsRasterLayer(parameters, self.REFERENCE, context)
        if ref_layer is None:
            raise self.error("Give the reference orthophoto (REFERENCE).")
        dem = self.read_dem(parameters, context)
        out = self.output_file(parameters, self.OUTPUT, context)
        keep = self.parameterAsBool(parameters, self.KEEP_OUTLIERS, context)
        # Threads, not processes: inside QGIS a process pool would start QGIS executables.
        with ThreadPoolExecutor(max_workers=self.parameterAsInt(parameters, self.THREADS, context)) as pool:
            rep = collect_gcps_file(image, ref_layer.source(), dem, out, keep_outliers=keep, overwrite=True,
                                    rpc=self.rpc_file(parameters, context),
                                    executor=pool, progress=progress, **matching_options(self, parameters, context))
        self.push_warnings(feedback, rep)
        gcps, table, w = rep["gcps"], rep["table"], rep["windows"]
        inliers = ~gcps["outlier"].to_numpy(bool)
        feedback.pushInfo(f"windows {w['total']} every {rep['spacing_px']} px: accepted {w['accepted']}, featureless "
                          f"{w['featureless']}, weak correlation {w['weak_correlation']}, cloud/change "
                          f"{w['cloud_or_change']}, no data {w['nodata']}, outside {w['outside_image']}; outliers "
                          f"{w['outliers']}")
        self.load_on_completion(out, "GCPs (matched)", "vector")
        # dsample, dline: offset measured - RPC prediction (collect_gcps always returns them).
        ds, dl = gcps["dsample"].to_numpy()[inliers], gcps["dline"].to_numpy()[inliers]
        return {self.OUTPUT: out, "N_GCPS": len(table), "N_WINDOWS": w["total"], "N_OUTLIERS": w["outliers"],
                "MEAN_DSAMPLE": float(ds.mean()) if ds.size else float("nan"),
                "MEAN_DLINE": float(dl.mean()) if dl.size else float("nan")}
