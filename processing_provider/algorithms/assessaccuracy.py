"""``gf4cal:assessaccuracy`` - how well an RPC fits GCPs: per-axis and planar statistics, CE90,
internal accuracy, per role, with the residuals as a styled GeoPackage."""
from __future__ import annotations

from qgis.core import (
    QgsProcessingOutputNumber,
    QgsProcessingParameterFileDestination,
)

from ..base import Gf4calAlgorithm


class AssessAccuracy(Gf4calAlgorithm):
    NAME = "assessaccuracy"
    DISPLAY = "Assess RPC accuracy at GCPs"
    GROUP = "Accuracy"
    GROUP_ID = "accuracy"
    HELP = ("Projects every GCP through the RPC and reports the residuals (measured - predicted, px): per axis mean, "
            "RMS, RMSE (spread about the mean) and max; planar RMS and CE90 in pixels and in ground metres; and the "
            "internal accuracy, what remains after removing a rotation + translation (Pi et al. 2023, eq. 8). "
            "Control and check points are reported separately when the GCP layer has both roles. The GeoPackage "
            "holds the GCPs "
            "with their residuals and the residual arrows (sample -> east, line -> south, exaggerated by the factor "
            "stated in the layer).")
    REFERENCES = ("pi",)

    def initAlgorithm(self, config=None):
        self.add_input_rpc()
        self.add_rpc_parameter()
        self.add_gcp_parameters()
        self.add_dem_parameters()
        self.add_plausibility_parameter()
        self._add(QgsProcessingParameterFileDestination(self.OUTPUT_GPKG, self.tr("Residuals GeoPackage"),
                                                        self.tr("GeoPackage (*.gpkg)"), optional=True),
                  "GCPs with residuals, residual arrows and footprint, styled for QGIS.")
        self.add_plot_output("Residual vectors in image space (PNG).")
        self.add_report_output("All statistics per role as JSON.")
        for key, label in (("N", "Number of GCPs"), ("RMS_SAMPLE", "RMS sample (px)"), ("RMS_LINE", "RMS line (px)"),
                           ("MEAN_SAMPLE", "Mean sample (px)"), ("MEAN_LINE", "Mean line (px)"),
                           ("RMS_PLANAR", "Planar RMS (px)"), ("CE90_M", "CE90 (m)"),
                           ("INTERNAL_RMS_PLANAR", "Internal accuracy, planar RMS (px)"),
                           ("CHECK_RMS_PLANAR", "Check points: planar RMS (px)")):
            self.addOutput(QgsProcessingOutputNumber(key, self.tr(label)))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.describe import image_size_of
        from gdal_gf4cal.workflows import assess_accuracy

        source = self.input_path(parameters, context)
        dem = self.read_dem(parameters, context)
        gcps = self.read_gcps(parameters, context, feedback, dem=dem)
        out_gpkg = self.output_file(parameters, self.OUTPUT_GPKG, context)
        out_plot = self.output_file(parameters, self.OUTPUT_PLOT, context)
        out_report = self.output_file(parameters, self.OUTPUT_REPORT, context)
        size = image_size_of(source)
        rpc = self.rpc_file(parameters, context)
        if size is None:
            from gdal_gf4cal.rpc import RPCModel
            size = RPCModel.from_file(rpc or source).image_size
        rep = assess_accuracy(source, gcps, rpc=rpc, residuals=out_gpkg, plot=out_plot, report=out_report,
                              image_size=size,
                              overwrite=True, progress=progress,
                              check_plausibility=self.check_plausibility(parameters, context))
        self.push_warnings(feedback, rep)
        a = rep["all"]
        outputs = {"N": rep["n"], "RMS_SAMPLE": a["sample"]["rms"], "RMS_LINE": a["line"]["rms"],
                   "MEAN_SAMPLE": a["sample"]["mean"], "MEAN_LINE": a["line"]["mean"],
                   "RMS_PLANAR": a["planar"]["rms"], "CE90_M": a["ce90_m"],
                   "INTERNAL_RMS_PLANAR": a["internal"]["planar"]["rms"] if "internal" in a else float("nan"),
                   "CHECK_RMS_PLANAR": rep["check"]["planar"]["rms"] if "check" in rep else float("nan")}
        for key in ("all", "control", "check"):
            if key in rep:
                r = rep[key]
                feedback.pushInfo(f"{key}: n={r['n']}, RMS sample {r['sample']['rms']:.3f} px, line "
                                  f"{r['line']['rms']:.3f} px, mean {r['sample']['mean']:.3f} / "
                                  f"{r['line']['mean']:.3f} px, CE90 {r['ce90_m']:.2f} m")
        for key, path in ((self.OUTPUT_GPKG, out_gpkg), (self.OUTPUT_PLOT, out_plot),
                          (self.OUTPUT_REPORT, out_report)):
            if path:
                outputs[key] = path
        if out_gpkg:
            self.load_gpkg_on_completion(out_gpkg)
        return outputs
