"""``gf4cal:refinerpc`` - bias-compensate an RPC with GCPs and write the refined RPC (Grodecki & Dial 2003)."""
from __future__ import annotations

from qgis.core import (
    QgsProcessingOutputNumber,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
)

from ..base import Gf4calAlgorithm, planar_rms

#: MODEL enum index -> engine model name (stable: the indices are part of the algorithm's interface).
MODELS = ["translation", "shift-drift", "affine", "poly2", "detector-poly", "auto"]
MODEL_LABELS = ["Translation (2 parameters, >= 1 GCP)", "Shift and drift (4 parameters, >= 2 GCPs)",
                "Affine (6 parameters, >= 3 GCPs)", "Polynomial order 2 (12 parameters, >= 6 GCPs)",
                "Detector-position polynomial (cross-track, order ORDER)",
                "Automatic: the simplest model the leave-one-out error supports (recommended)"]


class RefineRpc(Gf4calAlgorithm):
    NAME = "refinerpc"
    DISPLAY = "Refine RPC with GCPs (bias compensation)"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("Estimates an image-space correction of the RPC from ground control points (residual = measured - "
            "predicted, in pixels) and writes the refined RPC: .RPB, _RPC.TXT, or a VRT over the untouched image "
            "(then gdalwarp -rpc uses it). Translation and shift-drift fold exactly into the RPC; other models "
            "refit it and report the refit error. Blunders are flagged by robust estimation. The GeoPackage holds "
            "the GCPs with residuals before/after, the residual vectors (arrows coloured by magnitude, direction "
            "sample -> east, line -> south, before and after exaggerated by one factor stated in the layer names, e.g. "
            "\"residuals after (x37)\") and the footprint.")
    REFERENCES = ("grodecki", "fraser", "huang", "tao")

    MODEL = "MODEL"
    ORDER = "ORDER"
    CCD_AXIS = "CCD_AXIS"
    ROBUST = "ROBUST"
    OUTLIER_THRESHOLD = "OUTLIER_THRESHOLD"
    OUTPUT_ORTHO = "OUTPUT_ORTHO"
    MAX_UNCERTAINTY = "MAX_UNCERTAINTY"

    def initAlgorithm(self, config=None):
        self.add_input_image()
        self.add_rpc_parameter()
        self.add_gcp_parameters()
        self._add(QgsProcessingParameterEnum(self.MODEL, self.tr("Compensation model"), MODEL_LABELS,
                                             defaultValue=MODELS.index("auto")),
                  "Image-space correction estimated from the control points (Grodecki & Dial 2003). Automatic "
                  "compares translation, shift-drift, affine and poly2 by leave-one-out error and keeps the "
                  "simplest unless more parameters are significantly better; the log and report say why.")
        p = self._add(QgsProcessingParameterNumber(self.ORDER, self.tr("Detector polynomial order (1-6)"),
                                                   QgsProcessingParameterNumber.Integer, 3, minValue=1, maxValue=6),
                      "Order of the cross-track polynomial of the detector position (detector-poly model only).")
        p.setFlags(p.flags() | p.FlagAdvanced)
        p = self._add(QgsProcessingParameterEnum(self.CCD_AXIS, self.tr("Image axis along the CCD line"),
                                                 ["sample", "line"], defaultValue=0),
                      "Detector-poly: the image axis along the CCD line (push-broom: sample).")
        p.setFlags(p.flags() | p.FlagAdvanced)
        self.add_dem_parameters()
        p = self._add(QgsProcessingParameterBoolean(self.ROBUST, self.tr("Robust estimation (flag blunders)"),
                                                    defaultValue=True),
                      "Reweight and flag GCPs whose normalised residual exceeds the threshold.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        p = self._add(QgsProcessingParameterNumber(self.OUTLIER_THRESHOLD, self.tr("Outlier threshold (normalised)"),
                                                   QgsProcessingParameterNumber.Double, 4.0, minValue=1.0),
                      "Normalised residual (residual / its standard deviation) above which a GCP is a blunder.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        p = self._add(QgsProcessingParameterNumber(self.MAX_UNCERTAINTY, self.tr("Maximum correction uncertainty (px)"),
                                                   QgsProcessingParameterNumber.Double, 10.0, minValue=0.001),
                      "Refuse a correction whose propagated 1-sigma uncertainty (parameter covariance x measured "
                      "noise) exceeds this anywhere in the image: a weak GCP layout (clustered, near-collinear) "
                      "extrapolates; above 1 px a warning.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        self.add_plausibility_parameter()
        self._add(QgsProcessingParameterFileDestination(
            self.OUTPUT_RPC, self.tr("Refined RPC"),
            self.tr("RPB sidecar (*.RPB);;RPC text (*_RPC.TXT);;VRT over the image (*.vrt)")),
            "Where to write the refined RPC: .RPB, _RPC.TXT or .vrt (image input only). Never an input file.")
        self._add(QgsProcessingParameterFileDestination(self.OUTPUT_GPKG, self.tr("Residuals GeoPackage"),
                                                        self.tr("GeoPackage (*.gpkg)")),
                  "GCPs with residuals before/after, residual arrows and footprint, styled for QGIS.")
        self._add(QgsProcessingParameterRasterDestination(self.OUTPUT_ORTHO, self.tr("Orthoimage (needs the DEM)"),
                                                          optional=True, createByDefault=False),
                  "Also orthorectify the image with the refined RPC over the DEM (its heights made ellipsoidal); "
                  "this orthoimage, not the refined VRT, is loaded.")
        self.add_plot_output("Residual vectors in image space before and after (PNG).")
        self.add_report_output("Statistics per role before/after, parameters, outliers, refit error.")
        for key, label in (("CONTROL_RMS_BEFORE", "Control RMS before (px, planar)"),
                           ("CONTROL_RMS_AFTER", "Control RMS after (px, planar)"),
                           ("CHECK_RMS_BEFORE", "Check RMS before (px, planar)"),
                           ("CHECK_RMS_AFTER", "Check RMS after (px, planar)"),
                           ("N_OUTLIERS", "Number of flagged outliers"),
                           ("REFIT_MAX_PX", "RPC refit maximum error (px)"),
                           ("PRECISION_MAX_PX", "Correction uncertainty, max over the image (px, 1 sigma)")):
            self.addOutput(QgsProcessingOutputNumber(key, self.tr(label)))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.workflows import refine_rpc

        source = self.input_path(parameters, context)
        dem = self.read_dem(parameters, context)
        gcps = self.read_gcps(parameters, context, feedback, dem=dem)
        model = MODELS[self.parameterAsEnum(parameters, self.MODEL, context)]
        order = self.parameterAsInt(parameters, self.ORDER, context) if model == "detector-poly" else None
        out_rpc = self.output_file(parameters, self.OUTPUT_RPC, context)
        out_gpkg = self.output_file(parameters, self.OUTPUT_GPKG, context)
        out_plot = self.output_file(parameters, self.OUTPUT_PLOT, context)
        out_report = self.output_file(parameters, self.OUTPUT_REPORT, context)
        out_ortho = self.parameterAsOutputLayer(parameters, self.OUTPUT_ORTHO, context) or None
        if out_ortho and dem is None:
            raise self.error("An orthoimage (OUTPUT_ORTHO) needs the DEM (DEM).")
        rep = refine_rpc(source, gcps, model, out=out_rpc, order=order,
                         ccd_axis=["sample", "line"][self.parameterAsEnum(parameters, self.CCD_AXIS, context)],
                         dem=dem, robust=self.parameterAsBool(parameters, self.ROBUST, context),
                         outlier_threshold=self.parameterAsDouble(parameters, self.OUTLIER_THRESHOLD, context),
                         residuals=out_gpkg, plot=out_plot, report=out_report, overwrite=True, progress=progress,
                         ortho=out_ortho,
                         max_uncertainty_px=self.parameterAsDouble(parameters, self.MAX_UNCERTAINTY, context),
                         check_plausibility=self.check_plausibility(parameters, context),
                         rpc=self.rpc_file(parameters, context))
        self.push_warnings(feedback, rep)
        if "model_selection" in rep:
            feedback.pushInfo(f"automatic model choice: {rep['model_selection']['reason']}")
        outputs = {self.OUTPUT_RPC: out_rpc, self.OUTPUT_GPKG: out_gpkg}
        if out_plot:
            outputs[self.OUTPUT_PLOT] = out_plot
        if out_report:
            outputs[self.OUTPUT_REPORT] = out_report
        for role in ("control", "check"):
            for when in ("before", "after"):
                st = rep[role][when]
                rms = planar_rms(st)
                outputs[f"{role.upper()}_RMS_{when.upper()}"] = rms
                if st.get("n") and when == "after":
                    feedback.pushInfo(f"{role}: {st['n']} GCPs, RMS before {planar_rms(rep[role]['before']):.3f} px, "
                                      f"after {rms:.3f} px (planar)")
        pr = rep["precision_px"]
        outputs["PRECISION_MAX_PX"] = float(pr["max"])
        feedback.pushInfo(f"correction uncertainty over the image (1 sigma): max {pr['max']:.3f} px, "
                          f"rms {pr['rms']:.3f} px")
        outputs["N_OUTLIERS"] = len(rep["outliers"])
        for o in rep["outliers"]:
            feedback.pushWarning(f"outlier {o['id']} ({o['role']}): normalised residual sample "
                                 f"{o['norm_res_sample']:.1f}, line {o['norm_res_line']:.1f}")
        outputs["REFIT_MAX_PX"] = float(rep["apply"]["refit_max_px"])
        if not rep["apply"]["exact"]:
            feedback.pushInfo(f"RPC refitted on the corrected model: max error {rep['apply']['refit_max_px']:.2e} px")
        if out_ortho:
            outputs[self.OUTPUT_ORTHO] = out_ortho          # Processing loads it: the ortho, not the VRT
            self.name_output_layer(context, out_ortho, source)
        elif out_rpc.lower().endswith(".vrt"):
            self.load_on_completion(out_rpc, "Refined RPC (VRT)", "raster")
        self.load_gpkg_on_completion(out_gpkg)
        return outputs
