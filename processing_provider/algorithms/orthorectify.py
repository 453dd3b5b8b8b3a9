"""``gf4cal:orthorectify`` - an orthoimage from an image, its (refined) RPC and a DEM made ellipsoidal."""
from __future__ import annotations

from qgis.core import (
    QgsProcessingOutputNumber,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterCrs,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFile,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
    QgsProcessingParameterRasterLayer,
)

from ..base import Gf4calAlgorithm

RESAMPLINGS = ["near", "bilinear", "cubic", "cubicspline", "lanczos", "average", "mode"]


class Orthorectify(Gf4calAlgorithm):
    NAME = "orthorectify"
    DISPLAY = "Orthorectify with RPC and DEM"
    GROUP = "RPC calibration"
    GROUP_ID = "calibration"
    HELP = ("Warps the image to a map grid with its RPC (or a refined RPC: a .vrt, .RPB or _RPC.TXT written by "
            "'Refine RPC with GCPs') over the DEM, with GDAL's warper. The RPC needs ellipsoidal heights: when the "
            "DEM's heights are above a geoid (declared by its CRS, or chosen below) a temporary ellipsoidal copy of "
            "the DEM over the scene is made with PROJ's geoid grid (us_nga_egm96_15.tif, us_nga_egm08_25.tif, or "
            "the legacy egm96_15.gtx / egm08_25.gtx, searched in PROJ's data folders), or the grid file you give. "
            "If the grid is missing the run stops and names it; nothing is written. Output: a tiled, compressed "
            "GeoTIFF in the chosen CRS (default the UTM zone of the scene), loaded in the project.")

    RPC = "RPC"
    CRS = "CRS"
    RESOLUTION = "RESOLUTION"
    RESAMPLING = "RESAMPLING"
    FORCE = "FORCE"
    OUTPUT = "OUTPUT"

    def initAlgorithm(self, config=None):
        self._add(QgsProcessingParameterRasterLayer(self.INPUT, self.tr("Image")),
                  "The image to orthorectify (its own RPC is used unless a refined RPC is given).")
        self._add(QgsProcessingParameterFile(self.RPC, self.tr("Refined RPC (optional)"), optional=True,
                                             fileFilter="RPC (*.vrt *.VRT *.RPB *.rpb *_RPC.TXT *_rpc.txt *.geom "
                                                        "*.XML *.xml)"),
                  "An RPC replacing the image's own: the .vrt, .RPB or _RPC.TXT written by 'Refine RPC with GCPs'; or "
                  "the product's RPC (.geom, RPC_*.XML) of a crop that states its origin in the product (a pixel "
                  "geotransform without CRS): the origin is applied and the log says so.")
        self._add(QgsProcessingParameterRasterLayer(self.DEM, self.tr("DEM")),
                  "Height model covering the scene (any GDAL raster, any CRS).")
        self.add_geoid_parameters()
        self._add(QgsProcessingParameterCrs(self.CRS, self.tr("Output CRS (empty: UTM zone of the scene)"),
                                            optional=True),
                  "Map projection of the orthoimage; empty: the WGS84 UTM zone of the scene centre.")
        self._add(QgsProcessingParameterNumber(self.RESOLUTION, self.tr("Pixel size (CRS units; 0: automatic)"),
                                               QgsProcessingParameterNumber.Double, 0.0, minValue=0.0),
                  "Output pixel size in the output CRS's units (metres for UTM); 0 lets GDAL choose (about the GSD).")
        self._add(QgsProcessingParameterEnum(self.RESAMPLING, self.tr("Resampling"), RESAMPLINGS, defaultValue=1),
                  "How image values are interpolated (bilinear by default).")
        p = self._add(QgsProcessingParameterBoolean(self.FORCE, self.tr("Write past the size limit"),
                                                    defaultValue=False, optional=True),
                      "Write an orthoimage larger than 4e9 pixels, or larger (uncompressed) than the free space; "
                      "without it such a pixel size is refused before anything is written.")
        p.setFlags(p.flags() | p.FlagAdvanced)
        self._add(QgsProcessingParameterRasterDestination(self.OUTPUT, self.tr("Orthoimage")),
                  "The orthoimage (GeoTIFF, tiled, deflate-compressed). Never an input.")
        self.addOutput(QgsProcessingOutputNumber("RESOLUTION_OUT", self.tr("Pixel size of the orthoimage")))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.errors import Gf4calError
        from gdal_gf4cal.geoid import GeoidGridMissing
        from gdal_gf4cal.workflows import orthorectify

        image = self.parameterAsRasterLayer(parameters, self.INPUT, context)
        dem = self.parameterAsRasterLayer(parameters, self.DEM, context)
        if image is None or dem is None:
            raise self.error("Choose the image (INPUT) and the DEM (DEM).")
        rpc = self.parameterAsFile(parameters, self.RPC, context) or None
        geoid = self.geoid_choice(parameters, context)
        crs = self.parameterAsCrs(parameters, self.CRS, context)
        crs_text = crs.authid() or crs.toWkt() if crs.isValid() else "utm"
        res = self.parameterAsDouble(parameters, self.RESOLUTION, context)
        out = self.parameterAsOutputLayer(parameters, self.OUTPUT, context)
        try:
            rep = orthorectify(image.source(), dem=dem.source(), out=out, rpc=rpc, geoid=geoid, crs=crs_text,
                               res_m=res if res > 0 else None,
                               resampling=RESAMPLINGS[self.parameterAsEnum(parameters, self.RESAMPLING, context)],
                               overwrite=True, force=self.parameterAsBool(parameters, self.FORCE, context),
                               progress=progress)
        except GeoidGridMissing as exc:
            raise self.error(str(exc.phrase("the 'Geoid grid file' parameter (GEOID_GRID)"))) from None
        except Gf4calError as exc:
            if "--force" not in str(exc):
                raise
            raise self.error(str(exc).replace("pass --force", "tick 'Write past the size limit' (FORCE)")) from None
        self.push_warnings(feedback, rep)
        self.name_output_layer(context, out, image.source())
        g = rep.get("geoid")
        feedback.pushInfo(f"orthoimage {rep['size_px'][0]} x {rep['size_px'][1]} px of {rep['res_m']:.3f} in "
                          f"{rep['crs']}; " + (f"DEM heights above {g['name']} made ellipsoidal" if g else
                                               "DEM heights used as ellipsoidal"))
        return {self.OUTPUT: out, "RESOLUTION_OUT": rep["res_m"]}
