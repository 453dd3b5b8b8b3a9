"""``gf4cal:bundleadjust`` - bundle adjustment of separate views (stereo, tri-stereo, multi-date) on their RPCs from
tie points alone (METHODS §11, issue 22; the same inputs as ``gf4cal bundle-adjust``)."""
from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingOutputFile,
    QgsProcessingOutputMultipleLayers,
    QgsProcessingOutputNumber,
    QgsProcessingOutputVectorLayer,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFile,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterMultipleLayers,
    QgsProcessingParameterNumber,
    QgsProcessingParameterString,
)

from gdal_gf4cal.errors import Gf4calError

from ..base import Gf4calAlgorithm, split_items

#: MODEL enum index -> engine model name (stable: the indices are part of the algorithm's interface).
MODELS = ["translation", "shift-drift", "affine"]
MODEL_LABELS = ["Translation (a shift per view)", "Shift and drift (a shift plus a drift along the lines)",
                "Affine (recommended; a translation where the ties do not spread over a view, with a note)"]
OBS_FILTER = "Observation tables (*.csv *.gpkg *.CSV *.GPKG);;All files (*.*)"

#: The engine's option names in messages -> this dialog's parameters.
WORDS = (("(--prior-sigma)", "(PRIOR_SIGMA)"), ("--prior-sigma", "PRIOR_SIGMA"), ("--ties OBS", "TIES_FILE"),
         ("--ties / --match-ties", "TIES_FILE / MATCH_TIES"), ("--match-ties", "MATCH_TIES"), ("--ties", "TIES_FILE"),
         ("--max-pairs", "MAX_PAIRS"), ("--gcps", "GCPS_FILE"), ("--dem-sigma", "DEM_SIGMA"), ("--dem", "DEM"), ("--overwrite", "a new folder"))


def dialog_words(message: str) -> str:
    """A bundle-adjust message with the CLI's option names replaced by the dialog's parameter names."""
    for cli, qgis in WORDS:
        message = message.replace(cli, qgis)
    return message


class BundleAdjust(Gf4calAlgorithm):
    NAME = "bundleadjust"
    DISPLAY = "Bundle-adjust separate views (stereo, tri-stereo, multi-date)"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    REFERENCES = ("grodecki",)
    HELP = ("Brings separate views of the same ground (a stereo pair or triplet, images of several dates) into one "
            "frame from tie points alone, before making a surface model or stacking them: each view keeps its "
            "vendor RPC plus a correction in image space (translation, shift and drift, or affine), the tie points' "
            "ground is estimated with them, and each view's RPC holds the block in place where no GCPs are given "
            "(Grodecki & Dial 2003). Tie points come from a table or are matched raw to raw through the RPCs and "
            "the DEM on "
            "the overlapping pairs. Writes into the output folder one corrected RPC per view (<view>.RPB and, for an "
            "image, <view>.vrt over the untouched image carrying it: gdalwarp -rpc reads it), report.json (tie "
            "reprojection before/after per view and per pair, corrections with their sigmas, each view relative "
            "to the first, datum drift), residuals.gpkg (per view its ties with before/after residual arrows, and "
            "the tie points), ties.png, and the matched ties as ties.csv. Views are named in the tables by their "
            "file name without extension.")

    RPC_VIEWS = "RPC_VIEWS"
    TIES_FILE = "TIES_FILE"
    MATCH_TIES = "MATCH_TIES"
    GCPS_FILE = "GCPS_FILE"
    MODEL = "MODEL"
    MAX_PAIRS = "MAX_PAIRS"
    PRIOR_SIGMA = "PRIOR_SIGMA"
    DEM_SIGMA = "DEM_SIGMA"
    OUTPUT_FOLDER = "OUTPUT_FOLDER"

    def initAlgorithm(self, config=None):
        self._add(QgsProcessingParameterMultipleLayers(self.INPUT, self.tr("Views (images with RPCs)"),
                                                       QgsProcessing.TypeRaster, optional=True),
                  "Images of the same ground, each with its RPC (its own, an RPC file named like it beside it such "
                  "as a .geom, or given in RPCS). Two or more views in all, with RPC_VIEWS.")
        self._add(QgsProcessingParameterMultipleLayers(self.RPC_VIEWS, self.tr("Views given as RPC files alone"),
                                                       QgsProcessing.TypeFile, optional=True),
                  "With a tie table: views without their image, as RPC files (.geom, .RPB, _RPC.TXT, DIMAP "
                  "RPC_*.XML), in the pixels of the tie table. No .vrt is written for them.")
        self._add(QgsProcessingParameterFile(self.TIES_FILE, self.tr("Tie-point observations (long table)"),
                                             optional=True, behavior=QgsProcessingParameterFile.File,
                                             fileFilter=OBS_FILTER),
                  "CSV or GeoPackage, one row per point and view: point_id, image, sample, line (GDAL convention: "
                  "first pixel centre 0.5), optional sigma (px); rows with the same point_id are one ground point, "
                  "seen by two or more views.")
        self._add(QgsProcessingParameterBoolean(self.MATCH_TIES, self.tr("Find tie points by image matching"),
                                                defaultValue=False),
                  "Match the overlapping views raw to raw, through their RPCs and the DEM (every view joined to the "
                  "others first, then the largest overlaps), instead of, or besides, a tie table.")
        self.add_dem_parameters(optional=True)
        self._add(QgsProcessingParameterFile(self.GCPS_FILE, self.tr("GCP observations (long table)"), optional=True,
                                             behavior=QgsProcessingParameterFile.File, fileFilter=OBS_FILTER),
                  "Optional ground control: point_id, image, sample, line, lon, lat, h, optional role "
                  "(control/check) and sigma (px). Without it the block sits where the views' RPCs put it.")
        self._add(QgsProcessingParameterEnum(self.MODEL, self.tr("Correction per view"), MODEL_LABELS,
                                             defaultValue=2), "The image-space correction of each view's RPC.")
        self._advanced(QgsProcessingParameterNumber(self.MAX_PAIRS, self.tr("Largest number of pairs to match"),
                                                    QgsProcessingParameterNumber.Integer, optional=True, minValue=1),
                       "With image matching: match at most this many pairs of views (never fewer than it takes to "
                       "join every view). Empty: every overlapping pair.")
        self._advanced(QgsProcessingParameterString(self.PRIOR_SIGMA, self.tr("How far each RPC may be off (px)"),
                                                    optional=True),
                       "The 1-sigma prior on each view's correction that holds the block without GCPs: a number "
                       "for every view and/or VIEW=PX items (e.g. right=100), separated by commas or spaces. Empty: "
                       "the RPC's stated bias error (ERR_BIAS), else 5 m over the view's pixel size; a pair follows its "
                       "first view (the second's prior 1000x wider). Widen it for a view known to be far off.")
        self._advanced(QgsProcessingParameterNumber(self.DEM_SIGMA, self.tr("DEM height accuracy (m)"),
                                                    QgsProcessingParameterNumber.Double, defaultValue=5.0,
                                                    minValue=0.001),
                       "With a DEM every tie's height is held to the DEM within this 1-sigma (m): it fixes the "
                       "views' relative bias along the epipolar direction, which tie points alone cannot see. "
                       "Default 5 m, a global DEM's typical absolute accuracy.")
        self.add_rpc_pairs_parameter()
        self.add_plausibility_parameter()
        self._add(QgsProcessingParameterFolderDestination(self.OUTPUT_FOLDER, self.tr("Output folder")),
                  "Folder receiving the corrected RPCs (and VRTs), report.json, residuals.gpkg, ties.png and "
                  "ties.csv.")
        self._outputs()

    def _advanced(self, param, help_text: str):
        param.setFlags(param.flags() | param.FlagAdvanced)
        return self._add(param, help_text)

    def _outputs(self):
        self.addOutput(QgsProcessingOutputMultipleLayers("OUTPUT_RPCS", self.tr("Corrected RPC files")))
        self.addOutput(QgsProcessingOutputMultipleLayers("OUTPUT_VRTS", self.tr("VRTs over the images")))
        self.addOutput(QgsProcessingOutputVectorLayer(self.OUTPUT_GPKG, self.tr("Residuals GeoPackage")))
        self.addOutput(QgsProcessingOutputFile(self.OUTPUT_PLOT, self.tr("Tie residual plot")))
        self.addOutput(QgsProcessingOutputFile(self.OUTPUT_REPORT, self.tr("Report (JSON)")))
        self.addOutput(QgsProcessingOutputFile("OUTPUT_TIES", self.tr("Matched tie points (CSV)")))
        for key, label in (("RMS_BEFORE_PX", "Tie reprojection RMS before (px)"),
                           ("RMS_AFTER_PX", "Tie reprojection RMS after (px)"),
                           ("DATUM_DRIFT_M", "Datum drift (m)"), ("N_TIES", "Number of tie points"),
                           ("N_OUTLIERS", "Number of rejected observations")):
            self.addOutput(QgsProcessingOutputNumber(key, self.tr(label)))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.workflows import bundle_adjust
        images = [p for name in (self.INPUT, self.RPC_VIEWS)
                  for p in self.parameterAsFileList(parameters, name, context) if p]
        dem, geoid = self.dem_source(parameters, context)
        max_pairs = parameters.get(self.MAX_PAIRS)
        try:
            rep = bundle_adjust(
                images, dem=dem, geoid=geoid, out=self.output_folder(parameters, self.OUTPUT_FOLDER, context),
                overwrite=True, progress=progress,
                ties=self.parameterAsFile(parameters, self.TIES_FILE, context) or None,
                match_ties=self.parameterAsBool(parameters, self.MATCH_TIES, context),
                gcps=self.parameterAsFile(parameters, self.GCPS_FILE, context) or None,
                model=MODELS[self.parameterAsEnum(parameters, self.MODEL, context)],
                max_pairs=None if max_pairs in (None, "") else self.parameterAsInt(parameters, self.MAX_PAIRS,
                                                                                  context),
                prior_sigma_px=split_items(self.parameterAsString(parameters, self.PRIOR_SIGMA, context)) or None,
                dem_sigma_m=self.parameterAsDouble(parameters, self.DEM_SIGMA, context),
                rpcs=self.rpc_pairs(parameters, context), check_plausibility=self.check_plausibility(parameters,
                                                                                                    context))
        except Gf4calError as exc:
            exc.args = (dialog_words(str(exc)),)
            raise
        self.push_warnings(feedback, rep)
        self._log(feedback, rep)
        return self._results(parameters, context, rep)

    def _log(self, feedback, rep):
        rel = rep["relative_to_first_view_px"]
        for k, v in rep["views"].items():
            r = rel["views"].get(k, {})
            feedback.pushInfo(f"{k}: {v['model_used']} correction; relative to {rel['reference']} sample "
                              f"{r.get('sample', 0.0):+.3f} +- {r.get('sample_std', 0.0):.3f} px, line "
                              f"{r.get('line', 0.0):+.3f} +- {r.get('line_std', 0.0):.3f} px; tie RMS "
                              f"{v['reprojection_px']['before'] or float('nan'):.3f} -> "
                              f"{v['reprojection_px']['after'] or float('nan'):.3f} px")
        feedback.pushInfo(f"{rep['ties']['n_points']} tie points ({rep['ties']['source']}); datum drift "
                          f"{rep['datum_drift_m']:.3f} m")

    def _results(self, parameters, context, rep):
        outputs = rep["outputs"]
        views = list(rep["views"])
        layers = [f"{k}_{name}" for k in views for name in ("residual_vectors_before", "residual_vectors", "gcps")]
        self.load_gpkg_on_completion(outputs["residuals"], layers=tuple(layers) + ("tie_points",))
        nan = float("nan")
        rp = rep["reprojection_px"]
        return {self.OUTPUT_FOLDER: self.output_folder(parameters, self.OUTPUT_FOLDER, context),
                "OUTPUT_RPCS": [p for k, p in outputs.items() if k.startswith("rpb:")],
                "OUTPUT_VRTS": [p for k, p in outputs.items() if k.startswith("vrt:")],
                self.OUTPUT_GPKG: outputs["residuals"], self.OUTPUT_PLOT: outputs["plot"],
                self.OUTPUT_REPORT: outputs["report"], "OUTPUT_TIES": outputs.get("ties"),
                "RMS_BEFORE_PX": rp["before"]["all"] if rp["before"]["all"] is not None else nan,
                "RMS_AFTER_PX": rp["after"]["all"] if rp["after"]["all"] is not None else nan,
                "DATUM_DRIFT_M": rep["datum_drift_m"], "N_TIES": rep["ties"]["n_points"],
                "N_OUTLIERS": rep["n_outliers"]}
