"""``gf4cal:blockadjust`` in headless QGIS (issues 22, 24): the band-to-CCD pairing derived from the RPCs when
BANDS_OF is left empty, BANDS_OF as an optional table, every step named in the progress text with its number, the
log ending with the CLI's summary, and separate views (the real Pleiades Ventoux stereo pair's RPCs) refused with
one line pointing to the bundle adjustment."""
import json
import os

import pytest

import blocksim as B

DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data")


def _run(alg_id, params):
    """processing.run with a feedback that also records the progress texts and values."""
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback, QgsProject

    class Feedback(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.log, self.texts, self.values = [], [], []
            self.progressChanged.connect(self.values.append)

        def setProgressText(self, text):
            self.texts.append(text)
            super().setProgressText(text)

        def pushInfo(self, info):
            self.log.append(info)

        def pushWarning(self, warning):
            self.log.append(warning)

    fb = Feedback()
    ctx = QgsProcessingContext()
    ctx.setProject(QgsProject.instance())
    return processing.run(alg_id, params, feedback=fb, context=ctx), fb


def test_split_bands_of_table_and_text(qgis_app):
    from processing_provider.algorithms.blockadjust import split_bands_of
    assert split_bands_of(["ccd1", "ccd1_blue", "ccd2", "ccd2_blue"]) == ["ccd1=ccd1_blue", "ccd2=ccd2_blue"]
    assert split_bands_of("ccd1=ccd1_blue; ccd2=ccd2_blue") == ["ccd1=ccd1_blue", "ccd2=ccd2_blue"]
    assert split_bands_of([None]) == [] and split_bands_of(None) == []
    assert split_bands_of(["ccd1 ccd2_blue"]) == ["ccd1 ccd2_blue"]           # refused by the engine, see below


@pytest.mark.slow
def test_blockadjust_pairs_bands_from_the_rpcs_and_logs_the_cli_summary(qgis_app, tmp_path_factory, tmp_path):
    from gdal_gf4cal.workflows.block import summary_lines
    d = B.block_scene(str(tmp_path_factory.getbasetemp()))
    obs = os.path.join(d, "observations.csv")
    res, fb = _run("gf4cal:blockadjust", {"INPUT": [B.image_path(d, n) for n in B.NAMES],
                                          "DEM": os.path.join(d, "dem.tif"), "GCPS_FILE": obs, "TIES_FILE": obs,
                                          "OUTPUT_FOLDER": str(tmp_path / "out")})
    # no BANDS_OF: the same seams and registration as the explicit pairing of test_blockadjust
    assert len(res["OUTPUT_RPCS"]) == 20
    assert res["MAX_SEAM_BEFORE_PX"] > 1.5 and res["MAX_SEAM_PX"] < 0.1 and res["MAX_BAND_RMS_AFTER_PX"] < 0.3
    with open(res["OUTPUT_REPORT"]) as fh:
        rep = json.load(fh)
    assert {k: v["reference"] for k, v in rep["layout"]["images"].items() if k not in B.REF} == \
        {n: n.split("_")[0] + "_blue" for n in B.NAMES if n not in B.REF}
    # every step named with its number, the adjustment's iterations with their stage and phase, one message per
    # image refit and per image layer written; the bar never goes back
    texts = "\n".join(fb.texts)
    for words in ("step 1/5 reading the images", "step 2/5 adjusting the block: reference stage, iteration 1 "
                  "(a-priori weights): largest change of a corrected position", "bands stage, iteration",
                  "(robust rejection)", "step 3/5 refitting the RPCs: ccd4_nir (20 of 20)", "step 4/5 measuring the "
                  "seams", "step 5/5 writing residuals.gpkg, seams.png and report.json: residuals.gpkg: ccd1_blue",
                  "seams.png"):
        assert words in texts, words
    assert all(b >= a - 1e-9 for a, b in zip(fb.values, fb.values[1:]))
    # the log ends with the CLI's summary (band-to-band RMS, largest seam, converged)
    lines = summary_lines(rep)
    i = fb.log.index(lines[0])
    assert fb.log[i:i + len(lines)] == lines
    assert len(fb.log) - (i + len(lines)) <= 2 and not any(ln.startswith(("seam", "band", "bands stage"))
                                                            for ln in fb.log[i + len(lines):])   # QGIS's own end
    assert any("converged" in ln for ln in lines) and any(ln.startswith("band ccd4_nir vs ccd4_blue") for ln in lines)
    assert any("largest along the overlap" in ln for ln in lines)


def test_blockadjust_refuses_separate_views_and_bad_table_rows(qgis_app, tmp_path):
    from osgeo import gdal
    from qgis.core import QgsProcessingException
    out = tmp_path / "out"
    left, right = str(tmp_path / "left_image.tif"), str(tmp_path / "right_image.tif")
    for path, gt, size in ((left, (5000.0, 1.0, 0.0, 5000.0, 0.0, 1.0), (500, 500)),
                           (right, (4915.0, 1.0, 0.0, 5162.0, 0.0, 1.0), (498, 495))):
        ds = gdal.GetDriverByName("GTiff").Create(path, size[0], size[1], 1, gdal.GDT_Byte)
        ds.SetGeoTransform(gt)
        ds = None
    rpcs = f"{left}={os.path.join(DATA, 'rpc', 'ventoux_left_image.geom')}; " \
           f"{right}={os.path.join(DATA, 'crop_ventoux', 'right_image.geom')}"
    base = {"INPUT": [left, right], "DEM": os.path.join(DATA, "matching", "srtm_ventoux_crop.tif"), "RPCS": rpcs,
            "MATCH_TIES": True, "OUTPUT_FOLDER": str(out)}
    for extra in ({}, {"BANDS_OF": ["right_image", "left_image"]}):
        with pytest.raises(QgsProcessingException, match="separate views") as info:
            _run("gf4cal:blockadjust", dict(base, **extra))
        assert "\n" not in str(info.value).strip() and "gf4cal:bundleadjust" in str(info.value)
        assert not out.exists() or os.listdir(out) == []
    with pytest.raises(QgsProcessingException, match="IMAGE=REFIMAGE") as info:
        _run("gf4cal:blockadjust", dict(base, BANDS_OF=["right_image", "left_image", "left_image"]))
    assert "(BANDS_OF)" in str(info.value)
