"""``gf4cal:bundleadjust`` (METHODS §11, issue 22) in real headless QGIS on the real Pleiades Ventoux stereo crops
(tests/ventouxpair.py): ties matched raw to raw, every output written, the residual layers loaded with their
styles; bad input is one line naming the dialog's parameters, nothing written; cancel leaves nothing."""
import json
import os

import pytest

import ventouxpair as V


def _params(folder, out, **extra):
    left, right = V.pair(folder)
    return {"INPUT": [str(left), str(right)], "MATCH_TIES": True, "DEM": str(V.SRTM), "GEOID": 1,
            "OUTPUT_FOLDER": str(out), **extra}


def test_bundleadjust_matches_adjusts_and_loads_styled_layers(qgis_app, tmp_path):
    import processing
    from qgis.core import QgsProject

    QgsProject.instance().removeAllMapLayers()
    res = processing.runAndLoadResults("gf4cal:bundleadjust", _params(tmp_path / "in", tmp_path / "out"))
    assert sorted(os.path.basename(p) for p in res["OUTPUT_RPCS"]) == ["left.RPB", "right.RPB"]
    assert sorted(os.path.basename(p) for p in res["OUTPUT_VRTS"]) == ["left.vrt", "right.vrt"]
    for key in ("OUTPUT_GPKG", "OUTPUT_PLOT", "OUTPUT_REPORT", "OUTPUT_TIES"):
        assert os.path.getsize(res[key]) > 0, key
    assert res["N_TIES"] >= 150 and 1.4 < res["RMS_BEFORE_PX"] < 2.2 and res["RMS_AFTER_PX"] < 0.09
    with open(res["OUTPUT_REPORT"]) as fh:
        rep = json.load(fh)
    assert rep["relative_to_first_view_px"]["views"]["right"]["sample_std"] > 0
    layers = {lyr.name(): lyr for lyr in QgsProject.instance().mapLayers().values()}
    arrows = [n for n in layers if n.startswith("right_residuals after (x")]
    assert len(arrows) == 1 and layers[arrows[0]].renderer().type() == "graduatedSymbol"
    assert layers["tie_points"].renderer().type() == "RuleRenderer"
    assert {"left ties", "right ties"} <= set(layers)


def test_bundleadjust_bad_input_is_one_line_in_the_dialogs_words(run_alg, tmp_path):
    from qgis.core import QgsProcessingException
    out = tmp_path / "out"
    for extra, match in (({"MATCH_TIES": False}, r"give TIES_FILE \(the observation table\) or MATCH_TIES"),
                         ({"PRIOR_SIGMA": "right=-2"}, r"\(PRIOR_SIGMA\) '-2'"),
                         ({"INPUT": [], "RPC_VIEWS": [str(V.RIGHT_GEOM), str(V.LEFT_GEOM)]},
                          "MATCH_TIES needs every view's pixels"),
                         ({"INPUT": []}, "at least two views; 0 given")):
        with pytest.raises(QgsProcessingException, match=match) as info:
            run_alg("gf4cal:bundleadjust", _params(tmp_path / "in", out, **extra))
        assert "\n" not in str(info.value).strip() and "--" not in str(info.value)
        assert not out.exists() or os.listdir(out) == []


def test_bundleadjust_cancel_leaves_nothing(qgis_app, tmp_path):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingException, QgsProcessingFeedback, QgsProject

    class CancelWhileMatching(QgsProcessingFeedback):
        """The user presses Cancel once the progress passes 10 % (inside the raw-to-raw matching)."""

        def isCanceled(self):
            return self.progress() > 10

    ctx = QgsProcessingContext()
    ctx.setProject(QgsProject.instance())
    out = tmp_path / "out"
    with pytest.raises(QgsProcessingException, match="[Cc]ancel"):
        processing.run("gf4cal:bundleadjust", _params(tmp_path / "in", out), feedback=CancelWhileMatching(),
                       context=ctx)
    assert not out.exists(), sorted(os.listdir(out))
    assert not [n for n in os.listdir(tmp_path / "in") if n.startswith(".")]


def test_bundleadjust_rpc_files_alone_with_a_tie_table(run_alg, tmp_path):
    """Views given as RPC files alone (RPC_VIEWS) with a tie table: a simulated stereo pair (seed 5, 150 ties at
    0.2 px, biases of 5 px); the QGIS outputs are the CLI's."""
    from gdal_gf4cal.cli import main
    from gdal_gf4cal.rpc_io import write_rpb
    from gdal_gf4cal.simulate.views import simulate_views
    sim = simulate_views("stereo", n_ties=150, noise_px=0.2, translation_px=5.0, seed=5)
    paths = []
    for v, m in sim.models.items():
        paths.append(str(tmp_path / f"{v}.RPB"))
        write_rpb(m, paths[-1])
    obs = tmp_path / "ties.csv"
    sim.observations.drop(columns=["true_sample", "true_line"]).to_csv(obs, index=False)
    res, fb = run_alg("gf4cal:bundleadjust", {"INPUT": [], "RPC_VIEWS": paths, "TIES_FILE": str(obs), "MODEL": 0,
                                              "OUTPUT_FOLDER": str(tmp_path / "q")})
    assert sorted(os.path.basename(p) for p in res["OUTPUT_RPCS"]) == ["bwd.RPB", "fwd.RPB"]
    assert res["OUTPUT_VRTS"] == [] and not res["OUTPUT_TIES"] and res["N_TIES"] == 150
    assert res["RMS_AFTER_PX"] < 0.2 and res["RMS_BEFORE_PX"] > 2 * res["RMS_AFTER_PX"]
    assert "bwd: translation correction; relative to fwd" in fb.text()
    assert main(["bundle-adjust", *paths, "--ties", str(obs), "--model", "translation", "--out",
                 str(tmp_path / "c")]) == 0
    for v in ("fwd", "bwd"):
        with open(tmp_path / "q" / f"{v}.RPB") as a, open(tmp_path / "c" / f"{v}.RPB") as b:
            assert a.read() == b.read()
