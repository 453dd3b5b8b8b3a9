"""``gf4cal:blockadjust`` - multi-CCD / band-to-band block calibration of one group (METHODS §8)."""
from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingOutputFile,
    QgsProcessingOutputMultipleLayers,
    QgsProcessingOutputNumber,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFile,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterMultipleLayers,
    QgsProcessingParameterString,
)

from ..base import Gf4calAlgorithm

SOLVERS = ["simultaneous", "alternating"]


class BlockAdjust(Gf4calAlgorithm):
    NAME = "blockadjust"
    DISPLAY = "Block calibration of a multi-CCD group"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("Calibrates the CCD images (one RPC per CCD and band) of one group of a wide-swath push-broom camera "
            "together (METHODS §8): an exterior shared by the group, a cubic interior per CCD image and band, tie "
            "points between adjacent CCDs and between bands as unknowns on the DEM. Give the reference band's CCD "
            "images in their order across track (adjacent ones overlap), then the other bands' images with "
            "'Bands of' entries IMAGE=REFIMAGE. Writes <image>.RPB per image, calibration.json (for 'Apply a camera "
            "calibration' to other scenes of the group), report.json, residuals.gpkg (per image and a 'seams' "
            "layer) and seams.png in the output folder.")

    GCPS_FILE = "GCPS_FILE"
    TIES_FILE = "TIES_FILE"
    MATCH_TIES = "MATCH_TIES"
    REFERENCE_ORTHO = "REFERENCE_ORTHO"
    BANDS_OF = "BANDS_OF"
    SOLVER = "SOLVER"
    OUTPUT_FOLDER = "OUTPUT_FOLDER"

    def initAlgorithm(self, config=None):
        self._add(QgsProcessingParameterMultipleLayers(self.INPUT, self.tr("Images of the group (with RPCs)"),
                                                       QgsProcessing.TypeFile),
                  "The reference band's CCD images in their order across track, then the other bands' images.")
        self.add_dem_parameters(optional=False)
        self._add(QgsProcessingParameterFile(self.GCPS_FILE, self.tr("GCP observations (CSV/GeoPackage)"),
                                             optional=True),
                  "Long table point_id, image, sample, line, lon, lat, h [, role, sigma]; image = the image's file "
                  "name (or folder name).")
        self._add(QgsProcessingParameterFile(self.TIES_FILE, self.tr("Tie-point observations (CSV/GeoPackage)"),
                                             optional=True),
                  "Long table point_id, image, sample, line [, sigma]; may be the GCP file.")
        self._add(QgsProcessingParameterBoolean(self.MATCH_TIES, self.tr("Match tie points between the images"),
                                                defaultValue=False),
                  "Tie points by raw-to-raw matching (adjacent CCDs, each band against its reference band).")
        self._add(QgsProcessingParameterFile(self.REFERENCE_ORTHO, self.tr("Reference ortho for GCPs (optional)"),
                                             optional=True),
                  "Collect GCPs for the reference-band images from this orthophoto.")
        self._add(QgsProcessingParameterString(self.BANDS_OF, self.tr("Bands of (IMAGE=REFIMAGE; ...)"),
                                               optional=True),
                  "Other bands: IMAGE=REFIMAGE pairs separated by ';' (the band image and the reference-band image "
                  "of its CCD, by file or folder name).")
        self._add(QgsProcessingParameterEnum(self.SOLVER, self.tr("Solver"), SOLVERS, defaultValue=0),
                  "simultaneous: one sparse Gauss-Newton; alternating: the paper's exterior/interior alternation, "
                  "compared with the simultaneous solve in the report.")
        self._add(QgsProcessingParameterFolderDestination(self.OUTPUT_FOLDER, self.tr("Output folder")),
                  "Folder receiving the RPCs, calibration.json, report.json, residuals.gpkg and seams.png.")
        self.addOutput(QgsProcessingOutputMultipleLayers("OUTPUT_RPCS", self.tr("Recalibrated RPC files")))
        self.addOutput(QgsProcessingOutputFile(self.OUTPUT_REPORT, self.tr("Report (JSON)")))
        self.addOutput(QgsProcessingOutputFile("OUTPUT_CALIBRATION", self.tr("Calibration (JSON)")))
        self.addOutput(QgsProcessingOutputFile("OUTPUT_RESIDUALS", self.tr("Residuals (GeoPackage)")))
        self.addOutput(QgsProcessingOutputNumber("MAX_SEAM_PX", self.tr("Largest seam offset after (px)")))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.workflows import block_adjust

        images = self.parameterAsFileList(parameters, self.INPUT, context)
        if len(images) < 2:
            raise self.error("Give the images of at least two CCDs (INPUT).")
        dem = self.read_dem(parameters, context)
        if dem is None:
            raise self.error("Choose the DEM (DEM).")
        bands = [b for b in (self.parameterAsString(parameters, self.BANDS_OF, context) or "").split(";") if b.strip()]
        folder = self.output_folder(parameters, self.OUTPUT_FOLDER, context)
        rep = block_adjust(images, dem=dem, out=folder,
                           gcps=self.parameterAsFile(parameters, self.GCPS_FILE, context) or None,
                           ties=self.parameterAsFile(parameters, self.TIES_FILE, context) or None,
                           match_ties=self.parameterAsBoolean(parameters, self.MATCH_TIES, context),
                           reference_ortho=self.parameterAsFile(parameters, self.REFERENCE_ORTHO, context) or None,
                           bands_of=bands, solver=SOLVERS[self.parameterAsEnum(parameters, self.SOLVER, context)],
                           overwrite=True, progress=progress)
        self.push_warnings(feedback, rep)
        seam = 0.0
        for s in rep["seams"]:
            if s.get("n"):
                feedback.pushInfo(f"seam {s['pair'][0]} | {s['pair'][1]}: {s['before']['mean_px']:.3f} px before, "
                                  f"{s['after']['mean_px']:.3f} px after")
                seam = max(seam, s["after"]["mean_px"])
        out = rep["outputs"]
        return {self.OUTPUT_FOLDER: folder, "OUTPUT_RPCS": [e["rpb"] for e in rep["images"].values()],
                self.OUTPUT_REPORT: out["report"], "OUTPUT_CALIBRATION": out["calibration"],
                "OUTPUT_RESIDUALS": out["residuals"], "MAX_SEAM_PX": seam}
