"""Issue 24, one vocabulary: every algorithm with a DEM offers the same GEOID choice (order, labels, default) whose
words are the CLI's ``--geoid`` words; refine (many scenes) defaults to Automatic as refine does; no help text (QGIS
or CLI) cites a document that is not shipped; metadata.txt names every algorithm."""
from __future__ import annotations

import argparse
import os
import re

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _algorithms(qgis_app):
    from qgis.core import QgsApplication
    return QgsApplication.processingRegistry().providerById("gf4cal").algorithms()


def test_geoid_choice_identical_in_every_algorithm_and_at_the_cli(qgis_app):
    from gdal_gf4cal.cli import ortho as cli_ortho
    from processing_provider.base import GEOID_OPTIONS, GEOID_VALUES
    seen = {}
    for alg in _algorithms(qgis_app):
        p = alg.parameterDefinition("GEOID")
        if p is None:
            continue
        seen[alg.id()] = (p.options(), p.defaultValue(), alg.parameterDefinition("GEOID_GRID") is not None)
    assert {"gf4cal:orthorectify", "gf4cal:refinerpc", "gf4cal:collectgcpsbatch", "gf4cal:rpcinfo",
            "gf4cal:registerpanms"} <= set(seen)
    for alg_id, (options, default, grid) in seen.items():
        assert options == GEOID_OPTIONS and default == 0 and grid, alg_id
    # the CLI's --geoid: the same words in the same order, the same default (auto)
    parser = argparse.ArgumentParser()
    cli_ortho.add_geoid_argument(parser)
    action = next(a for a in parser._actions if a.dest == "geoid")
    assert action.metavar == "|".join(GEOID_VALUES) + "|PATH" and action.default == GEOID_VALUES[0]
    assert [w in o.lower() or (w, o) == ("none", GEOID_OPTIONS[3]) or w == "auto"
            for w, o in zip(GEOID_VALUES, GEOID_OPTIONS)] == [True] * 4


def test_every_cli_command_with_a_dem_has_the_same_geoid_option():
    from gdal_gf4cal.cli import build_parser
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {}
    for name, p in sub.choices.items():
        for a in p._actions:
            if a.dest == "geoid":
                helps[name] = (a.metavar, a.default, a.help)
    assert {"ortho", "refine", "info", "collect-gcps", "block-adjust", "calibrate-lookangle",
            "register-pan-ms"} <= set(helps)
    assert len(set(helps.values())) == 1, helps


def test_refine_many_scenes_defaults_to_automatic_like_refine(qgis_app):
    from qgis.core import QgsApplication
    reg = QgsApplication.processingRegistry()
    one, many = (reg.algorithmById(f"gf4cal:{n}").parameterDefinition("MODEL") for n in ("refinerpc", "refinerpcbatch"))
    assert one.options() == many.options() and one.description() == many.description()
    assert one.defaultValue() == many.defaultValue() and one.options()[one.defaultValue()].startswith("Automatic")


def test_help_texts_cite_no_unshipped_document(qgis_app):
    from gdal_gf4cal.cli import build_parser
    for alg in _algorithms(qgis_app):
        assert "METHODS" not in alg.shortHelpString(), alg.id()
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert "METHODS" not in parser.format_help()
    for name, p in sub.choices.items():
        assert "METHODS" not in p.format_help(), name


def test_metadata_names_every_algorithm(qgis_app):
    with open(os.path.join(ROOT, "metadata.txt"), encoding="utf-8") as f:
        text = f.read()
    description = re.search(r"^description=(.*)$", text, re.M).group(1)
    about = re.search(r"^about=(.*)$", text, re.M).group(1)
    changelog = text[text.index("changelog="):]
    for alg in _algorithms(qgis_app):
        assert alg.id() in changelog, alg.id()
        assert alg.name() in description + about, alg.id()
