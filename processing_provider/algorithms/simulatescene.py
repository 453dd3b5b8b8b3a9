"""``gf4cal:simulatescene`` - a simulated scene with known truth: image, RPC, DEM, GCPs, truth.json."""
from __future__ import annotations

from qgis.core import (
    QgsProcessingOutputFile,
    QgsProcessingOutputNumber,
    QgsProcessingOutputRasterLayer,
    QgsProcessingOutputVectorLayer,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterNumber,
)

from ..base import Gf4calAlgorithm

SENSORS = ["gf4", "zy3", "hj1", "jl1", "gf7"]
SENSOR_LABELS = ["GF4 PMS (geostationary area array)", "ZY-3 three-line push-broom (nadir/fwd/bwd)",
                 "HJ-1A wide-swath CCD (push-broom)", "Jilin-1 KF01A staggered TDI CCDs",
                 "GF7 backward camera (pan + MS)"]


class SimulateScene(Gf4calAlgorithm):
    NAME = "simulatescene"
    DISPLAY = "Simulate a scene with known truth"
    GROUP = "Simulation"
    GROUP_ID = "simulation"
    HELP = ("Writes a simulated scene of a known sensor: image (placeholder or rendered), RPC fitted from the "
            "'current' rigorous model (with its systematic errors), DEM, GCPs measured on the 'true' model with the "
            "chosen noise and blunders, a dense check grid, the cameras and truth.json. Multi-image sensors get one "
            "sub-folder per image; the outputs below are those of the first image.")

    SENSOR = "SENSOR"
    SEED = "SEED"
    WIDTH = "WIDTH"
    HEIGHT = "HEIGHT"
    CROP_X0 = "CROP_X0"
    CROP_Y0 = "CROP_Y0"
    N_GCPS = "N_GCPS"
    GCP_NOISE = "GCP_NOISE"
    OUTLIER_FRACTION = "OUTLIER_FRACTION"
    CHECK_FRACTION = "CHECK_FRACTION"
    RENDER = "RENDER"
    OUTPUT_FOLDER = "OUTPUT_FOLDER"

    def initAlgorithm(self, config=None):
        Num = QgsProcessingParameterNumber
        self._add(QgsProcessingParameterEnum(self.SENSOR, self.tr("Sensor"), SENSOR_LABELS, defaultValue=0),
                  "Sensor family to simulate.")
        self._add(Num(self.SEED, self.tr("Random seed"), Num.Integer, 0, minValue=0),
                  "Seeds every random draw (errors, terrain, GCPs): same seed, same scene.")
        self._add(Num(self.WIDTH, self.tr("Crop width (px, 0 = full array)"), Num.Integer, 0, minValue=0),
                  "Crop the detector array around its centre to this width (geometry unchanged); 0 keeps it all.")
        self._add(Num(self.HEIGHT, self.tr("Crop height (px, 0 = full array)"), Num.Integer, 0, minValue=0),
                  "Crop height in pixels; 0 keeps the full array.")
        self._add(Num(self.CROP_X0, self.tr("Crop origin column in the product (-1 = centred)"), Num.Integer, -1,
                      minValue=-1),
                  "GF7: with a crop width and height, simulate the full product and write only the crop at this "
                  "column and row of the pan product (multiples of 4); the crop keeps its place (pixel-unit "
                  "geotransform without CRS, the product's RPC in product.RPB). -1: the crop is centred.")
        self._add(Num(self.CROP_Y0, self.tr("Crop origin row in the product (-1 = centred)"), Num.Integer, -1,
                      minValue=-1),
                  "Row of the crop's first pixel in the product (with the origin column).")
        self._add(Num(self.N_GCPS, self.tr("Number of GCPs per image"), Num.Integer, 200, minValue=0),
                  "GCPs drawn at random true image positions on the DEM.")
        self._add(Num(self.GCP_NOISE, self.tr("GCP measurement noise (px per axis)"), Num.Double, 0.6, minValue=0.0),
                  "Standard deviation of the image measurement noise added to the true positions.")
        self._add(Num(self.OUTLIER_FRACTION, self.tr("Blunder fraction"), Num.Double, 0.0, minValue=0.0,
                      maxValue=0.5),
                  "Share of GCPs given a 5-30 px blunder (flagged in truth, not in the GCP file).")
        self._add(Num(self.CHECK_FRACTION, self.tr("Check point fraction"), Num.Double, 0.3, minValue=0.0,
                      maxValue=0.9),
                  "Share of GCPs with role 'check' (only evaluated, never estimated from).")
        self._add(QgsProcessingParameterBoolean(self.RENDER, self.tr("Render the image"), defaultValue=False),
                  "Render scene.tif through the true model from a built-in texture (slower); otherwise a "
                  "placeholder raster of the right size.")
        self._add(QgsProcessingParameterFolderDestination(self.OUTPUT_FOLDER, self.tr("Output folder")),
                  "Folder receiving the scene (created).")
        self.addOutput(QgsProcessingOutputRasterLayer("IMAGE", self.tr("Image (with RPC)")))
        self.addOutput(QgsProcessingOutputFile("RPC", self.tr("RPC (.RPB)")))
        self.addOutput(QgsProcessingOutputVectorLayer("GCPS", self.tr("GCPs")))
        self.addOutput(QgsProcessingOutputRasterLayer("DEM", self.tr("DEM (ellipsoidal heights)")))
        self.addOutput(QgsProcessingOutputFile("CAMERA", self.tr("Current camera (JSON)")))
        self.addOutput(QgsProcessingOutputFile("TRUTH", self.tr("truth.json")))
        self.addOutput(QgsProcessingOutputNumber("RPC_FIT_MAX_PX", self.tr("RPC fit check error, max (px)")))

    def run_algorithm(self, parameters, context, feedback, progress):
        from gdal_gf4cal.workflows import simulate_scene

        sensor = SENSORS[self.parameterAsEnum(parameters, self.SENSOR, context)]
        w = self.parameterAsInt(parameters, self.WIDTH, context)
        h = self.parameterAsInt(parameters, self.HEIGHT, context)
        if (w == 0) != (h == 0):
            raise self.error("Give both crop width and height, or neither (0 = full array).")
        x0 = self.parameterAsInt(parameters, self.CROP_X0, context)
        y0 = self.parameterAsInt(parameters, self.CROP_Y0, context)
        if (x0 < 0) != (y0 < 0) or (x0 >= 0 and not w):
            raise self.error("Give the crop origin's column and row together, with the crop width and height.")
        crop = (x0, y0, w, h) if x0 >= 0 else None
        folder = self.output_folder(parameters, self.OUTPUT_FOLDER, context)
        res = simulate_scene(sensor, folder, overwrite=True, seed=self.parameterAsInt(parameters, self.SEED, context),
                          size=(w, h) if w and crop is None else None, crop=crop, n_gcps=self.parameterAsInt(parameters, self.N_GCPS, context),
                          gcp_noise_px=self.parameterAsDouble(parameters, self.GCP_NOISE, context),
                          outlier_fraction=self.parameterAsDouble(parameters, self.OUTLIER_FRACTION, context),
                          check_fraction=self.parameterAsDouble(parameters, self.CHECK_FRACTION, context),
                          render=self.parameterAsBool(parameters, self.RENDER, context), progress=progress)
        self.push_warnings(feedback, res)
        first = next(iter(res.images.values()))
        for name, im in res.images.items():
            chk = im.fit_report.check
            feedback.pushInfo(f"{name or sensor}: {len(im.gcps)} GCPs, RPC fit check max {chk.max_px:.2e} px "
                              f"({im.dir})")
        self.load_on_completion(first.paths["image"], f"{sensor} scene", "raster")
        self.load_on_completion(res.dem_path, f"{sensor} DEM", "raster")
        self.load_on_completion(first.paths["gcps_gpkg"], f"{sensor} GCPs", "vector")
        return {self.OUTPUT_FOLDER: res.out_dir, "IMAGE": first.paths["image"], "RPC": first.paths["rpc"],
                "GCPS": first.paths["gcps_gpkg"], "DEM": res.dem_path, "CAMERA": first.paths["camera_current"],
                "TRUTH": res.truth_path, "RPC_FIT_MAX_PX": float(first.fit_report.check.max_px)}
