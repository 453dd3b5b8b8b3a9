"""What every gf4cal algorithm shares: naming, the progress/cancel adapter, reading GCP layers, and the single place
where engine errors become ``QgsProcessingException`` (with no partial outputs left behind).
"""
from __future__ import annotations

import os
import re
import shutil
import traceback
import warnings
from typing import Any, Dict, List, Optional

from qgis.core import (
    QgsProcessing,
    QgsProcessingAlgorithm,
    QgsProcessingParameterBoolean,
    QgsProcessingException,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterField,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterRasterLayer,
    QgsProcessingParameterString,
    QgsWkbTypes,
)
from qgis.PyQt.QtCore import QCoreApplication

from gdal_gf4cal.errors import CancelledError, Gf4calError

#: The GEOID choice of every algorithm (one vocabulary: same order, labels and default, index 0), and the engine's
#: ``geoid=`` word of each (the CLI's ``--geoid auto|egm96|egm2008|none|PATH``, same order).
GEOID_OPTIONS = ["As the DEM's CRS declares (ellipsoidal when it declares none)", "Heights above EGM96",
                 "Heights above EGM2008", "Ellipsoidal heights (no conversion, whatever the CRS declares)"]
GEOID_VALUES = ["auto", "egm96", "egm2008", "none"]
PIXEL_CONVENTIONS = [None, "corner", "center"]
PIXEL_CONVENTION_LABELS = ["The file format's own (centre for orthority GeoJSON and ASP .gcp, else corner)",
                           "Pixel corners at integers (GDAL: first pixel centre at 0.5)",
                           "Pixel centres at integers (orthority, ASP: first pixel centre at 0)"]
GEOID_GRID_WORDS = "the 'Geoid grid file' parameter (GEOID_GRID)"
PLAUSIBILITY_WORDS = "CHECK_PLAUSIBILITY, an advanced parameter"


def qgis_words(message: str) -> str:
    """An engine message with its interface-neutral option names in the words of the QGIS dialog."""
    return (message.replace("(geoid=<grid path>, --geoid) or geoid=False",
                            f"({GEOID_GRID_WORDS}) or choose 'DEM heights are: Ellipsoidal heights'")
            .replace("geoid=<grid path>", GEOID_GRID_WORDS)
            .replace("(--columns)", "(GCP_COLUMNS)").replace("(--gcp-pixel-convention)", "(GCP_PIXEL_CONVENTION)")
            .replace("(--bands-of)", "(BANDS_OF)").replace("(--rpc)", "(RPCS)")
            .replace("(--no-plausibility-check)", f"({PLAUSIBILITY_WORDS})").replace("(--geoid)", "(GEOID)"))


def split_items(text: str) -> List[str]:
    """``"a=b, c=d"`` (commas, semicolons, spaces or new lines between items) -> ``["a=b", "c=d"]``."""
    return [t for t in re.split(r"[\s,;]+", text or "") if t]


TRACKER = "https://github.com/gdal-gf4cal/gdal_gf4cal/issues"

#: The papers the help texts cite (an algorithm lists its keys in ``REFERENCES``; its help ends with them).
PAPERS = {
    "grodecki": "Grodecki J., Dial G. (2003). Block adjustment of high-resolution satellite images described by "
                "rational polynomials. Photogrammetric Engineering & Remote Sensing 69(1), 59-68.",
    "fraser": "Fraser C.S., Hanley H.B. (2005). Bias-compensated RPCs for sensor orientation of high-resolution "
              "satellite imagery. Photogrammetric Engineering & Remote Sensing 71(8), 909-915.",
    "tao": "Tao C.V., Hu Y. (2001). A comprehensive study of the rational function model for photogrammetric "
           "processing. Photogrammetric Engineering & Remote Sensing 67(12), 1347-1357.",
    "huang": "Huang Q., Zhao H., Yang J. (2014). Geometric positioning and error analysis of HJ-1 wide-coverage CCD "
             "images (detector-position polynomial). Geomatics and Information Science of Wuhan University 39(12), "
             "1425-1429.",
    "pi": "Pi Y., Wang M., Wang S., Zhao H., Zhao L. (2023). On-orbit geometric calibration of the Gaofen-4 "
          "visible area-array camera based on the rational polynomial model. Acta Optica Sinica.",
    "wu": "Wu H., Bai Y., Wang L., Zhang L., Wang D., Ba Q., Jia Y., Zhong X. On-orbit geometric calibration of the "
          "Jilin1-KF01A wide-field camera: look angles per CCD, inter-CCD consistency, band-to-band registration "
          "(Chang Guang Satellite Technology).",
    "zhang": "Zhang Y., Wang M., Wan Y., Zhou B., Feng J., Cao B., Yao Y. (2023). A pan-multispectral registration "
             "error compensation model for Gaofen-7 image fusion. Geomatics and Information Science of Wuhan "
             "University 48(7).",
}


def one_line(exc: BaseException) -> str:
    """The first line of an exception's message (the engine's messages say what to do in one line)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def planar_rms(stats) -> float:
    """Planar RMS (px) from an engine statistics dict's per-axis RMS; NaN when the role has no points."""
    if not stats or not stats.get("n"):
        return float("nan")
    return float((stats["sample"]["rms"] ** 2 + stats["line"]["rms"] ** 2) ** 0.5)


#: GCP files whose format maps its own fields (no field choice): ASP .gcp and QGIS Georeferencer .points.
SELF_DESCRIBED_GCP_EXTS = (".gcp", ".points")


def layer_file_path(layer) -> str:
    """The file a vector layer reads (OGR ``path|layername=...`` or a delimited-text ``file:///path?...`` URI)."""
    from qgis.core import QgsProviderRegistry
    parts = QgsProviderRegistry.instance().decodeUri(layer.providerType(), layer.source())
    path = parts.get("path") if parts else None
    if not path:
        src = layer.source()
        if src.startswith("file:"):
            from qgis.PyQt.QtCore import QUrl
            path = QUrl(src).toLocalFile()
        else:
            path = src.split("|")[0]
    return path


def _layer_file(layer) -> str:
    """The file of the GCP layer read with a column map (GCP_COLUMNS); refused when it is not read from a file."""
    if layer is None:
        raise QgsProcessingException("A column map (GCP_COLUMNS) needs a GCP layer read from a file.")
    path = layer_file_path(layer)
    if not os.path.isfile(path):
        raise QgsProcessingException(f"A column map (GCP_COLUMNS) needs a GCP layer read from a file, not {path!r}.")
    return path


class FeedbackProgress:
    """Engine progress callback over a ``QgsProcessingFeedback``: fraction -> percent, cancel -> CancelledError."""

    def __init__(self, feedback, start: float = 0.0, stop: float = 1.0):
        self.feedback = feedback
        self.start, self.stop = start, stop
        self._last_message = None

    def __call__(self, fraction: float, message: str = "") -> None:
        if self.feedback is None:
            return
        if self.feedback.isCanceled():
            raise CancelledError("cancelled by the user")
        self.feedback.setProgress(100.0 * (self.start + (self.stop - self.start) * min(max(fraction, 0.0), 1.0)))
        if message and message != self._last_message:
            self._last_message = message
            self.feedback.setProgressText(message)

    def is_cancelled(self) -> bool:
        """Asked by the output policy right before it renames the written outputs into place."""
        return self.feedback is not None and self.feedback.isCanceled()

    def sub(self, start: float, stop: float) -> "FeedbackProgress":
        """A callback mapping [0, 1] of a sub-task onto [start, stop] of this one."""
        a = self.start + (self.stop - self.start) * start
        b = self.start + (self.stop - self.start) * stop
        return FeedbackProgress(self.feedback, a, b)


class Gf4calAlgorithm(QgsProcessingAlgorithm):
    """Base of the gf4cal algorithms.

    Subclasses set ``NAME`` (stable lowercase id), ``DISPLAY``, ``GROUP``/``GROUP_ID`` and ``HELP``, define
    ``initAlgorithm`` and implement :meth:`run_algorithm` (instead of ``processAlgorithm``). Output files are
    registered with
    :meth:`output_file` (folders with :meth:`output_folder`) so that a failed or cancelled run removes what it
    created.
    """

    NAME = ""
    DISPLAY = ""
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ""
    REFERENCES: tuple = ()       # keys of PAPERS cited by HELP

    # Parameter names shared by the algorithms (same name = same meaning).
    INPUT = "INPUT"
    GCPS = "GCPS"
    SAMPLE_FIELD = "SAMPLE_FIELD"
    LINE_FIELD = "LINE_FIELD"
    HEIGHT_FIELD = "HEIGHT_FIELD"
    ID_FIELD = "ID_FIELD"
    ROLE_FIELD = "ROLE_FIELD"
    SIGMA_FIELD = "SIGMA_FIELD"
    GCP_COLUMNS = "GCP_COLUMNS"
    GCP_PIXEL_CONVENTION = "GCP_PIXEL_CONVENTION"
    GCP_RASTER = "GCP_RASTER"
    DEM = "DEM"
    GEOID = "GEOID"
    GEOID_GRID = "GEOID_GRID"
    OUTPUT_RPC = "OUTPUT_RPC"
    OUTPUT_GPKG = "OUTPUT_GPKG"
    OUTPUT_PLOT = "OUTPUT_PLOT"
    OUTPUT_REPORT = "OUTPUT_REPORT"
    CHECK_PLAUSIBILITY = "CHECK_PLAUSIBILITY"
    RPC = "RPC"
    RPCS = "RPCS"

    def __init__(self):
        super().__init__()
        self._created: List[str] = []
        self._created_dirs: List[str] = []
        self._to_load: List[tuple] = []

    # ---- identity ------------------------------------------------------------------------------------------
    def tr(self, text: str) -> str:
        return QCoreApplication.translate("gf4cal", text)

    def name(self) -> str:
        return self.NAME

    def displayName(self) -> str:
        return self.tr(self.DISPLAY)

    def group(self) -> str:
        return self.tr(self.GROUP)

    def groupId(self) -> str:
        return self.GROUP_ID

    def shortHelpString(self) -> str:
        """The algorithm's description, then what each parameter means (self-contained: no manual needed)."""
        lines = [self.tr(self.HELP)]
        params = [p for p in self.parameterDefinitions() if p.help()]
        if params:
            lines.append("")
            lines.append(self.tr("Parameters:"))
            lines += [f"- {p.description()} ({p.name()}): {p.help()}" for p in params]
        if self.REFERENCES:
            lines += ["", self.tr("References:")] + [f"- {PAPERS[k]}" for k in self.REFERENCES]
        return "\n".join(lines)

    def helpUrl(self) -> str:
        return "https://github.com/gdal-gf4cal/gdal_gf4cal"

    def createInstance(self):
        return type(self)()

    # ---- common parameters ---------------------------------------------------------------------------------
    def _add(self, param, help_text: str):
        param.setHelp(self.tr(help_text))
        self.addParameter(param)
        return param

    def add_input_image(self, description="Image (with an RPC)", rpc_file: bool = True):
        """INPUT as a raster layer picker; with ``rpc_file`` a standalone RPC file path is also accepted."""
        text = "The image, carrying an RPC (TIFF tags, .RPB or _RPC.TXT beside it, NITF)."
        if rpc_file:
            text += " From Python or qgis_process a standalone RPC file (.RPB, _RPC.TXT) may be given instead."
        self._add(QgsProcessingParameterRasterLayer(self.INPUT, self.tr(description)), text)

    def add_rpc_parameter(self):
        """RPC (optional file): the RPC of an image that carries none (CLI ``--rpc``; a crop and its product's RPC:
        the crop's origin is applied, :func:`gdal_gf4cal.crop.image_rpc`)."""
        return self._add(QgsProcessingParameterFile(self.RPC, self.tr("RPC file (if not in the image)"), optional=True,
                                                    behavior=QgsProcessingParameterFile.File),
                         "The RPC file of an image that carries none (.geom, RPC_*.XML, .RPB, _RPC.TXT). For a crop "
                         "that states its origin in the product (a pixel geotransform without CRS) give the "
                         "product's RPC: the origin is applied and the log says so. Empty: the image's own RPC, "
                         "else an RPC file named like the image beside it.")

    def add_rpc_pairs_parameter(self):
        """RPCS (optional text): ``IMAGE=RPC`` items of a many-image algorithm (CLI ``--rpc IMAGE=RPC ...``)."""
        return self._add(QgsProcessingParameterString(self.RPCS, self.tr("RPC files (if not in the images): "
                                                                         "IMAGE=RPC, ..."), optional=True,
                                                      multiLine=True),
                         "For images that carry no RPC: items IMAGE=RPC (the image's file name or path and its RPC "
                         "file), separated by commas, semicolons or new lines. For a crop that states its origin in "
                         "the product (a pixel geotransform without CRS) give the product's RPC: the origin is "
                         "applied and the log says so. Images not named: their own RPC, else an RPC file named "
                         "like the image beside it.")

    def rpc_pairs(self, parameters, context) -> List[str]:
        """The RPCS parameter's ``IMAGE=RPC`` items (:func:`split_items`)."""
        return split_items(self.parameterAsString(parameters, self.RPCS, context))

    def rpc_file(self, parameters, context) -> Optional[str]:
        """The RPC parameter's path, or None (also for an algorithm without it)."""
        if self.parameterDefinition(self.RPC) is None:
            return None
        return self.parameterAsFile(parameters, self.RPC, context) or None

    def add_input_rpc(self, description="Image or RPC file"):
        self._add(QgsProcessingParameterFile(self.INPUT, self.tr(description),
                                             behavior=QgsProcessingParameterFile.File),
                  "A raster carrying an RPC (TIFF tags, .RPB, _RPC.TXT, NITF) or a standalone RPC sidecar.")

    def add_gcp_parameters(self, optional_sigma=True):
        # TypeVector too: a header-less CSV/text file (no geometry) is read with a column map (GCP_COLUMNS).
        # Optional only so that a raster with embedded GCPs (GCP_RASTER) can replace it; read_gcps needs one.
        self._add(QgsProcessingParameterFeatureSource(self.GCPS, self.tr("Ground control points"),
                                                      [QgsProcessing.TypeVectorPoint, QgsProcessing.TypeVector],
                                                      optional=True),
                  "Point layer: the geometry is the ground position (any CRS); fields give the image position. "
                  "An orthority GCP GeoJSON ('ji' property), an ASP .gcp or a QGIS Georeferencer .points file is "
                  "read as the command line reads it (its fields mapped by the format; the field choices below are "
                  "not used). Or a header-less CSV/text file read with a column map (GCP_COLUMNS). Or leave it empty "
                  "and give a raster with embedded GCPs (GCP_RASTER).")
        fields = [
            (self.SAMPLE_FIELD, "Image column (sample) field", "sample", False,
             "Field holding the image column of each GCP, in pixels, GDAL convention (first pixel centre 0.5)."),
            (self.LINE_FIELD, "Image row (line) field", "line", False,
             "Field holding the image row of each GCP, in pixels, GDAL convention (first pixel centre 0.5)."),
            (self.HEIGHT_FIELD, "Ellipsoidal height field", "h", True,
             "Field holding each GCP's ellipsoidal height (m); empty or missing heights are taken from the DEM."),
            (self.ID_FIELD, "GCP id field", "id", True, "Field naming each GCP (default: feature order)."),
            (self.ROLE_FIELD, "Role field (control/check)", "role", True,
             "Field with 'control' (used in the estimate) or 'check' (only evaluated); default: all control."),
        ]
        if optional_sigma:
            fields.append((self.SIGMA_FIELD, "Measurement precision field (px)", "sigma", True,
                           "Field with each GCP's a priori precision in pixels (relative weights); default 1."))
        for name, desc, default, _required, help_text in fields:
            # Optional for Processing even when the engine needs the field: a missing value then means the default
            # name (qgis_process / processing.run need not repeat it); read_gcps checks that the field exists.
            p = QgsProcessingParameterField(name, self.tr(desc), default, self.GCPS,
                                            QgsProcessingParameterField.Any, optional=True)
            self._add(p, help_text)
        p = self._add(QgsProcessingParameterString(self.GCP_COLUMNS, self.tr("Column map of a header-less GCP file"),
                                                   optional=True),
                      "For a GCP layer read from a CSV/text file without a header line: the meaning of its columns "
                      "in order, e.g. id,sample,line,lon,lat,h (x,y for map coordinates, - to skip a column). "
                      "When given, the file is read with this map and the field choices above are not used.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        p = self._add(QgsProcessingParameterRasterLayer(self.GCP_RASTER, self.tr("Raster with embedded GCPs "
                                                                                 "(instead of the GCP layer)"),
                                                        optional=True),
                      "A raster whose GCPs (GeoTIFF tie points, GDAL GCPs) are the ground control points, read in "
                      "the pixel convention below (GeoTIFF: corners at integers unless the file was written with "
                      "centres); all GCPs are control points.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        p = self._add(QgsProcessingParameterEnum(self.GCP_PIXEL_CONVENTION, self.tr("GCP image coordinates are"),
                                                 PIXEL_CONVENTION_LABELS, defaultValue=0, optional=True),
                      "Pixel convention of the GCPs' image coordinates; a wrong choice biases them by half a pixel. "
                      "They are converted to GDAL's (corners at integers).")
        p.setFlags(p.flags() | p.FlagAdvanced)

    def add_plausibility_parameter(self):
        """CHECK_PLAUSIBILITY (advanced, default on): the engine's GCP plausibility check (CLI
        ``--no-plausibility-check``); its refusals name this parameter (:func:`qgis_words`)."""
        p = self._add(QgsProcessingParameterBoolean(self.CHECK_PLAUSIBILITY, self.tr("Check the GCPs' plausibility"),
                                                    defaultValue=True, optional=True),
                      "Refuse GCPs that cannot belong to this image: beyond its RPC's domain, lon/lat swapped, "
                      "another CRS or scene, heights in feet or on another vertical datum than the DEM's. GCPs "
                      "outside the image but inside its RPC's domain (field GCPs just outside a crop) are used "
                      "with a warning either way. Untick only for points you know to be right.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        return p

    def check_plausibility(self, parameters, context) -> bool:
        """The CHECK_PLAUSIBILITY choice (True when not given)."""
        if parameters.get(self.CHECK_PLAUSIBILITY) is None:
            return True
        return self.parameterAsBool(parameters, self.CHECK_PLAUSIBILITY, context)

    def add_dem_parameters(self, optional=True):
        self._add(QgsProcessingParameterRasterLayer(self.DEM, self.tr("DEM"), optional=optional),
                  "Height model (any GDAL raster, any CRS) for GCP heights and line-of-sight intersections.")
        self.add_geoid_parameters()

    def add_geoid_parameters(self):
        """GEOID (what the DEM's heights are above, :data:`GEOID_OPTIONS`) and GEOID_GRID (a grid file), advanced:
        the same two parameters in every algorithm with a DEM."""
        p = QgsProcessingParameterEnum(self.GEOID, self.tr("DEM heights are"), GEOID_OPTIONS, defaultValue=0,
                                       optional=True)
        p.setFlags(p.flags() | p.FlagAdvanced)
        self._add(p, "What the DEM's heights are above. 'As the DEM's CRS declares' converts heights above EGM96 or "
                     "EGM2008 to ellipsoidal heights (with PROJ's geoid grid) when the CRS says so and uses them as "
                     "they are otherwise; 'Ellipsoidal heights' never converts.")
        p = QgsProcessingParameterFile(self.GEOID_GRID, self.tr("Geoid grid file (optional)"), optional=True,
                                       behavior=QgsProcessingParameterFile.File,
                                       fileFilter="Geoid grids (*.tif *.gtx);;All files (*)")
        p.setFlags(p.flags() | p.FlagAdvanced)
        self._add(p, "A geoid grid (.tif/.gtx) to use instead of PROJ's: the DEM's heights are above this geoid.")

    def geoid_choice(self, parameters, context):
        """The engine's ``geoid=`` from GEOID and GEOID_GRID: the grid path when given, else a word of
        :data:`GEOID_VALUES` (``"auto"`` for an algorithm without GEOID)."""
        geoid = GEOID_VALUES[self.parameterAsEnum(parameters, self.GEOID, context)] \
            if self.parameterDefinition(self.GEOID) is not None else "auto"
        if self.parameterDefinition(self.GEOID_GRID) is not None:
            geoid = self.parameterAsFile(parameters, self.GEOID_GRID, context) or geoid
        return geoid

    def add_plot_output(self, help_text: str):
        self._add(QgsProcessingParameterFileDestination(self.OUTPUT_PLOT, self.tr("Residual plot"),
                                                        self.tr("PNG image (*.png)"), optional=True,
                                                        createByDefault=False), help_text)

    def add_report_output(self, help_text: str):
        self._add(QgsProcessingParameterFileDestination(self.OUTPUT_REPORT, self.tr("Report (JSON)"),
                                                        self.tr("JSON files (*.json)"), optional=True,
                                                        createByDefault=False), help_text)

    def error(self, message: str):
        """A QgsProcessingException with a translated one-line message (raise it)."""
        return QgsProcessingException(self.tr(message))

    # ---- reading parameters --------------------------------------------------------------------------------
    def input_path(self, parameters, context) -> str:
        definition = self.parameterDefinition(self.INPUT)
        path = None
        if isinstance(definition, QgsProcessingParameterRasterLayer):
            layer = self.parameterAsRasterLayer(parameters, self.INPUT, context)
            if layer is not None:
                path = layer.source()
            else:                           # a standalone RPC file given by path (not a raster)
                path = self.parameterAsString(parameters, self.INPUT, context)
        else:
            path = self.parameterAsFile(parameters, self.INPUT, context)
        if not path:
            raise QgsProcessingException(self.tr("No input given: choose an image with an RPC or an RPC file."))
        if not os.path.exists(path):
            raise QgsProcessingException(self.tr(f"Input not found: {path}; choose an existing image or RPC file "
                                                 f"(INPUT)."))
        return path

    def dem_source(self, parameters, context):
        """``(path, geoid)`` of the DEM parameter for a workflow taking a DEM path and a geoid choice, or
        ``(None, None)``: the geoid as the engine's ``geoid=`` (:meth:`geoid_choice`)."""
        layer = self.parameterAsRasterLayer(parameters, self.DEM, context)
        if layer is None:
            return None, None
        geoid = self.geoid_choice(parameters, context)
        return layer.source(), geoid

    def read_dem(self, parameters, context):
        """The DEM parameter as an engine :class:`gdal_gf4cal.dem.DEM`, or None."""
        path, geoid = self.dem_source(parameters, context)
        if path is None:
            return None
        from gdal_gf4cal.dem import DEM
        return DEM.from_file(path, geoid=geoid)

    def read_gcps(self, parameters, context, feedback, dem=None):
        """The GCPs as an engine GCP table (DESIGN.md schema, EPSG:4326), read by the engine's own readers.

        A raster with embedded GCPs (GCP_RASTER); a file whose format names its own fields (orthority GCP GeoJSON,
        ASP ``.gcp``, QGIS ``.points``: :meth:`self_described_gcp_file`) or a header-less file with a column map
        (GCP_COLUMNS) read as the CLI reads it (:func:`gdal_gf4cal.gcp.read_gcps`, with the input image); else the
        point layer with the chosen fields (:meth:`read_gcp_fields`).
        """
        from gdal_gf4cal.gcp import read_gcps

        convention = PIXEL_CONVENTIONS[self.parameterAsEnum(parameters, self.GCP_PIXEL_CONVENTION, context)] \
            if self.parameterDefinition(self.GCP_PIXEL_CONVENTION) is not None else None
        raster = self.parameterAsRasterLayer(parameters, self.GCP_RASTER, context) \
            if self.parameterDefinition(self.GCP_RASTER) is not None else None
        has_layer = parameters.get(self.GCPS) not in (None, "")
        if raster is not None:
            if has_layer:
                raise QgsProcessingException(self.tr(
                    "Give either the GCP layer (GCPS) or a raster with embedded GCPs (GCP_RASTER), not both."))
            return read_gcps(raster.source(), dem=dem, pixel_convention=convention)
        if not has_layer:
            raise QgsProcessingException(self.tr(
                "Choose the GCP layer (GCPS), or a raster with embedded GCPs (GCP_RASTER)."))
        own = self.self_described_gcp_file(parameters, context)
        if own is not None:
            return read_gcps(own, dem=dem, pixel_convention=convention, image=self._gcp_image(parameters, context))
        columns = self.parameterAsString(parameters, self.GCP_COLUMNS, context) \
            if self.parameterDefinition(self.GCP_COLUMNS) is not None else ""
        if columns.strip():    # a header-less file: the engine reads it with the map (the fields are not used)
            return read_gcps(_layer_file(self.parameterAsVectorLayer(parameters, self.GCPS, context)), dem=dem,
                             columns=columns, pixel_convention=convention)
        return self.read_gcp_fields(parameters, context, feedback, dem, convention)

    def self_described_gcp_file(self, parameters, context) -> Optional[str]:
        """The GCP file when its format maps its own fields, as the CLI reads it: ASP ``.gcp``, QGIS ``.points``, or
        orthority's GCP GeoJSON (a ``ji`` property holding [column, row]); else None (a layer read by its fields)."""
        value = parameters.get(self.GCPS)
        if isinstance(value, str):
            path = value.split("|")[0]
            if path.startswith("file:"):
                from qgis.PyQt.QtCore import QUrl
                path = QUrl(path).toLocalFile()
        else:
            layer = self.parameterAsVectorLayer(parameters, self.GCPS, context)
            path = layer_file_path(layer) if layer is not None else None
        if not path or not os.path.isfile(path):
            return None
        ext = os.path.splitext(path)[1].lower()
        if ext in SELF_DESCRIBED_GCP_EXTS:
            return path
        if ext in (".geojson", ".json"):
            from qgis.core import QgsVectorLayer
            if "ji" in QgsVectorLayer(path, "gcps", "ogr").fields().names():
                return path
        return None

    def _gcp_image(self, parameters, context) -> Optional[str]:
        """The input image the GCPs belong to (selects its rows of a multi-image GCP file), or None."""
        if not isinstance(self.parameterDefinition(self.INPUT), QgsProcessingParameterRasterLayer):
            return None
        layer = self.parameterAsRasterLayer(parameters, self.INPUT, context)
        return layer.source() if layer is not None else None

    def read_gcp_fields(self, parameters, context, feedback, dem, convention):
        """The GCP point layer read with its chosen fields (SAMPLE_FIELD, ...) by
        :func:`gdal_gf4cal.gcp_formats.read_gcp_layer` (geometry = ground position in any CRS, reprojected to
        WGS84); QGIS hands over the layer's file, exporting it to a temporary GeoPackage only when OGR cannot read
        its source (a memory layer, a selection)."""
        from gdal_gf4cal.gcp import validate_gcps
        from gdal_gf4cal.gcp_formats import read_gcp_layer

        source = self.parameterAsSource(parameters, self.GCPS, context)
        if source is None:
            raise QgsProcessingException(self.invalidSourceError(parameters, self.GCPS))
        if QgsWkbTypes.geometryType(source.wkbType()) != QgsWkbTypes.PointGeometry:
            raise QgsProcessingException(self.tr(
                "The GCP layer must be a point layer (ground positions), or a header-less CSV/text file read with "
                "a column map (GCP_COLUMNS)."))
        chosen = self._chosen_fields(parameters, context, source.fields().names())
        if source.featureCount() == 0:
            raise QgsProcessingException(self.tr("The GCP layer has no features."))
        if "h" not in chosen and dem is None:
            raise QgsProcessingException(self.tr(
                f"The GCPs have no height (no {self.HEIGHT_FIELD}); choose the height field or give a DEM to take "
                "the heights from."))
        path, layer = self.parameterAsCompatibleSourceLayerPathAndLayerName(
            parameters, self.GCPS, context, ["gpkg", "geojson", "shp", "fgb"], "gpkg", feedback)
        if feedback is not None and feedback.isCanceled():
            raise CancelledError("cancelled by the user")
        table = read_gcp_layer(path, layer=layer or None, dem=dem, sample_field=chosen.get("sample"),
                               line_field=chosen.get("line"), height_field=chosen.get("h"),
                               pixel_convention=convention)
        changed = False
        for key in ("id", "role", "sigma"):
            field = chosen.get(key)
            if field and field != key and field in table.columns:
                values = table[field]
                if key == "id":
                    values = values.astype(str)
                elif key == "role":
                    values = values.where(values.notna() & (values.astype(str) != ""), "control").astype(str)
                else:
                    values = values.astype(float).fillna(1.0)
                table[key] = values.to_numpy()
                changed = True
        return validate_gcps(table, source=f"GCP layer {source.sourceName()!r}", dem=dem) if changed else table

    def _chosen_fields(self, parameters, context, names) -> Dict[str, str]:
        """``{engine column: layer field}`` of the field parameters; a required or explicitly chosen field the layer
        lacks is an error naming the layer's fields."""
        chosen = {}
        for param, key, required in ((self.SAMPLE_FIELD, "sample", True), (self.LINE_FIELD, "line", True),
                                     (self.HEIGHT_FIELD, "h", False), (self.ID_FIELD, "id", False),
                                     (self.ROLE_FIELD, "role", False), (self.SIGMA_FIELD, "sigma", False)):
            if self.parameterDefinition(param) is None:
                continue
            field = self.parameterAsString(parameters, param, context)
            if not field:
                if required:
                    raise QgsProcessingException(self.tr(f"Choose the GCP layer's {key} field ({param})."))
                continue
            if field not in names:
                explicit = param in parameters and parameters[param] not in (None, "")
                if required or explicit:
                    raise QgsProcessingException(self.tr(
                        f"The GCP layer has no field '{field}' ({param}); its fields are: {', '.join(names)}. "
                        f"Choose the field holding the {key} values."))
                continue  # an optional field left at its default name that the layer does not have
            chosen[key] = field
        return chosen

    def push_warnings(self, feedback, rep) -> None:
        """Send the workflow report's ``notes`` and ``warnings`` (lists of one-line str) to the Processing log."""
        if feedback is None:
            return
        for n in (rep.get("notes", []) if isinstance(rep, dict) else []):
            feedback.pushInfo(str(n))
        for w in (rep.get("warnings", []) if isinstance(rep, dict) else getattr(rep, "warnings", []) or []):
            feedback.pushWarning(str(w))

    # ---- outputs -------------------------------------------------------------------------------------------
    def output_file(self, parameters, name, context) -> Optional[str]:
        """A file destination's path (None when optional and unset). The workflow writes it under its output
        policy (:class:`gdal_gf4cal.outputs.OutputSet`): folders made and files written by a failed or cancelled
        run are removed there, so nothing is created here (a new path is still removed if the run fails)."""
        path = self.parameterAsFileOutput(parameters, name, context)
        if path and not os.path.exists(path):
            self._created.append(path)    # safety net for an algorithm that writes it itself
        return path or None

    def output_folder(self, parameters, name, context) -> str:
        """A folder destination's path; the workflow creates it (and removes it again if the run fails)."""
        folder = self.parameterAsString(parameters, name, context)
        if not folder:
            raise QgsProcessingException(self.tr(f"Choose an output folder ({name})."))
        return os.path.abspath(folder)

    def load_on_completion(self, uri: str, name: str, kind: str = "vector", style: Optional[str] = None) -> None:
        """Open ``uri`` as a layer (with its default style, or the QML text ``style``) in the project when the
        algorithm finishes."""
        self._to_load.append((uri, name, kind) if style is None else (uri, name, kind, style))

    def name_output_layer(self, context, destination: str, image: str) -> None:
        """Name the raster output Processing loads ``<image stem> ortho`` (not the parameter's label)."""
        if destination and context.willLoadLayerOnCompletion(destination):
            stem = os.path.splitext(os.path.basename(image.split("|")[0]))[0]
            context.layerToLoadOnCompletionDetails(destination).name = f"{stem} ortho"

    def load_gpkg_on_completion(self, path: str, layers=("footprint", "residual_vectors_before",
                                                         "residual_vectors", "gcps")) -> None:
        """Load the residual GeoPackage's layers (those present), bottom to top, with their stored styles, named
        by their titles (the arrows state their one exaggeration: "residuals before (x37)", "residuals after (x37)")."""
        from gdal_gf4cal.report.gpkg import layer_titles
        titles = layer_titles(path)
        for layer in layers:
            if layer in titles:
                self._to_load.append((f"{path}|layername={layer}", titles[layer], "vector"))

    def postProcessAlgorithm(self, context, feedback):
        # Runs in the main thread after processAlgorithm: layers are created here, not in the worker thread.
        from qgis.core import QgsProcessingContext, QgsRasterLayer, QgsVectorLayer
        for uri, name, kind, *style in getattr(self, "_to_load", []):
            layer = QgsRasterLayer(uri, name, "gdal") if kind == "raster" else QgsVectorLayer(uri, name, "ogr")
            if not layer.isValid():
                feedback.pushWarning(self.tr(f"Could not open {uri} as a layer"))
                continue
            if style:
                from qgis.PyQt.QtXml import QDomDocument
                doc = QDomDocument()
                doc.setContent(style[0])
                layer.importNamedStyle(doc)
            context.temporaryLayerStore().addMapLayer(layer)
            context.addLayerToLoadOnCompletion(layer.id(), QgsProcessingContext.LayerDetails(
                name, context.project(), name))
        self._to_load = []
        return {}

    def _remove_partial_outputs(self) -> None:
        self._to_load = []
        for path in self._created:
            for p in (path, path + ".aux.xml"):
                try:
                    os.remove(p)
                except OSError:
                    pass
        for folder in self._created_dirs:
            shutil.rmtree(folder, ignore_errors=True)
        self._created, self._created_dirs = [], []

    # ---- running -------------------------------------------------------------------------------------------
    def checkParameterValues(self, parameters, context):
        # An ASP .gcp or a QGIS .points file is no layer QGIS opens: the engine reads it (read_gcps).
        value = parameters.get(self.GCPS) if self.parameterDefinition(self.GCPS) is not None else None
        if isinstance(value, str) and os.path.isfile(value) and \
                os.path.splitext(value)[1].lower() in SELF_DESCRIBED_GCP_EXTS:
            parameters = {k: v for k, v in parameters.items() if k != self.GCPS}
        return super().checkParameterValues(parameters, context)

    def run_algorithm(self, parameters: Dict[str, Any], context, feedback,
                      progress: FeedbackProgress) -> Dict[str, Any]:
        raise NotImplementedError

    def processAlgorithm(self, parameters, context, feedback):
        self._created, self._created_dirs, self._to_load = [], [], []
        progress = FeedbackProgress(feedback)
        caught: list = []
        try:
            # Engine warnings (e.g. a poorly conditioned GCP layout) go to the Processing log, not to stderr;
            # also when the run fails, where they often explain why.
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                warnings.filterwarnings("ignore", category=DeprecationWarning)
                result = self.run_algorithm(parameters, context, feedback, progress)
        except CancelledError:
            self._remove_partial_outputs()
            raise QgsProcessingException(self.tr("Cancelled; no output was written.")) from None
        except QgsProcessingException:
            self._remove_partial_outputs()
            raise
        except Gf4calError as exc:
            self._remove_partial_outputs()
            from gdal_gf4cal.geoid import GeoidGridMissing
            if isinstance(exc, GeoidGridMissing):
                exc = exc.phrase(GEOID_GRID_WORDS)
            raise QgsProcessingException(qgis_words(one_line(exc))) from None
        except (OSError, ValueError, ArithmeticError, RuntimeError) as exc:
            # GDAL (RuntimeError), file-system and numeric errors: still one line, the type says where.
            self._remove_partial_outputs()
            raise QgsProcessingException(f"{type(exc).__name__}: {one_line(exc)}") from None
        except Exception as exc:
            # A bug, not bad input: the traceback goes to the log (for the report), the user gets one line, and
            # partial outputs are removed like for any other failure.
            if feedback is not None:
                feedback.pushDebugInfo(traceback.format_exc())
            self._remove_partial_outputs()
            raise QgsProcessingException(self.tr(
                f"Internal error ({type(exc).__name__}: {one_line(exc)}); no output was written. Please report it "
                f"with the log at {TRACKER}")) from None
        finally:
            for w in caught if feedback is not None else ():
                feedback.pushWarning(f"{w.category.__name__}: {w.message}")
        if feedback is not None:
            feedback.setProgress(100)
        self._created, self._created_dirs = [], []
        return result
