"""``gf4cal:rpcinfo`` - what an RPC says: image size, height range, corners, ground sample distance, footprint."""
from __future__ import annotations

from qgis.core import (
    QgsCoordinateReferenceSystem,
    QgsFeature,
    QgsFeatureSink,
    QgsField,
    QgsFields,
    QgsGeometry,
    QgsProcessing,
    QgsProcessingOutputNumber,
    QgsProcessingOutputString,
    QgsProcessingParameterFeatureSink,
    QgsWkbTypes,
)
from qgis.PyQt.QtCore import QVariant

from ..base import Gf4calAlgorithm


class RpcInfo(Gf4calAlgorithm):
    NAME = "rpcinfo"
    DISPLAY = "RPC information and footprint"
    GROUP = "RPC tools"
    GROUP_ID = "rpctools"
    HELP = ("Reads the RPC of an image or of a standalone RPC file (.RPB, _RPC.TXT, vendor XML, JSON) and reports "
            "the image size, valid height range, footprint centre and the approximate ground sample distance along "
            "each image axis. The footprint is the image's corners localised on the DEM, or at the RPC's "
            "HEIGHT_OFF without a DEM.")
    OUTPUT_FOOTPRINT = "OUTPUT_FOOTPRINT"
    LABELS = {"WIDTH": "Image width (px)", "HEIGHT": "Image height (px)", "HEIGHT_MIN": "Minimum valid height (m)",
              "HEIGHT_MAX": "Maximum valid height (m)", "CENTER_LON": "Footprint centre longitude",
              "CENTER_LAT": "Footprint centre latitude", "GSD_SAMPLE": "Ground pixel size along samples (m)",
              "GSD_LINE": "Ground pixel size along lines (m)"}

    def initAlgorithm(self, config=None):
        self.add_input_rpc()
        self.add_rpc_parameter()
        self.add_dem_parameters()
        self._add(QgsProcessingParameterFeatureSink(self.OUTPUT_FOOTPRINT, self.tr("Footprint"),
                                                    QgsProcessing.TypeVectorPolygon, optional=True,
                                                    createByDefault=True),
                  "The image corners localised through the RPC, as a polygon in WGS84.")
        self.add_report_output("Everything above and the RPC offsets/scales as JSON.")
        for key, label in self.LABELS.items():
            self.addOutput(QgsProcessingOutputNumber(key, self.tr(label)))
        self.addOutput(QgsProcessingOutputString("SUMMARY", self.tr("Summary")))

    def run_algorithm(self, parameters, context, feedback, progress):
        from shapely import wkt

        from gdal_gf4cal.describe import describe_rpc
        from gdal_gf4cal.outputs import OutputSet
        from gdal_gf4cal.report import write_report_json

        path = self.input_path(parameters, context)
        dem = self.read_dem(parameters, context)
        progress(0.1, "reading the RPC")
        info = describe_rpc(path, dem=dem, rpc=self.rpc_file(parameters, context))
        self.push_warnings(feedback, info)
        footprint = wkt.loads(info["footprint_wkt"])
        centre = footprint.centroid
        (w, h), (hmin, hmax) = info["size"], info["height_range_m"]
        values = {"WIDTH": w, "HEIGHT": h, "HEIGHT_MIN": hmin, "HEIGHT_MAX": hmax, "CENTER_LON": centre.x,
                  "CENTER_LAT": centre.y, "GSD_SAMPLE": info["gsd_m"]["sample"], "GSD_LINE": info["gsd_m"]["line"]}
        summary = (f"{path} ({info['format']}): {w} x {h} px"
                   f"{'' if info['size_from_image'] else ' (from the RPC scales)'}, valid heights "
                   f"{hmin:.0f}..{hmax:.0f} m, centre {centre.x:.6f}, {centre.y:.6f}, GSD "
                   f"{values['GSD_SAMPLE']:.3g} x {values['GSD_LINE']:.3g} m; footprint on {info['footprint_height']}")
        feedback.pushInfo(summary)
        outputs = dict(values, SUMMARY=summary)
        progress(0.8, "writing outputs")
        report = self.output_file(parameters, self.OUTPUT_REPORT, context)
        if report:
            outs = OutputSet([path], overwrite=True, cancelled=progress.is_cancelled)
            tmp = outs.declare("report", report)
            with outs:
                write_report_json(info, tmp)
            outputs[self.OUTPUT_REPORT] = report
        fields = QgsFields()
        for name, kind in (("source", QVariant.String), ("width", QVariant.Int), ("height", QVariant.Int),
                           ("h_min_m", QVariant.Double), ("h_max_m", QVariant.Double),
                           ("gsd_sample_m", QVariant.Double), ("gsd_line_m", QVariant.Double)):
            fields.append(QgsField(name, kind))
        sink, dest = self.parameterAsSink(parameters, self.OUTPUT_FOOTPRINT, context, fields, QgsWkbTypes.Polygon,
                                          QgsCoordinateReferenceSystem("EPSG:4326"))
        if sink is not None:
            feat = QgsFeature(fields)
            feat.setGeometry(QgsGeometry.fromWkt(info["footprint_wkt"]))
            feat.setAttributes([path, w, h, hmin, hmax, values["GSD_SAMPLE"], values["GSD_LINE"]])
            sink.addFeature(feat, QgsFeatureSink.FastInsert)
            outputs[self.OUTPUT_FOOTPRINT] = dest
        return outputs
