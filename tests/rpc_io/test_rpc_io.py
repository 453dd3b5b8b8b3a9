"""RPC file reading and writing (gdal_gf4cal.rpc_io, METHODS §1) on real RPC files.

Equality with GDAL's own readers and with GDAL's RPC transformer: tests/test_rpc_gdal_agreement.py.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal import RPCModel, rpc_io
from gdal_gf4cal.errors import Gf4calError, InputOverwriteError, RPCFormatError

DATA = Path(__file__).parents[1] / "data" / "rpc"

#: Every real RPC file in tests/data/rpc and the format the reader must recognise in it.
FORMATS = {
    "md_dg.RPB": "rpb",
    "test_rpc.txt": "rpc_txt",
    "md_ov_rpc.txt": "rpc_txt",
    "RPC-md_alos.txt": "alos",
    "rpc.vrt": "gdal_xml",
    "rpc_5395.vrt": "gdal_xml",
    "transformer_11_rpc.txt": "rpc_txt",
    "rpc_IKONOS.txt": "rpc_txt",
    "rpc_PLANET_L1A.txt": "rpc_txt",
    "rpc_PLANET_L1B.txt": "rpc_txt",
    "20191015_073816_ssc1d3_0011_basic_l1a_panchromatic_dn_RPC.TXT": "rpc_txt",
    "rpc_PLEIADES.xml": "dimap",
    "rpc_SPOT6.xml": "dimap",
    "rpc_WV2.xml": "isd",
    "rpc_unsupported.xml": "gdal_xml",
    "JAX_068_001_RGB.json": "json",
    "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif": "gdal",
    "RPC_PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.XML": "dimap",
    "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.geom": "geom",
    "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML": "dimap",
    "ventoux_left_image.geom": "geom",
    "RPC_PHR1A_P_202503191043438_SEN_7342362101-1.XML": "dimap",
    "wv3_20.NTF": "gdal",
    "PHRDIMAP_P1BP--2018122638935449CP_excerpt.XML": "dimap",
}


def _tiny_tiff(path: Path, size=(8, 8)) -> Path:
    ds = gdal.GetDriverByName("GTiff").Create(str(path), size[0], size[1], 1, gdal.GDT_Byte)
    ds = None
    return path


def _numbers(value: str) -> list:
    """GDAL's RPC strings as floats: a scalar may carry a unit ('+005124.00 pixels')."""
    tokens = value.split()
    if len(tokens) > 1 and not re.match(r"^[-+.\d]", tokens[1]):
        tokens = tokens[:1]
    return [float(t) for t in tokens]


# ------------------------------------------------------------------------------------------------- reading
@pytest.mark.parametrize("name", sorted(FORMATS))
def test_every_real_rpc_file_parses(name):
    md = rpc_io.read_rpc_metadata(DATA / name)
    assert rpc_io.rpc_file_format(DATA / name) == FORMATS[name]
    assert set(rpc_io.REQUIRED_KEYS) <= set(md)
    for key in rpc_io.SCALAR_KEYS:
        assert np.isfinite(float(md[key]))
    for key in rpc_io.COEFF_KEYS:
        assert len(md[key].split()) == 20
        assert all(np.isfinite(float(t)) for t in md[key].split())
    RPCModel.from_gdal_metadata(md)  # the model accepts the canonical dict as it is


def test_data_folder_is_fully_covered():
    present = {p.name for p in DATA.iterdir() if p.name != "PROVENANCE.txt"}
    assert present == set(FORMATS)


def test_dimap_offsets_are_shifted_to_rpc00b_like_gdal():
    """DIMAP v2 counts the first pixel centre as (1, 1): LINE_OFF/SAMP_OFF lose 1 (GDAL formats them %.15g)."""
    md = rpc_io.read_rpc_metadata(DATA / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    text = (DATA / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML").read_text()
    raw_line = float(re.search(r"<LINE_OFF>([^<]+)</LINE_OFF>", text).group(1))
    raw_samp = float(re.search(r"<SAMP_OFF>([^<]+)</SAMP_OFF>", text).group(1))
    assert raw_line == 21110.49999999999
    assert md["LINE_OFF"] == "%.15g" % (raw_line - 1) == "21109.5"
    assert float(md["SAMP_OFF"]) == raw_samp - 1


def test_dimap_v3_first_col_zero_keeps_offsets(tmp_path):
    """DIMAP v3 may state the first pixel as 0 in ImagetoGround_Validity_Domain/FIRST_COL (GDAL honours it)."""
    text = (DATA / "rpc_PLEIADES.xml").read_text()
    v3 = text.replace("<RFM_Validity>", "<RFM_Validity><ImagetoGround_Validity_Domain><FIRST_ROW>0</FIRST_ROW>"
                      "<FIRST_COL>0</FIRST_COL></ImagetoGround_Validity_Domain>", 1)
    (tmp_path / "RPC_v3.XML").write_text(v3)
    md = rpc_io.read_rpc_metadata(tmp_path / "RPC_v3.XML")
    assert md["LINE_OFF"] == "18088.5" and md["SAMP_OFF"] == "20000.5"


@pytest.mark.parametrize("geom, dimap", [
    ("PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.geom", "RPC_PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.XML"),
    ("ventoux_left_image.geom", "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML"),
])
def test_ossim_geom_equals_dimap_of_the_same_image(geom, dimap):
    """GDAL has no .geom reader: OSSIM's export of the same Pleiades RPC (0-based) is the independent check."""
    a = rpc_io.read_rpc_metadata(DATA / geom)
    b = rpc_io.read_rpc_metadata(DATA / dimap)
    for key in rpc_io.SCALAR_KEYS:
        assert float(a[key]) == pytest.approx(float(b[key]), rel=1e-13, abs=1e-9), key
    for key in rpc_io.COEFF_KEYS:
        np.testing.assert_allclose(np.array(a[key].split(), float), np.array(b[key].split(), float),
                                   rtol=1e-13, atol=1e-20, err_msg=key)


def test_ossim_geom_polynomial_format_a_is_reordered(tmp_path):
    text = (DATA / "ventoux_left_image.geom").read_text()
    b_to_a = {7: 8, 8: 9, 9: 10, 10: 7}  # RPC00B term index -> RPC00A index (L², P², H², PLH)

    def rename(m):
        j = int(m.group(2))
        return f"{m.group(1)}_{b_to_a.get(j, j):02d}:"
    a_text = re.sub(r"((?:line|samp)_(?:num|den)_coeff)_(\d\d):", rename, text)
    a_text = a_text.replace("polynomial_format:  B", "polynomial_format:  A")
    assert a_text != text and "polynomial_format:  A" in a_text
    (tmp_path / "a.geom").write_text(a_text)
    assert rpc_io.read_rpc_metadata(tmp_path / "a.geom") == rpc_io.read_rpc_metadata(DATA / "ventoux_left_image.geom")


def test_sat_nerf_json_maps_rows_to_lines():
    """The footprint stored in the JSON projects (at ALT_OFF) onto the 746 x 815 image corners: rows are lines."""
    data = json.loads((DATA / "JAX_068_001_RGB.json").read_text())
    md = rpc_io.read_rpc_metadata(DATA / "JAX_068_001_RGB.json")
    assert float(md["LINE_OFF"]) == data["rpc"]["row_offset"]
    assert float(md["SAMP_SCALE"]) == data["rpc"]["col_scale"]
    assert [float(t) for t in md["SAMP_DEN_COEFF"].split()] == data["rpc"]["col_den"]
    assert float(md["MIN_HEIGHT"]) == data["min_alt"] and float(md["MAX_HEIGHT"]) == data["max_alt"]
    rpc = RPCModel.from_gdal_metadata(md)
    corners = np.array(data["geojson"]["coordinates"][0])
    s, l = rpc.project(corners[:, 0], corners[:, 1], data["rpc"]["alt_offset"])
    w, h = data["width"], data["height"]
    np.testing.assert_allclose(np.c_[s, l], [[0, 0], [w, 0], [w, h], [0, h]], atol=2.0)


@pytest.mark.parametrize("name, new_name", [
    ("md_dg.RPB", "scene.txt"), ("test_rpc.txt", "scene.rpc"), ("rpc_WV2.xml", "scene.rpb"),
    ("rpc_PLEIADES.xml", "scene.txt"), ("JAX_068_001_RGB.json", "scene.rpc"), ("ventoux_left_image.geom", "x.xml"),
    ("RPC-md_alos.txt", "scene.RPB"), ("wv3_20.NTF", "scene.rpc"),
])
def test_format_detected_by_content_not_name(name, new_name, tmp_path):
    shutil.copy(DATA / name, tmp_path / new_name)
    assert rpc_io.read_rpc_metadata(tmp_path / new_name) == rpc_io.read_rpc_metadata(DATA / name)


def test_json_with_gdal_keys_flat_nested_and_numeric(tmp_path):
    md = rpc_io.read_rpc_metadata(DATA / "md_dg.RPB")
    (tmp_path / "flat.json").write_text(json.dumps(md))
    (tmp_path / "nested.json").write_text(json.dumps({"image": "x.tif", "rpc": md}))
    numeric = {k: ([float(t) for t in v.split()] if k in rpc_io.COEFF_KEYS else float(v)) for k, v in md.items()}
    (tmp_path / "numeric.json").write_text(json.dumps({k.lower(): v for k, v in numeric.items()}))
    for name in ("flat.json", "nested.json"):
        assert rpc_io.read_rpc_metadata(tmp_path / name) == md
    got = rpc_io.read_rpc_metadata(tmp_path / "numeric.json")
    assert {k: [float(t) for t in v.split()] for k, v in got.items()} == \
        {k: [float(t) for t in v.split()] for k, v in md.items()}


def test_gdal_pam_aux_xml_is_read_like_gdal(tmp_path):
    """A PAM .aux.xml with an RPC domain (what rpcm refuses): we read it, and so does GDAL next to an image."""
    vrt = (DATA / "rpc_unsupported.xml").read_text()
    block = vrt[vrt.index("<Metadata"):vrt.index("</Metadata>") + len("</Metadata>")]
    (tmp_path / "img.tif.aux.xml").write_text(f"<PAMDataset>\n  {block}\n</PAMDataset>\n")
    ours = rpc_io.read_rpc_metadata(tmp_path / "img.tif.aux.xml")
    assert ours == rpc_io.read_rpc_metadata(DATA / "rpc_unsupported.xml")
    theirs = gdal.Open(str(_tiny_tiff(tmp_path / "img.tif"))).GetMetadata("RPC")
    assert {k: _numbers(v) for k, v in theirs.items()} == {k: _numbers(v) for k, v in ours.items()}


def test_image_with_sidecar_is_read_through_gdal(tmp_path):
    shutil.copy(DATA / "md_dg.RPB", tmp_path / "scene.RPB")
    _tiny_tiff(tmp_path / "scene.tif")
    assert rpc_io.rpc_file_format(tmp_path / "scene.tif") == "gdal"
    assert rpc_io.read_rpc_metadata(tmp_path / "scene.tif") == rpc_io.read_rpc_metadata(DATA / "md_dg.RPB")


def test_normalize_strips_units_and_validates():
    md = rpc_io.read_rpc_metadata(DATA / "test_rpc.txt")
    assert md["LINE_OFF"] == "+015834.00" and md["ERR_BIAS"] == "0000.31"
    bad = dict(md, LINE_OFF="12 34")
    with pytest.raises(RPCFormatError, match="LINE_OFF"):
        rpc_io.normalize_rpc_metadata(bad, "x")
    garbage_optional = dict(md, ERR_BIAS="n/a")
    assert "ERR_BIAS" not in rpc_io.normalize_rpc_metadata(garbage_optional, "x")


# ---------------------------------------------------------------------------------------------- bad input
def _edit(src: str, dst: Path, old: str, new: str, count: int = 1) -> Path:
    text = (DATA / src).read_text()
    assert old in text, old
    dst.write_text(text.replace(old, new, count))
    return dst


def _lines_without(src: str, dst: Path, pattern: str) -> Path:
    lines = (DATA / src).read_text().splitlines(keepends=True)
    kept = [ln for ln in lines if not re.search(pattern, ln)]
    assert len(kept) == len(lines) - 1, pattern
    dst.write_text("".join(kept))
    return dst


@pytest.mark.parametrize("make, key", [
    (lambda d: _lines_without("test_rpc.txt", d / "a_rpc.txt", r"^LINE_OFF:"), "LINE_OFF"),
    (lambda d: _lines_without("test_rpc.txt", d / "b_rpc.txt", r"^SAMP_DEN_COEFF_7:"), "SAMP_DEN_COEFF_7"),
    (lambda d: _edit("test_rpc.txt", d / "c_rpc.txt", "LAT_SCALE: +00.07150000", "LAT_SCALE: +00.00000"),
     "LAT_SCALE"),
    (lambda d: _edit("test_rpc.txt", d / "d_rpc.txt", "HEIGHT_OFF: +0300.000", "HEIGHT_OFF: three"), "HEIGHT_OFF"),
    (lambda d: _lines_without("md_dg.RPB", d / "e.RPB", r"-1\.617343E-04"), "LINE_NUM_COEFF"),  # 19 coefficients
    (lambda d: _lines_without("md_dg.RPB", d / "f.RPB", r"heightScale"), "heightScale"),
    (lambda d: _edit("md_dg.RPB", d / "g.RPB", "+1.340215E-04", "+1.34O215E-04"), "SAMP_DEN_COEFF"),
    (lambda d: _lines_without("rpc_PLEIADES.xml", d / "h.xml", r"<LINE_NUM_COEFF_20>1\.2054"),  # Inverse_Model's
     "Inverse_Model/LINE_NUM_COEFF_20"),
    (lambda d: _lines_without("rpc_PLEIADES.xml", d / "i.xml", r"<SAMP_OFF>"), "SAMP_OFF"),
    (lambda d: _edit("rpc_WV2.xml", d / "j.xml", "<LONGSCALE>6.360000000000000e-02</LONGSCALE>", ""),
     "LONGSCALE"),
    (lambda d: _edit("rpc_WV2.xml", d / "k.xml", "<HEIGHTSCALE>501</HEIGHTSCALE>", "<HEIGHTSCALE>0</HEIGHTSCALE>"),
     "HEIGHT_SCALE"),
    (lambda d: _lines_without("rpc_unsupported.xml", d / "l.xml", r'key="LONG_OFF"'), "LONG_OFF"),
    (lambda d: _lines_without("JAX_068_001_RGB.json", d / "m.json", r'"lat_scale"'), "lat_scale"),
    (lambda d: _lines_without("ventoux_left_image.geom", d / "n.geom", r"^samp_num_coeff_13:"),
     "samp_num_coeff_13"),
    (lambda d: _edit("transformer_11_rpc.txt", d / "o.txt", "LINE_DEN_COEFF=1 ", "LINE_DEN_COEFF="),
     "LINE_DEN_COEFF"),
])
def test_bad_rpc_names_file_and_key(make, key, tmp_path):
    path = make(tmp_path)
    with pytest.raises(RPCFormatError) as err:
        rpc_io.read_rpc_metadata(path)
    message = str(err.value)
    assert "\n" not in message
    assert str(path) in message and key in message, message


def test_nineteen_coefficients_are_counted(tmp_path):
    path = _lines_without("md_dg.RPB", tmp_path / "x.RPB", r"-1\.617343E-04")
    with pytest.raises(RPCFormatError, match=r"LINE_NUM_COEFF has 19 coefficients instead of 20"):
        rpc_io.read_rpc_metadata(path)


def test_unsupported_and_non_rpc_inputs(tmp_path):
    text = (DATA / "rpc_PLEIADES.xml").read_text()
    head = text[:text.index("?>") + 2]  # the XML declaration only
    (tmp_path / "PHRDIMAP.XML").write_text(
        head + "<PHR_Dimap_Document><Geoposition><Rational_Sensor_Model><Global_RFM><Inverse_Model>"
        "<F_COL>0 1</F_COL><F_ROW>0 1</F_ROW></Inverse_Model></Global_RFM></Rational_Sensor_Model>"
        "</Geoposition></PHR_Dimap_Document>")
    (tmp_path / "empty.txt").write_text("")
    (tmp_path / "bands.xml").write_text("<level_X><RPC>" + "".join(
        f'<bandID number="{b}"><ROW_OFF>512</ROW_OFF><ROW_NUM_01>0.1</ROW_NUM_01></bandID>' for b in (1, 2))
        + "</RPC></level_X>")
    (tmp_path / "broken.xml").write_text("<isd><RPB>")
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "noise.bin").write_bytes(bytes(range(256)) * 4)
    ds = gdal.GetDriverByName("GTiff").Create(str(tmp_path / "plain.tif"), 4, 4)
    ds = None
    cases = {
        "PHRDIMAP.XML": "DIMAP v1", "empty.txt": "no RPC found", "bands.xml": "one RPC per band (2 bands", "broken.xml": "not well-formed XML",
        "list.json": "JSON", "noise.bin": "GDAL", "plain.tif": "no RPC metadata", "missing.RPB": "no such file",
    }
    for name, words in cases.items():
        with pytest.raises(RPCFormatError) as err:
            rpc_io.read_rpc_metadata(tmp_path / name)
        assert words in str(err.value) and str(tmp_path / name) in str(err.value), str(err.value)
    with pytest.raises(RPCFormatError):  # also through the model, and catchable as ValueError
        RPCModel.from_file(tmp_path / "plain.tif")
    with pytest.raises(ValueError):
        rpc_io.read_rpc_metadata(tmp_path / "empty.txt")


def test_pleiades_dimap_v1_inverse_model_inverts_its_direct_model():
    """Pleiades DIMAP v1.4 (PHR_Dimap_Document): the RPC read from the inverse model F_COL/F_ROW takes every ground
    point of the product's own direct model F_LON/F_LAT (an independent fit, DIMAP pixel centres at 1) back to the
    pixel it came from, GDAL convention = DIMAP - 0.5 (Shareloc's test_rpc_phrdimap: within 2e-2 px)."""
    from xml.etree import ElementTree as ET
    from gdal_gf4cal.rpc import monomials
    path = DATA / "PHRDIMAP_P1BP--2018122638935449CP_excerpt.XML"
    rpc = RPCModel.from_file(path)
    root = ET.parse(path).getroot()
    coeff = {n: np.array(root.find(f".//Direct_Model/{n}").text.split(), float) for n in ("F_LON", "F_LAT")}
    ab = {n: [float(root.find(f".//RFM_Validity/{n}/{k}").text) for k in "AB"] for n in ("Lon", "Lat", "Alt", "Col", "Row")}
    col, row, h = (a.ravel() for a in np.meshgrid(np.linspace(1, 40000, 9), np.linspace(1, 38248, 9), [490.0, 660.0]))
    x, y, z = ((v - ab[n][1]) / ab[n][0] for v, n in ((col, "Col"), (row, "Row"), (h, "Alt")))
    m = monomials(x, y, z).T            # direct model: L <- normalised column, P <- normalised row
    lon, lat = ((m @ c[:20]) / (m @ c[20:]) * ab[n][0] + ab[n][1] for c, n in ((coeff["F_LON"], "Lon"),
                                                                             (coeff["F_LAT"], "Lat")))
    s, l = rpc.project(lon, lat, h)
    assert np.max(np.abs(s - (col - 0.5))) < 2e-2 and np.max(np.abs(l - (row - 0.5))) < 2e-2
    assert (rpc.min_long, rpc.max_lat) == (2.111390777763922, 31.11614087798913)


# ------------------------------------------------------------------------------------------------- writing
ROUND_TRIP = ["md_dg.RPB", "test_rpc.txt", "transformer_11_rpc.txt",
              "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML", "JAX_068_001_RGB.json", "rpc_5395.vrt"]


def _gdal_sidecar_read_back(folder: Path, writer, rpc) -> dict:
    """Write ``rpc`` as the sidecar of a fresh GeoTIFF (named so GDAL finds it) and return GDAL's reading."""
    image = _tiny_tiff(folder / "scene.tif")
    sidecar = rpc_io.rpb_path_for(image) if writer is rpc_io.write_rpb else rpc_io.rpc_txt_path_for(image)
    writer(rpc, sidecar)
    ds = gdal.Open(str(image))
    files = ds.GetFileList()
    md = dict(ds.GetMetadata("RPC"))
    ds = None
    assert str(sidecar) in files, "GDAL did not pick the sidecar up"
    return md


@pytest.mark.parametrize("name", ROUND_TRIP)
@pytest.mark.parametrize("writer", [rpc_io.write_rpb, rpc_io.write_rpc_txt], ids=["rpb", "rpc_txt"])
def test_written_sidecars_read_back_identically_by_gdal(name, writer, tmp_path):
    source = rpc_io.read_rpc_metadata(DATA / name)
    back = _gdal_sidecar_read_back(tmp_path, writer, source)
    for key in rpc_io.REQUIRED_KEYS:
        ours = np.array(source[key].split(), float)
        theirs = np.array(_numbers(back[key]))
        assert np.array_equal(ours, theirs), key  # bit-identical doubles (so also within 1e-15 relative)
    assert rpc_io.read_rpc_metadata(next(p for p in tmp_path.iterdir() if p.suffix.upper() in (".RPB", ".TXT"))) \
        .keys() >= set(rpc_io.REQUIRED_KEYS)


@pytest.mark.parametrize("method", ["write_rpb", "write_rpc_txt"])
def test_rpcmodel_writes_bit_identical_values(method, tmp_path):
    """A model with full-precision coefficients (not the file's 7 digits): GDAL reads back the same doubles."""
    rng = np.random.default_rng(20240601)
    base = RPCModel.from_file(DATA / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    rpc = base.replace(line_num=base.line_num * (1 + 1e-9 * rng.standard_normal(20)),
                       samp_off=base.samp_off + float(rng.uniform()) / 3, lat_off=base.lat_off + 1e-7 / 3)
    image = _tiny_tiff(tmp_path / "scene.tif")
    sidecar = rpc_io.rpb_path_for(image) if method == "write_rpb" else rpc_io.rpc_txt_path_for(image)
    getattr(rpc, method)(sidecar)
    back = RPCModel.from_gdal_metadata(gdal.Open(str(image)).GetMetadata("RPC"))
    for field in ("line_off", "samp_off", "lat_off", "long_off", "height_off", "line_scale", "samp_scale",
                  "lat_scale", "long_scale", "height_scale"):
        assert getattr(back, field) == getattr(rpc, field), field
    for field in ("line_num", "line_den", "samp_num", "samp_den"):
        assert np.array_equal(getattr(back, field), getattr(rpc, field)), field


def test_writers_refuse_to_overwrite_and_leave_no_temporary_files(tmp_path):
    md = rpc_io.read_rpc_metadata(DATA / "md_dg.RPB")
    out = tmp_path / "new.RPB"
    rpc_io.write_rpb(md, out)
    first = out.read_bytes()
    with pytest.raises(InputOverwriteError, match="exists"):
        rpc_io.write_rpb(md, out)
    with pytest.raises(FileExistsError):  # InputOverwriteError is also a FileExistsError
        rpc_io.write_rpc_txt(md, out)
    assert out.read_bytes() == first
    other = dict(md, LINE_OFF="813")
    rpc_io.write_rpb(other, out, overwrite=True)
    assert rpc_io.read_rpc_metadata(out)["LINE_OFF"] == "813.0"
    rpc_io.write_rpb(md, out, overwrite=True)  # our own output, re-read to check it, stays replaceable...
    with pytest.raises(InputOverwriteError, match="input"):  # ...but not by the model that came from it
        RPCModel.from_file(out).write_rpb(out, overwrite=True)
    assert rpc_io.read_rpc_metadata(out)["LINE_OFF"] == "812.0"
    with pytest.raises(RPCFormatError, match="LINE_NUM_COEFF"):
        rpc_io.write_rpc_txt(dict(md, LINE_NUM_COEFF="1 2 3"), tmp_path / "bad_RPC.TXT")
    assert not (tmp_path / "bad_RPC.TXT").exists()
    with pytest.raises(Gf4calError, match="does not exist"):
        rpc_io.write_rpb(md, tmp_path / "no" / "such" / "x.RPB")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.RPB"]


def test_writers_never_replace_the_file_an_rpc_came_from(tmp_path):
    src = tmp_path / "scene_RPC.TXT"
    shutil.copy(DATA / "test_rpc.txt", src)
    before = src.read_bytes()
    md = rpc_io.read_rpc_metadata(src)
    model = RPCModel.from_file(src)
    for rpc in (md, model):
        with pytest.raises(InputOverwriteError, match="input"):
            rpc_io.write_rpc_txt(rpc, src, overwrite=True)
    with pytest.raises(InputOverwriteError, match="input"):
        model.write_rpb(src, overwrite=True)
    assert src.read_bytes() == before


def test_rpb_and_rpc_txt_text_layout():
    md = rpc_io.read_rpc_metadata(DATA / "rpc_PLANET_L1A.txt")  # no ERR_BIAS/ERR_RAND
    rpb = rpc_io.format_rpb(md)
    assert rpb.startswith('satId = "UNKNOWN";\nbandId = "P";\nSpecId = "RPC00B";\nBEGIN_GROUP = IMAGE\n')
    assert "\terrBias = 0.0;\n" in rpb and rpb.endswith("END_GROUP = IMAGE\nEND;\n")
    txt = rpc_io.format_rpc_txt(md)
    assert txt.startswith("LINE_OFF: 540.400296515938\n") and "ERR_BIAS" not in txt
    assert len(re.findall(r"^SAMP_DEN_COEFF_\d+: ", txt, re.M)) == 20


# ---------------------------------------------------------------------------------------------------- VRT
def _md5(path: Path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


def test_write_rpc_vrt_carries_the_new_rpc(tmp_path):
    image = tmp_path / "scene.tif"
    shutil.copy(DATA / "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif", image)
    checksum = _md5(image)
    old = RPCModel.from_file(image)
    new = old.replace(line_off=old.line_off + 10.25, samp_off=old.samp_off - 3.5)
    vrt = tmp_path / "scene_new.vrt"
    assert Path(rpc_io.write_rpc_vrt(image, new, vrt)) == vrt

    assert _md5(image) == checksum
    text = vrt.read_text()
    assert 'relativeToVRT="1">scene.tif<' in text
    ds = gdal.Open(str(vrt))
    assert ds.RasterXSize == 128 and ds.GetRasterBand(1).Checksum() == gdal.Open(str(image)).GetRasterBand(1).Checksum()
    assert RPCModel.from_gdal_metadata(ds.GetMetadata("RPC")).line_off == new.line_off

    lon, lat, h = 7.048662660737769592, 43.72774839443545858, 100.0
    t_new = gdal.Transformer(ds, None, ["METHOD=RPC"])
    t_old = gdal.Transformer(gdal.Open(str(image)), None, ["METHOD=RPC"])
    (s_new, l_new, _), = t_new.TransformPoints(1, [(lon, lat, h)])[0]
    (s_old, l_old, _), = t_old.TransformPoints(1, [(lon, lat, h)])[0]
    assert (s_new - s_old, l_new - l_old) == pytest.approx((-3.5, 10.25), abs=1e-9)
    assert (s_new, l_new) == pytest.approx(new.project(lon, lat, h), abs=1e-6)
    ds = None

    with pytest.raises(InputOverwriteError, match="exists"):
        rpc_io.write_rpc_vrt(image, new, vrt)
    rpc_io.write_rpc_vrt(image, old, vrt, overwrite=True)
    assert RPCModel.from_file(vrt).line_off == old.line_off
    with pytest.raises(InputOverwriteError, match="input"):
        rpc_io.write_rpc_vrt(image, new, image, overwrite=True)
    assert _md5(image) == checksum
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.tif", "scene_new.vrt"]


def test_gdalwarp_rpc_uses_the_vrt_rpc_and_paths_survive_a_change_of_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "img").mkdir()
    (tmp_path / "out").mkdir()
    shutil.copy(DATA / "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif", "img/scene.tif")
    old = RPCModel.from_file("img/scene.tif")
    new = old.replace(line_off=old.line_off + 40.0, long_off=old.long_off + 2e-4)
    rpc_io.write_rpc_vrt("img/scene.tif", new, "out/scene.vrt")  # relative paths, other folder
    # reference: a copy of the image whose RPC tags are replaced by the new model
    ref = gdal.Translate(str(tmp_path / "ref.tif"), str(tmp_path / "img/scene.tif"))
    ref.SetMetadata(new.to_gdal_metadata(), "RPC")
    ref = None
    monkeypatch.chdir(tmp_path / "img")
    opts = dict(format="MEM", rpc=True, dstSRS="EPSG:4326", xRes=5e-6, yRes=5e-6)
    via_vrt = gdal.Warp("", str(tmp_path / "out/scene.vrt"), **opts)
    via_ref = gdal.Warp("", str(tmp_path / "ref.tif"), **opts)
    via_old = gdal.Warp("", "scene.tif", **opts)
    assert via_vrt.GetGeoTransform() == via_ref.GetGeoTransform() != via_old.GetGeoTransform()
    assert via_vrt.GetRasterBand(1).Checksum() == via_ref.GetRasterBand(1).Checksum()


def test_write_rpc_vrt_over_an_image_with_sidecar_drops_the_old_rpc(tmp_path):
    image = _tiny_tiff(tmp_path / "scene.tif", size=(16, 12))
    shutil.copy(DATA / "md_dg.RPB", tmp_path / "scene.RPB")
    new = rpc_io.read_rpc_metadata(DATA / "rpc_PLANET_L1A.txt")
    vrt = rpc_io.write_rpc_vrt(image, new, tmp_path / "out.vrt")
    got = gdal.Open(str(vrt)).GetMetadata("RPC")
    assert "ERR_BIAS" not in got  # the RPB's ERR_BIAS is not carried over: the whole domain is replaced
    assert float(got["LAT_SCALE"]) == float(new["LAT_SCALE"]) == -0.0234
    with pytest.raises(InputOverwriteError):
        rpc_io.write_rpc_vrt(image, new, tmp_path / "scene.RPB", overwrite=True)
    with pytest.raises(Gf4calError, match="cannot open"):
        rpc_io.write_rpc_vrt(tmp_path / "none.tif", new, tmp_path / "x.vrt")


def test_toplevel_exports():
    import gdal_gf4cal
    assert gdal_gf4cal.write_rpc_vrt is rpc_io.write_rpc_vrt
    assert os.fspath(rpc_io.rpc_txt_path_for("/a/b/scene.tif")) == "/a/b/scene_RPC.TXT"
    assert os.fspath(rpc_io.rpb_path_for("/a/b/scene.tif")) == "/a/b/scene.RPB"
