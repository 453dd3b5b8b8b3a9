"""``gf4cal:blockadjust`` - block calibration of one multi-CCD group from its RPC images: seams removed, bands
registered (Wu et al., Jilin1-KF01A; the same inputs as ``gf4cal block-adjust``)."""
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
    QgsProcessingParameterRasterLayer,
    QgsProcessingParameterString,
)

from ..base import Gf4calAlgorithm, split_items

#: SOLVER enum index -> engine solver name (stable: the indices are part of the algorithm's interface).
SOLVERS = ["simultaneous", "alternating"]
SOLVER_LABELS = ["Simultaneous (one sparse Gauss-Newton solve; recommended)",
                 "Alternating (the paper's scheme: exterior, then interior, repeated; compared with the simultaneous "
                 "solve in the report)"]
OBS_FILTER = "Observation tables (*.csv *.gpkg *.CSV *.GPKG);;All files (*.*)"


split_bands_of = split_items


class BlockAdjust(Gf4calAlgorithm):
    NAME = "blockadjust"
    DISPLAY = "Block-adjust a multi-CCD group (seams, band-to-band)"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("Calibrates one group of a multi-CCD push-broom camera delivered as one RPC image per CCD and band "
            "(e.g. Jilin-1 wide-field): an exterior shared by the group (roll, pitch, yaw, roll and pitch drift) and "
            "a cubic interior per CCD and band, from GCPs and tie points, in one sparse adjustment (Wu et al.). "
            "Adjacent CCDs then agree in their overlaps and the bands register. Writes into the output folder one "
            "recalibrated RPC per image (<image>.RPB, refit error reported), calibration.json (for 'Apply a camera "
            "calibration' to other scenes of the same group), report.json (seam offsets before/after, residuals "
            "per CCD and band, band-to-band registration), residuals.gpkg (per image its GCPs and residual vectors, "
            "and a 'seams' layer) and seams.png. Images are named in the tables by their file name without "
            "extension, or by their folder name when file names repeat (ccd1/scene.tif -> ccd1).")
    REFERENCES = ("wu",)

    GCPS_FILE = "GCPS_FILE"
    TIES_FILE = "TIES_FILE"
    MATCH_TIES = "MATCH_TIES"
    REFERENCE_ORTHO = "REFERENCE_ORTHO"
    BANDS_OF = "BANDS_OF"
    SOLVER = "SOLVER"
    REFERENCE_CCD = "REFERENCE_CCD"
    OUTPUT_FOLDER = "OUTPUT_FOLDER"

    def initAlgorithm(self, config=None):
        self._add(QgsProcessingParameterMultipleLayers(self.INPUT, self.tr("Images of the group (with RPCs)"),
                                                       QgsProcessing.TypeRaster),
                  "Every CCD image of the group, each with its RPC: the reference-band CCD images in their order "
                  "across track (adjacent ones overlap), and the other bands' images (named in BANDS_OF). From Python or qgis_process, file paths.")
        self.add_dem_parameters(optional=False)
        self._add(QgsProcessingParameterFile(self.GCPS_FILE, self.tr("GCP observations (long table)"), optional=True,
                                             behavior=QgsProcessingParameterFile.File, fileFilter=OBS_FILTER),
                  "CSV or GeoPackage, one row per point and image: point_id, image, sample, line (GDAL convention: "
                  "first pixel centre 0.5), lon, lat, h, optional role (control/check) and sigma (px). 'image' is "
                  "the image's file name (or folder name, see above).")
        self._add(QgsProcessingParameterFile(self.TIES_FILE, self.tr("Tie-point observations (long table)"),
                                             optional=True, behavior=QgsProcessingParameterFile.File,
                                             fileFilter=OBS_FILTER),
                  "CSV or GeoPackage: point_id, image, sample, line, optional sigma (px); rows with the same "
                  "point_id are one ground point. May be the same file as the GCP observations.")
        self._add(QgsProcessingParameterBoolean(self.MATCH_TIES, self.tr("Find tie points by image matching"),
                                                defaultValue=False),
                  "Match adjacent CCDs in their overlaps and every band against its reference band (raw to raw, "
                  "through the RPCs and the DEM) instead of, or besides, a tie-point table.")
        self._add(QgsProcessingParameterRasterLayer(self.REFERENCE_ORTHO, self.tr("Reference orthophoto"),
                                                    optional=True),
                  "Collect GCPs for the reference-band images by matching them against this orthophoto.")
        self._add(QgsProcessingParameterString(self.BANDS_OF, self.tr("Bands of (IMAGE=REFIMAGE, ...)"),
                                               optional=True, multiLine=True),
                  "Which image is another band of which CCD: items IMAGE=REFIMAGE (the band image and the "
                  "reference-band image of its CCD), separated by commas, semicolons or new lines, e.g. ccd1_green=ccd1_blue. "
                  "These bands are calibrated relatively (interior only, reference exterior fixed).")
        self.add_rpc_pairs_parameter()
        self._add(QgsProcessingParameterEnum(self.SOLVER, self.tr("Solver"), SOLVER_LABELS, defaultValue=0),
                  "How the group is solved.")
        p = self._add(QgsProcessingParameterString(self.REFERENCE_CCD, self.tr("Reference CCD image (datum)"),
                                                   optional=True),
                      "The reference-band CCD image whose constant and linear interior terms are fixed (the datum); "
                      "default: the middle one.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        self.add_plausibility_parameter()
        self._add(QgsProcessingParameterFolderDestination(self.OUTPUT_FOLDER, self.tr("Output folder")),
                  "Folder receiving the recalibrated RPCs, calibration.json, report.json, residuals.gpkg and "
                  "seams.png.")
        self.addOutput(QgsProcessingOutputMultipleLayers("OUTPUT_RPCS", self.tr("Recalibrated RPC files")))
        self.addOutput(QgsProcessingOutputFile("OUTPUT_CALIBRATION", self.tr("Group calibration (JSON)")))
        self.addOutput(QgsProcessingOutputVectorLayer(self.OUTPUT_GPKG, self.tr("Residuals GeoPackage")))
        self.addOutput(QgsProcessingOutputFile(self.OUTPUT_PLOT, self.tr("Seam plot")))
        self.addOutput(QgsProcessingOutputFile(self.OUTPUT_REPORT, self.tr("Report (JSON)")))
        for key, label in (("MAX_SEAM_BEFORE_PX", "Largest mean seam offset before (px)"),
                           ("MAX_SEAM_PX", "Largest mean seam offset after (px)"),
                           ("MAX_BAND_RMS_AFTER_PX", "Largest band-to-band tie RMS after (px)"),
                           ("N_OUTLIERS", "Number of flagged outliers"), ("ITERATIONS", "Iterations")):
            self.addOutput(QgsProcessingOutputNumber(key, self.tr(label)))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.workflows import block_adjust

        images = self.parameterAsFileList(parameters, self.INPUT, context)
        if len(images) < 2:
            raise self.error("Give the images of at least two CCDs of the group (INPUT).")
        dem, geoid = self.dem_source(parameters, context)
        if dem is None:
            raise self.error("Give a DEM (DEM): tie-point heights come from it.")
        ortho = self.parameterAsRasterLayer(parameters, self.REFERENCE_ORTHO, context)
        folder = self.output_folder(parameters, self.OUTPUT_FOLDER, context)
        rep = block_adjust(
            images, dem=dem, geoid=geoid, out=folder, overwrite=True, progress=progress,
            gcps=self.parameterAsFile(parameters, self.GCPS_FILE, context) or None,
            ties=self.parameterAsFile(parameters, self.TIES_FILE, context) or None,
            match_ties=self.parameterAsBool(parameters, self.MATCH_TIES, context),
            reference_ortho=ortho.source() if ortho is not None else None,
            bands_of=split_bands_of(self.parameterAsString(parameters, self.BANDS_OF, context)),
            solver=SOLVERS[self.parameterAsEnum(parameters, self.SOLVER, context)],
            reference_ccd=self.parameterAsString(parameters, self.REFERENCE_CCD, context) or None,
            check_plausibility=self.check_plausibility(parameters, context),
            rpcs=self.rpc_pairs(parameters, context))
        self.push_warnings(feedback, rep)
        for st in rep["stages"]:
            feedback.pushInfo(f"{st['stage']} stage ({st['solver']}): {st['iterations']} iterations, "
                              f"{st['n_tie_points']} tie points, {st['n_rejected']} observations rejected")
        seams = [s for s in rep["seams"] if s.get("n")]
        for s in seams:
            feedback.pushInfo(f"seam {s['pair'][0]} | {s['pair'][1]}: mean offset {s['before']['mean_px']:.3f} px "
                              f"before, {s['after']['mean_px']:.3f} px after ({s['n']} tie points)")
        band_after = [v["rms_px_after"] for v in rep["band_to_band"].values() if v.get("rms_px_after") is not None]
        outputs = rep["outputs"]
        self.load_gpkg_on_completion(outputs["residuals"], layers=("seams",))
        nan = float("nan")
        return {self.OUTPUT_FOLDER: folder,
                "OUTPUT_RPCS": [p for k, p in outputs.items() if k.startswith("rpb:")],
                "OUTPUT_CALIBRATION": outputs["calibration"], self.OUTPUT_GPKG: outputs["residuals"],
                self.OUTPUT_PLOT: outputs["seams_plot"], self.OUTPUT_REPORT: outputs["report"],
                "MAX_SEAM_BEFORE_PX": max((s["before"]["mean_px"] for s in seams), default=nan),
                "MAX_SEAM_PX": max((s["after"]["mean_px"] for s in seams), default=nan),
                "MAX_BAND_RMS_AFTER_PX": max(band_after, default=nan),
                "N_OUTLIERS": rep["n_outliers"], "ITERATIONS": sum(st["iterations"] for st in rep["stages"])}
