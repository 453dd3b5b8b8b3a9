"""``gf4cal:blockadjust`` - block calibration of one multi-CCD group from its RPC images: seams removed, bands
registered (Wu et al., Jilin1-KF01A; the same inputs as ``gf4cal block-adjust``)."""
from __future__ import annotations

from typing import List

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
    QgsProcessingParameterMatrix,
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


def split_bands_of(cells) -> List[str]:
    """BANDS_OF (a two-column table: band image, reference-band image; or ``IMAGE=REFIMAGE`` items, as text from
    Python or qgis_process) -> ``["IMAGE=REFIMAGE", ...]``. A cell that is neither an item nor a table cell (e.g.
    two names with a space) is passed on as it is, and the engine says how to write it."""
    if isinstance(cells, str):
        cells = [cells]
    items, plain = [], []
    for c in cells or []:
        c = "" if c is None else str(c).strip()
        if c in ("", "NULL"):
            continue
        if "=" in c:
            items.extend(split_items(c))
        else:
            plain.append(c)
    if len(plain) % 2 or any(split_items(c) != [c] for c in plain):
        return items + plain
    return items + [f"{a}={b}" for a, b in zip(plain[::2], plain[1::2])]


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
                  "across track (adjacent ones overlap), and the other bands' images after them (paired with their CCD "
                  "from the RPCs, or as BANDS_OF says). Separate views (stereo, other dates) are refused: use the "
                  "bundle adjustment (gf4cal:bundleadjust). From Python or qgis_process, file paths.")
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
        self._add(QgsProcessingParameterMatrix(self.BANDS_OF, self.tr("Bands of (optional: band image, reference-band "
                                                                      "image of its CCD)"),
                                               numberRows=0, hasFixedNumberRows=False, optional=True,
                                               headers=[self.tr("Band image"), self.tr("Reference-band image")]),
                  "Optional: which image is another band of which CCD, one row per band image (the band image and "
                  "the reference-band image of its CCD, named as in the tables). Left empty, the pairing comes from "
                  "the RPCs: an image whose footprint coincides with an earlier-listed image's is another band of "
                  "that CCD. These bands are calibrated relatively (interior only, reference exterior fixed). From "
                  "Python or qgis_process also IMAGE=REFIMAGE items, e.g. ccd1_green=ccd1_blue.")
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
        # the engine loads when the algorithm runs, not when QGIS loads the plugin
        from gdal_gf4cal.workflows import block_adjust
        from gdal_gf4cal.workflows.block import summary_lines

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
            bands_of=split_bands_of(self.parameterAsMatrix(parameters, self.BANDS_OF, context)),
            solver=SOLVERS[self.parameterAsEnum(parameters, self.SOLVER, context)],
            reference_ccd=self.parameterAsString(parameters, self.REFERENCE_CCD, context) or None,
            check_plausibility=self.check_plausibility(parameters, context),
            rpcs=self.rpc_pairs(parameters, context))
        self.push_warnings(feedback, rep)
        seams = [s for s in rep["seams"] if s.get("n")]
        band_after = [v["rms_px_after"] for v in rep["band_to_band"].values() if v.get("rms_px_after") is not None]
        outputs = rep["outputs"]
        self.load_gpkg_on_completion(outputs["residuals"], layers=("seams",))
        feedback.pushInfo("Summary (as gf4cal block-adjust prints it; the iteration trace above gives, per stage, "
                          "the largest change of a corrected position at each Gauss-Newton iteration: it rises "
                          "again when the robust weights change between phases):")
        for line in summary_lines(rep):
            feedback.pushInfo(line)
        nan = float("nan")
        return {self.OUTPUT_FOLDER: folder,
                "OUTPUT_RPCS": [p for k, p in outputs.items() if k.startswith("rpb:")],
                "OUTPUT_CALIBRATION": outputs["calibration"], self.OUTPUT_GPKG: outputs["residuals"],
                self.OUTPUT_PLOT: outputs["seams_plot"], self.OUTPUT_REPORT: outputs["report"],
                "MAX_SEAM_BEFORE_PX": max((s["before"]["mean_px"] for s in seams), default=nan),
                "MAX_SEAM_PX": max((s["after"]["mean_px"] for s in seams), default=nan),
                "MAX_BAND_RMS_AFTER_PX": max(band_after, default=nan),
                "N_OUTLIERS": rep["n_outliers"], "ITERATIONS": sum(st["iterations"] for st in rep["stages"])}
