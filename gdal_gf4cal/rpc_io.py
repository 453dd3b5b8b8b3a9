"""RPC file reading and writing (METHODS §1).

Every reader returns one canonical dictionary: GDAL's ``RPC`` metadata-domain keys with string values, exactly
what ``gdal.Open(image).GetMetadata('RPC')`` gives for the same RPC (units such as ``pixels`` stripped,
coefficient lists as 20 space-separated numbers)::

    LINE_OFF, SAMP_OFF, LAT_OFF, LONG_OFF, HEIGHT_OFF,
    LINE_SCALE, SAMP_SCALE, LAT_SCALE, LONG_SCALE, HEIGHT_SCALE,
    LINE_NUM_COEFF, LINE_DEN_COEFF, SAMP_NUM_COEFF, SAMP_DEN_COEFF   (required)
    ERR_BIAS, ERR_RAND, MIN_LONG, MIN_LAT, MAX_LONG, MAX_LAT, MIN_HEIGHT, MAX_HEIGHT  (optional)

Offsets are in GDAL's RPC convention (RPC00B: the centre of the first pixel is at 0, 0); the GDAL pixel
convention used by :meth:`gdal_gf4cal.RPCModel.project` is this plus 0.5 (METHODS §0).

Formats are recognised by content, not by name (vendors use ``.rpc``, ``.rpb``, ``.txt``, ``.xml`` loosely):

=============  ==========================================================================================
``gdal``       any raster GDAL opens with RPC metadata: GeoTIFF tags, ``.RPB``/``_RPC.TXT``/vendor XML
               sidecars found by GDAL next to the image, NITF RPC00B
``rpb``        DigitalGlobe/Maxar ``.RPB`` keyword file (``BEGIN_GROUP = IMAGE`` ... ``lineNumCoef = (...)``)
``rpc_txt``    GeoEye/IKONOS/Planet ``_RPC.TXT`` (``LINE_OFF: 1234 pixels``, ``LINE_NUM_COEFF_1: ...``) and
               flat ``KEY=value`` lists (``gdalinfo`` output, GDAL key dumps)
``dimap``      Pleiades/SPOT DIMAP v2 (and v3) ``RPC_*.XML``: the inverse model; offsets shifted from the
               DIMAP first-pixel convention (1, 1, or ``FIRST_COL`` of DIMAP v3) to RPC00B as GDAL does; and
               Pleiades DIMAP v1 (``PHR_Dimap_Document`` profile 1.4, ``Global_RFM`` with ``F_COL``/``F_ROW``),
               read as CNES Shareloc reads it
``isd``        DigitalGlobe/Maxar ISD XML (``<isd><RPB><IMAGE>`` ... ``<LINENUMCOEFList>``)
``gdal_xml``   GDAL VRT or PAM ``.aux.xml`` with a ``<Metadata domain="RPC">`` block
``json``       a JSON dict: DFC2019 / Sat-NeRF / rpcm style (``"rpc": {"row_offset": ...}``) or GDAL keys
``geom``       OSSIM keyword list ``.geom`` (``ossimRpcModel``/``ossimPleiadesModel``, polynomial format A or B)
``alos``       ALOS PRISM/AVNIR-2 fixed-width ``RPC-*.txt`` record
=============  ==========================================================================================

Writers produce ``.RPB`` and ``_RPC.TXT`` sidecars that GDAL reads back to identical doubles (shortest
round-trip ``repr``), and a VRT over an untouched image carrying a new RPC. They write atomically (temporary file
in the same folder, then an atomic rename), refuse to replace an existing file unless ``overwrite=True`` and
never replace a file an RPC was read from in this process (:class:`InputOverwriteError`).
"""
from __future__ import annotations

import json
import math
import os
import re
import uuid
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any, Dict, Iterable, List, Mapping, Optional, Tuple, Union

from .errors import Gf4calError, InputOverwriteError, RPCFormatError

PathLike = Union[str, "os.PathLike[str]"]

#: Required scalar keys, in GDAL's order.
SCALAR_KEYS: Tuple[str, ...] = (
    "LINE_OFF", "SAMP_OFF", "LAT_OFF", "LONG_OFF", "HEIGHT_OFF",
    "LINE_SCALE", "SAMP_SCALE", "LAT_SCALE", "LONG_SCALE", "HEIGHT_SCALE",
)
#: Required 20-coefficient keys.
COEFF_KEYS: Tuple[str, ...] = ("LINE_NUM_COEFF", "LINE_DEN_COEFF", "SAMP_NUM_COEFF", "SAMP_DEN_COEFF")
#: Optional numeric keys kept when present and valid (the MIN/MAX_HEIGHT pair is not GDAL's; GDAL ignores it).
OPTIONAL_KEYS: Tuple[str, ...] = (
    "ERR_BIAS", "ERR_RAND", "MIN_LONG", "MIN_LAT", "MAX_LONG", "MAX_LAT", "MIN_HEIGHT", "MAX_HEIGHT",
)
REQUIRED_KEYS: Tuple[str, ...] = SCALAR_KEYS + COEFF_KEYS
_SCALE_KEYS = ("LINE_SCALE", "SAMP_SCALE", "LAT_SCALE", "LONG_SCALE", "HEIGHT_SCALE")
_N_COEFF = 20

# Files RPCs were read from in this process (resolved paths): writers never replace them, except files this
# module wrote itself (re-reading an output to check it must not lock it against a later overwrite=True).
_INPUT_FILES: set = set()
_OUTPUT_FILES: set = set()


# ----------------------------------------------------------------------------------------------------------------
# Validation / canonical form
# ----------------------------------------------------------------------------------------------------------------
def _number(token: str) -> Optional[float]:
    """float(token) if it is a finite number, else None (no Fortran 'D' exponents: GDAL would misread them)."""
    try:
        value = float(token)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


_UNIT_RE = re.compile(r"^[A-Za-z_()\[\]/%°]+$")


def _scalar_token(value: Any, key: str, source: Any) -> str:
    """The number in a scalar value: ``'+005124.00 pixels'`` -> ``'+005124.00'`` (a trailing unit is allowed)."""
    if isinstance(value, bool):
        raise RPCFormatError(f"{source}: RPC key {key} is not a number ({value!r})")
    if isinstance(value, (int, float)):
        if isinstance(value, int) and abs(value) > 10 ** 300:   # float() would overflow: a 400-digit integer
            raise RPCFormatError(f"{source}: RPC key {key} is not a finite number (an integer of "
                                 f"{len(str(abs(value)))} digits)")
        if not math.isfinite(float(value)):
            raise RPCFormatError(f"{source}: RPC key {key} is not a finite number ({value!r})")
        return repr(float(value)) if isinstance(value, float) else str(value)
    if isinstance(value, (list, tuple)):
        if len(value) != 1:
            raise RPCFormatError(f"{source}: RPC key {key} should be one number, got {len(value)}")
        return _scalar_token(value[0], key, source)
    tokens = str(value).split()
    if not tokens:
        raise RPCFormatError(f"{source}: RPC key {key} is empty")
    if _number(tokens[0]) is None:
        raise RPCFormatError(f"{source}: RPC key {key} is not a number ({str(value).strip()!r})")
    if any(not _UNIT_RE.match(t) for t in tokens[1:]):
        raise RPCFormatError(
            f"{source}: RPC key {key} should be one number, got {str(value).strip()!r}")
    return tokens[0]


def _coeff_tokens(value: Any, key: str, source: Any) -> List[str]:
    """The 20 coefficients of a list value (string separated by blanks/commas/parentheses, or a sequence)."""
    if isinstance(value, str):
        tokens = [t for t in re.split(r"[\s,()]+", value) if t]
    elif isinstance(value, (list, tuple)):
        tokens = []
        for item in value:
            if isinstance(item, bool):
                raise RPCFormatError(f"{source}: RPC key {key} holds a non-number ({item!r})")
            if isinstance(item, int) and abs(item) > 10 ** 300:
                raise RPCFormatError(f"{source}: RPC key {key} holds a non-finite number (an integer of "
                                     f"{len(str(abs(item)))} digits)")
            tokens.append(repr(float(item)) if isinstance(item, float) else str(item).strip())
    else:
        try:  # numpy arrays and other sequences
            return _coeff_tokens([x.item() if hasattr(x, "item") else x for x in value], key, source)
        except TypeError:
            raise RPCFormatError(f"{source}: RPC key {key} should list 20 numbers") from None
    if len(tokens) != _N_COEFF:
        raise RPCFormatError(
            f"{source}: RPC key {key} has {len(tokens)} coefficients instead of {_N_COEFF}")
    for i, tok in enumerate(tokens):
        if _number(tok) is None:
            raise RPCFormatError(
                f"{source}: RPC key {key} coefficient {i + 1} is not a number ({tok!r})")
    return tokens


def normalize_rpc_metadata(md: Mapping[str, Any], source: Any = "RPC metadata") -> Dict[str, str]:
    """Validate a GDAL ``RPC``-domain mapping and return its canonical form.

    Parameters
    ----------
    md : mapping
        GDAL RPC keys (case-insensitive) to values: strings as GDAL gives them (a trailing unit such as
        ``pixels`` is allowed), numbers, or sequences of 20 numbers for the ``*_COEFF`` keys.
    source : str or path
        What to name in error messages (usually the file).

    Returns
    -------
    dict of str to str
        The 14 required keys and the valid optional ones (:data:`OPTIONAL_KEYS`); scalars as the number token
        of the input, coefficient lists as 20 numbers separated by single spaces. Unknown keys are dropped.

    Raises
    ------
    RPCFormatError
        A missing key, a non-number, not exactly 20 coefficients, or a zero scale; the message names
        ``source`` and the key.
    """
    if not isinstance(md, Mapping):
        raise RPCFormatError(f"{source}: RPC metadata should be a mapping of GDAL RPC keys")
    upper: Dict[str, Any] = {}
    for k, v in md.items():
        upper.setdefault(str(k).strip().upper(), v)
    out: Dict[str, str] = {}
    for key in SCALAR_KEYS:
        if key not in upper or upper[key] is None:
            raise RPCFormatError(f"{source}: missing RPC key {key}")
        out[key] = _scalar_token(upper[key], key, source)
    for key in COEFF_KEYS:
        if key not in upper or upper[key] is None:
            raise RPCFormatError(f"{source}: missing RPC key {key}")
        out[key] = " ".join(_coeff_tokens(upper[key], key, source))
    for key in _SCALE_KEYS:
        if float(out[key]) == 0.0:
            raise RPCFormatError(f"{source}: RPC key {key} is zero (a scale must not be 0)")
    for key in OPTIONAL_KEYS:
        if key in upper and upper[key] is not None:
            try:
                out[key] = _scalar_token(upper[key], key, source)
            except RPCFormatError:
                pass  # optional accuracy/validity fields: GDAL ignores unreadable ones too
    return out


# ----------------------------------------------------------------------------------------------------------------
# File access helpers
# ----------------------------------------------------------------------------------------------------------------
def _is_vsi(path: str) -> bool:
    return path.startswith("/vsi")


def _read_bytes(path: str, limit: Optional[int] = None) -> bytes:
    if _is_vsi(path):
        from osgeo import gdal
        fp = gdal.VSIFOpenL(path, "rb")
        if fp is None:
            raise RPCFormatError(f"{path}: cannot open the file")
        try:
            if limit is None:
                gdal.VSIFSeekL(fp, 0, 2)
                limit = gdal.VSIFTellL(fp)
                gdal.VSIFSeekL(fp, 0, 0)
            return bytes(gdal.VSIFReadL(1, limit, fp) or b"")
        finally:
            gdal.VSIFCloseL(fp)
    with open(path, "rb") as f:
        return f.read() if limit is None else f.read(limit)


def _register_input(paths: Iterable[str]) -> None:
    for p in paths:
        if p and not _is_vsi(str(p)):
            _INPUT_FILES.add(os.path.realpath(str(p)))


def _gdal_open(path: str):
    """gdal.OpenEx as a raster (None if GDAL cannot), quiet, whatever the caller's exception mode."""
    from osgeo import gdal
    gdal.PushErrorHandler("CPLQuietErrorHandler")
    try:
        return gdal.OpenEx(path, gdal.OF_RASTER)
    except RuntimeError:
        return None
    finally:
        gdal.PopErrorHandler()


# ----------------------------------------------------------------------------------------------------------------
# Format parsers (each returns a raw GDAL-key dict; read_rpc_metadata validates it)
# ----------------------------------------------------------------------------------------------------------------
def _missing(source: str, what: str, fmt: str) -> RPCFormatError:
    return RPCFormatError(f"{source}: missing RPC key {what} ({fmt} format)")


# --- .RPB (CPLKeywordParser-like) ---------------------------------------------------------------------------
_RPB_MAP = (
    ("ERR_BIAS", "errbias"), ("ERR_RAND", "errrand"),
    ("LINE_OFF", "lineoffset"), ("SAMP_OFF", "sampoffset"), ("LAT_OFF", "latoffset"),
    ("LONG_OFF", "longoffset"), ("HEIGHT_OFF", "heightoffset"),
    ("LINE_SCALE", "linescale"), ("SAMP_SCALE", "sampscale"), ("LAT_SCALE", "latscale"),
    ("LONG_SCALE", "longscale"), ("HEIGHT_SCALE", "heightscale"),
    ("LINE_NUM_COEFF", "linenumcoef"), ("LINE_DEN_COEFF", "linedencoef"),
    ("SAMP_NUM_COEFF", "sampnumcoef"), ("SAMP_DEN_COEFF", "sampdencoef"),
)
_RPB_NAME = dict((  # lower case -> spelling used in files
    ("errbias", "errBias"), ("errrand", "errRand"), ("lineoffset", "lineOffset"), ("sampoffset", "sampOffset"),
    ("latoffset", "latOffset"), ("longoffset", "longOffset"), ("heightoffset", "heightOffset"),
    ("linescale", "lineScale"), ("sampscale", "sampScale"), ("latscale", "latScale"),
    ("longscale", "longScale"), ("heightscale", "heightScale"), ("linenumcoef", "lineNumCoef"),
    ("linedencoef", "lineDenCoef"), ("sampnumcoef", "sampNumCoef"), ("sampdencoef", "sampDenCoef"),
))
_RPB_STMT = re.compile(r'([A-Za-z_][\w.]*)\s*=\s*(\([^)]*\)|"[^"]*"|[^;\n]*)\s*;?')


def _parse_keyword_text(text: str) -> Dict[str, str]:
    """ODL-like ``key = value;`` statements with BEGIN_GROUP/END_GROUP -> {'group.key' (lower case): value}."""
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    groups: List[str] = []
    out: Dict[str, str] = {}
    for m in _RPB_STMT.finditer(text):
        key, value = m.group(1), m.group(2).strip()
        ukey = key.upper()
        if ukey in ("BEGIN_GROUP", "GROUP", "BEGIN_OBJECT", "OBJECT"):
            groups.append(value.strip('"').lower())
            continue
        if ukey in ("END_GROUP", "END_OBJECT"):
            if groups:
                groups.pop()
            continue
        if value.startswith("("):
            value = " ".join(t for t in re.split(r"[\s,()]+", value) if t)
        elif value.startswith('"'):
            value = value.strip('"')
        out.setdefault(".".join(groups + [key.lower()]), value)
    return out


def _parse_rpb(text: str, source: str) -> Dict[str, str]:
    kw = _parse_keyword_text(text)
    md: Dict[str, str] = {}
    for gdal_key, rpb_key in _RPB_MAP:
        # GDAL requires the IMAGE group; a bare key is accepted too (same meaning, no ambiguity).
        value = kw.get("image." + rpb_key, kw.get(rpb_key))
        if value is None:
            if gdal_key in ("ERR_BIAS", "ERR_RAND"):
                continue
            raise _missing(source, f"IMAGE.{_RPB_NAME[rpb_key]}", "RPB")
        md[gdal_key] = value
    return md




# --- _RPC.TXT and KEY=value -----------------------------------------------------------------------------------
_KV_LINE = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*[:=]\s*(.*?)\s*$")


def _parse_kv_lines(text: str, lower: bool = False) -> Dict[str, str]:
    out: Dict[str, str] = {}
    for line in text.splitlines():
        m = _KV_LINE.match(line)
        if m:
            key = m.group(1).lower() if lower else m.group(1).upper()
            out.setdefault(key, m.group(2))  # first occurrence wins, as in GDAL's CSLFetchNameValue
    return out


def _parse_rpc_txt(text: str, source: str) -> Dict[str, str]:
    kv = _parse_kv_lines(text)
    md: Dict[str, str] = {}
    for key in SCALAR_KEYS + OPTIONAL_KEYS:
        if key in kv:
            md[key] = kv[key]
        elif key in SCALAR_KEYS:
            raise _missing(source, key, "_RPC.TXT")
    for key in COEFF_KEYS:
        if f"{key}_1" in kv:  # GeoEye layout: one coefficient per line, numbered 1..20
            values = []
            for j in range(1, _N_COEFF + 1):
                if f"{key}_{j}" not in kv:
                    raise _missing(source, f"{key}_{j}", "_RPC.TXT")
                values.append(kv[f"{key}_{j}"])
            if f"{key}_{_N_COEFF + 1}" in kv:
                raise RPCFormatError(f"{source}: RPC key {key} has more than {_N_COEFF} coefficients "
                                     f"({key}_{_N_COEFF + 1} present)")
            md[key] = " ".join(values)
        elif key in kv:  # GDAL key=value dump: the whole list on one line
            md[key] = kv[key]
        else:
            raise _missing(source, f"{key}_1", "_RPC.TXT")
    return md


# --- OSSIM .geom keyword list -----------------------------------------------------------------------------------
# RPC00A term order -> RPC00B: B[7..10] = A[8], A[9], A[10], A[7] (L², P², H², PLH); the rest coincide.
_A_TO_B = (0, 1, 2, 3, 4, 5, 6, 8, 9, 10, 7, 11, 12, 13, 14, 15, 16, 17, 18, 19)


def _parse_geom(text: str, source: str) -> Dict[str, str]:
    kv = _parse_kv_lines(text, lower=True)
    md: Dict[str, str] = {}
    for key in SCALAR_KEYS:
        if key.lower() not in kv:
            raise _missing(source, key.lower(), "OSSIM .geom")
        md[key] = kv[key.lower()]
    for gdal_key, geom_key in (("ERR_BIAS", "bias_error"), ("ERR_RAND", "rand_error")):
        if geom_key in kv:
            md[gdal_key] = kv[geom_key]
    fmt = kv.get("polynomial_format", "B").strip().upper()
    if fmt not in ("A", "B"):
        raise RPCFormatError(f"{source}: RPC key polynomial_format is {fmt!r}, expected A or B (OSSIM .geom)")
    for key in COEFF_KEYS:
        values = []
        for j in range(_N_COEFF):
            name = f"{key.lower()}_{j:02d}"
            if name not in kv:
                raise _missing(source, name, "OSSIM .geom")
            values.append(kv[name])
        if fmt == "A":
            values = [values[i] for i in _A_TO_B]
        md[key] = " ".join(values)
    return md


# --- ALOS fixed width -------------------------------------------------------------------------------------------
_ALOS_FIELDS = (("LINE_OFF", 6), ("SAMP_OFF", 5), ("LAT_OFF", 8), ("LONG_OFF", 9), ("HEIGHT_OFF", 5),
                ("LINE_SCALE", 6), ("SAMP_SCALE", 5), ("LAT_SCALE", 8), ("LONG_SCALE", 9), ("HEIGHT_SCALE", 5))
_ALOS_COEFF_WIDTH = 12
_ALOS_LEN = sum(w for _, w in _ALOS_FIELDS) + 4 * _N_COEFF * _ALOS_COEFF_WIDTH  # 1026
_ALOS_RE = re.compile(r"^[0-9+\-.Ee ]{%d,}$" % _ALOS_LEN)


def _parse_alos(text: str, source: str) -> Dict[str, str]:
    row = text.splitlines()[0] if text else ""
    if len(row) < _ALOS_LEN:
        raise RPCFormatError(f"{source}: ALOS RPC record has {len(row)} characters, {_ALOS_LEN} are required")
    md: Dict[str, str] = {}
    pos = 0
    for key, width in _ALOS_FIELDS:
        md[key] = row[pos:pos + width]
        pos += width
    for key in COEFF_KEYS:
        values = []
        for _ in range(_N_COEFF):
            values.append(row[pos:pos + _ALOS_COEFF_WIDTH])
            pos += _ALOS_COEFF_WIDTH
        md[key] = " ".join(values)
    return md


# --- XML formats -------------------------------------------------------------------------------------------------
def _local(tag: Any) -> str:
    return tag.split("}")[-1] if isinstance(tag, str) else ""


def _iter_named(root: ET.Element, name: str):
    lname = name.lower()
    for el in root.iter():
        if _local(el.tag).lower() == lname:
            yield el


def _first_named(root: ET.Element, name: str) -> Optional[ET.Element]:
    return next(_iter_named(root, name), None)


def _xml_to_dotted(node: ET.Element) -> Dict[str, str]:
    """Children of ``node`` flattened to {'a.b.c' (lower case): text}, first occurrence winning (like GDAL's
    ReadXMLToList + CSLFetchNameValue, which are case-insensitive)."""
    out: Dict[str, str] = {}

    def walk(el: ET.Element, prefix: str) -> None:
        for child in el:
            name = _local(child.tag).lower()
            if not name:
                continue
            key = f"{prefix}.{name}" if prefix else name
            text = (child.text or "").strip()
            if text:
                out.setdefault(key, text)
            walk(child, key)

    walk(node, "")
    return out


def _parse_gdal_xml(root: ET.Element, source: str) -> Optional[Dict[str, str]]:
    """<Metadata domain="RPC"><MDI key=...> at dataset level of a VRT or PAM file (as GDAL reads it), None if
    absent."""
    for el in root:
        if _local(el.tag) != "Metadata":
            continue
        if (el.get("domain") or "").upper() == "RPC":
            md = {}
            for mdi in el:
                if _local(mdi.tag) == "MDI" and mdi.get("key"):
                    md.setdefault(mdi.get("key"), mdi.text or "")
            return md
    return None


_ISD_MAP = (
    ("ERR_BIAS", "image.errbias"), ("ERR_RAND", "image.errrand"),
    ("LINE_OFF", "image.lineoffset"), ("SAMP_OFF", "image.sampoffset"), ("LAT_OFF", "image.latoffset"),
    ("LONG_OFF", "image.longoffset"), ("HEIGHT_OFF", "image.heightoffset"),
    ("LINE_SCALE", "image.linescale"), ("SAMP_SCALE", "image.sampscale"), ("LAT_SCALE", "image.latscale"),
    ("LONG_SCALE", "image.longscale"), ("HEIGHT_SCALE", "image.heightscale"),
    ("LINE_NUM_COEFF", "image.linenumcoeflist.linenumcoef"), ("LINE_DEN_COEFF", "image.linedencoeflist.linedencoef"),
    ("SAMP_NUM_COEFF", "image.sampnumcoeflist.sampnumcoef"), ("SAMP_DEN_COEFF", "image.sampdencoeflist.sampdencoef"),
)


def _parse_isd(rpb: ET.Element, source: str) -> Dict[str, str]:
    flat = _xml_to_dotted(rpb)
    md: Dict[str, str] = {}
    for gdal_key, path in _ISD_MAP:
        if path in flat:
            md[gdal_key] = flat[path]
        elif gdal_key not in ("ERR_BIAS", "ERR_RAND"):
            raise _missing(source, "RPB/" + path.upper().replace(".", "/"), "DigitalGlobe ISD XML")
    return md


_DIMAP_SCALARS = ("LINE_OFF", "SAMP_OFF", "LAT_OFF", "LONG_OFF", "HEIGHT_OFF",
                  "LINE_SCALE", "SAMP_SCALE", "LAT_SCALE", "LONG_SCALE", "HEIGHT_SCALE")


def _parse_dimap(root: ET.Element, source: str) -> Dict[str, str]:
    """DIMAP v2/v3 RPC, as GDAL's Pleiades metadata reader: the inverse (ground->image) model, LINE_OFF and
    SAMP_OFF minus the first-pixel index (1 in DIMAP v2, FIRST_COL of ImagetoGround_Validity_Domain in v3),
    formatted with %.15g."""
    model = _first_named(root, "Global_RFM")
    if model is None:
        model = _first_named(root, "Rational_Function_Model")
    if model is None:
        raise RPCFormatError(f"{source}: no Global_RFM / Rational_Function_Model element (DIMAP RPC format)")
    flat = _xml_to_dotted(model)
    if any(k.endswith(".f_col") or k.endswith(".f_row") for k in flat) and not any(
            k.endswith("line_num_coeff_1") for k in flat):
        return _parse_dimap_phr(flat, source)
    first_col = 1.0
    validity = _first_named(root, "ImagetoGround_Validity_Domain")
    if validity is not None:
        fc = _xml_to_dotted(validity).get("first_col")
        if fc is not None:
            value = _number(fc)
            if value is None:
                raise RPCFormatError(f"{source}: RPC key ImagetoGround_Validity_Domain/FIRST_COL is not a number")
            first_col = value
    md: Dict[str, str] = {}
    for key in _DIMAP_SCALARS:
        path = "rfm_validity." + key.lower()
        if path not in flat:
            raise _missing(source, f"RFM_Validity/{key}", "DIMAP")
        value = flat[path]
        if key in ("LINE_OFF", "SAMP_OFF"):
            number = _number(value.split()[0]) if value.split() else None
            if number is None:
                raise RPCFormatError(f"{source}: RPC key RFM_Validity/{key} is not a number ({value!r})")
            value = "%.15g" % (number - first_col)
        md[key] = value
    for key in COEFF_KEYS:
        values = []
        for j in range(1, _N_COEFF + 1):
            name = f"{key.lower()}_{j}"
            value = flat.get("inverse_model." + name, flat.get("groundtoimage_values." + name))
            if value is None:
                raise _missing(source, f"Inverse_Model/{key}_{j}", "DIMAP")
            values.append(value)
        md[key] = " ".join(values)
    return md


#: Pleiades DIMAP v1 (``PHR_Dimap_Document``, profile 1.4) ``RFM_Validity`` children: ``A`` is the scale, ``B`` the
#: offset (as CNES Shareloc reads them, ``rpc_reader_dimap_v1``).
_PHR_SCALARS = (("LONG", "lon"), ("LAT", "lat"), ("HEIGHT", "alt"), ("SAMP", "col"), ("LINE", "row"))
_PHR_BOX = (("MIN_LONG", "first_lon"), ("MIN_LAT", "first_lat"), ("MAX_LONG", "last_lon"), ("MAX_LAT", "last_lat"))


def _parse_dimap_phr(flat: Dict[str, str], source: str) -> Dict[str, str]:
    """Pleiades DIMAP v1 (PHR, profile 1.4) ``Global_RFM``: the inverse model ``F_COL``/``F_ROW`` (40 numbers each:
    20 numerator then 20 denominator coefficients, RPC00B term order with L = longitude, P = latitude), scales and
    offsets ``RFM_Validity/{Lon,Lat,Alt,Col,Row}/{A,B}``; image offsets in DIMAP's first-pixel-centre-at-1
    convention, so SAMP_OFF = Col/B - 1 and LINE_OFF = Row/B - 1 (RPC00B: first pixel centre at 0), as Shareloc."""
    md: Dict[str, str] = {}
    for key, name in _PHR_SCALARS:
        for suffix, child in (("_OFF", "b"), ("_SCALE", "a")):
            value = flat.get(f"rfm_validity.{name}.{child}")
            if value is None:
                raise _missing(source, f"RFM_Validity/{name.capitalize()}/{child.upper()}", "Pleiades DIMAP v1")
            if key in ("SAMP", "LINE") and suffix == "_OFF":
                number = _number(value)
                if number is None:
                    raise RPCFormatError(f"{source}: RPC key RFM_Validity/{name.capitalize()}/B is not a number "
                                         f"({value!r})")
                value = repr(number - 1.0)
            md[key + suffix] = value
    for key, name in (("SAMP", "f_col"), ("LINE", "f_row")):
        text = flat.get(f"inverse_model.{name}")
        if text is None:
            raise _missing(source, f"Inverse_Model/{name.upper()}", "Pleiades DIMAP v1")
        values = text.split()
        if len(values) != 2 * _N_COEFF:
            raise RPCFormatError(f"{source}: RPC key Inverse_Model/{name.upper()} has {len(values)} coefficients "
                                 f"instead of {2 * _N_COEFF} (20 numerator + 20 denominator)")
        md[f"{key}_NUM_COEFF"] = " ".join(values[:_N_COEFF])
        md[f"{key}_DEN_COEFF"] = " ".join(values[_N_COEFF:])
    for key, name in _PHR_BOX:
        value = flat.get(f"rfm_validity.inverse_model_validity_domain.{name}")
        if value is not None:
            md[key] = value
    return md


# --- JSON --------------------------------------------------------------------------------------------------------
_RPCM_MAP = (
    ("LINE_OFF", "row_offset"), ("SAMP_OFF", "col_offset"), ("LAT_OFF", "lat_offset"),
    ("LONG_OFF", "lon_offset"), ("HEIGHT_OFF", "alt_offset"),
    ("LINE_SCALE", "row_scale"), ("SAMP_SCALE", "col_scale"), ("LAT_SCALE", "lat_scale"),
    ("LONG_SCALE", "lon_scale"), ("HEIGHT_SCALE", "alt_scale"),
    ("LINE_NUM_COEFF", "row_num"), ("LINE_DEN_COEFF", "row_den"),
    ("SAMP_NUM_COEFF", "col_num"), ("SAMP_DEN_COEFF", "col_den"),
)


def _parse_json(data: Any, source: str) -> Dict[str, Any]:
    if not isinstance(data, dict):
        raise RPCFormatError(f"{source}: JSON RPC must be an object with RPC keys")
    inner = data
    for name in ("rpc", "RPC", "rpcs"):
        if isinstance(data.get(name), dict):
            inner = data[name]
            break
    lower = {str(k).lower(): v for k, v in inner.items()}
    md: Dict[str, Any] = {}
    if "row_offset" in lower or "row_num" in lower:  # rpcm / DFC2019 / Sat-NeRF attribute names
        for gdal_key, name in _RPCM_MAP:
            if name not in lower:
                raise _missing(source, name, "rpcm/DFC2019 JSON")
            md[gdal_key] = lower[name]
        top = {str(k).lower(): v for k, v in data.items()}
        for gdal_key, name in (("MIN_HEIGHT", "min_alt"), ("MAX_HEIGHT", "max_alt")):
            if name in top:
                md[gdal_key] = top[name]
        return md
    for key in REQUIRED_KEYS + OPTIONAL_KEYS:
        if key.lower() in lower:
            md[key] = lower[key.lower()]
        elif key in REQUIRED_KEYS:
            raise _missing(source, key, "JSON")
    return md


# ----------------------------------------------------------------------------------------------------------------
# Detection and the public reader
# ----------------------------------------------------------------------------------------------------------------
_RE_RPB = re.compile(r"\b(lineNumCoef|BEGIN_GROUP\s*=\s*IMAGE)\b", re.I)
_RE_GEOM = re.compile(r"^\s*line_num_coeff_00\s*:", re.M)
_RE_KV = re.compile(r"^\s*LINE_NUM_COEFF(_1)?\s*[:=]", re.M | re.I)
_SNIFF = 1 << 16


def _read_any(path: str) -> Tuple[Dict[str, Any], str, List[str]]:
    """(raw GDAL-key dict, format name, files read) for ``path``; raises RPCFormatError."""
    local = not _is_vsi(path)
    if local:
        if not os.path.exists(path):
            raise RPCFormatError(f"{path}: no such file")
        if os.path.isdir(path):
            return _read_gdal(path)  # e.g. a product folder some GDAL driver opens
    try:
        head = _read_bytes(path, _SNIFF)
    except OSError as exc:
        raise RPCFormatError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    if b"\x00" in head[:4096]:  # binary: an image
        return _read_gdal(path)
    stripped = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if stripped.startswith(b"<"):
        return _read_xml(path)
    if stripped.startswith(b"{") or stripped.startswith(b"["):
        try:
            data = json.loads(_read_bytes(path).decode("utf-8-sig"))
        except RecursionError:
            raise RPCFormatError(f"{path}: JSON nested too deeply to be an RPC file") from None
        except (UnicodeDecodeError, ValueError) as exc:
            raise RPCFormatError(f"{path}: not valid JSON ({str(exc)[:120]})") from None
        return _parse_json(data, path), "json", [path]
    text = head.decode("latin-1")
    if len(head) == _SNIFF:  # text sidecars are small; read the rest only when there is more
        text = _read_bytes(path).decode("latin-1")
    if _RE_RPB.search(text):
        return _parse_rpb(text, path), "rpb", [path]
    if _RE_GEOM.search(text):
        return _parse_geom(text, path), "geom", [path]
    if _RE_KV.search(text):
        return _parse_rpc_txt(text, path), "rpc_txt", [path]
    first = text.splitlines()[0] if text else ""
    if _ALOS_RE.match(first):
        return _parse_alos(text, path), "alos", [path]
    return _read_gdal(path, "text")


def _read_xml(path: str) -> Tuple[Dict[str, Any], str, List[str]]:
    try:
        root = ET.fromstring(_read_bytes(path))
    except ET.ParseError as exc:
        raise RPCFormatError(f"{path}: not well-formed XML ({exc})") from None
    except LookupError as exc:   # <?xml encoding="..."?> naming a codec Python does not know
        raise RPCFormatError(f"{path}: the XML declares an unknown encoding ({exc}); save it as UTF-8") from None
    except (ValueError, UnicodeError) as exc:
        raise RPCFormatError(f"{path}: cannot decode the XML ({exc}); save it as UTF-8") from None
    except RecursionError:
        raise RPCFormatError(f"{path}: XML nested too deeply to be an RPC file") from None
    md = _parse_gdal_xml(root, path)
    if md is not None:
        return md, "gdal_xml", [path]
    rpb = _first_named(root, "RPB")
    if rpb is not None:
        return _parse_isd(rpb, path), "isd", [path]
    if _first_named(root, "Global_RFM") is not None or _first_named(root, "Rational_Function_Model") is not None:
        return _parse_dimap(root, path), "dimap", [path]
    per_band = [b for b in _iter_named(root, "bandID") if _first_named(b, "ROW_NUM_01") is not None]
    if per_band:
        raise RPCFormatError(f"{path}: one RPC per band ({len(per_band)} bands, EnMAP-style metadata), not one RPC "
                             "of the image: not read; give the RPC of the band you use as its own file (GDAL keys)")
    if _local(root.tag) == "PAMDataset":
        raise RPCFormatError(f"{path}: no <Metadata domain=\"RPC\"> in this GDAL .aux.xml file")
    return _read_gdal(path, "xml")  # e.g. a VRT without an RPC block: GDAL is the judge


_KINDS = {
    "binary": "not an image GDAL can open",
    "text": "no RPC found in this text file",
    "xml": "no RPC found in this XML file (no <RPB>, DIMAP Rational_Function_Model or <Metadata domain=\"RPC\">)",
}


def _read_gdal(path: str, kind: str = "binary") -> Tuple[Dict[str, Any], str, List[str]]:
    ds = _gdal_open(path)
    if ds is None:
        raise RPCFormatError(
            f"{path}: {_KINDS[kind]}; expected an image with RPC, .RPB, _RPC.TXT, DIMAP RPC_*.XML, ISD XML, "
            "JSON, OSSIM .geom or ALOS RPC")
    md = ds.GetMetadata("RPC") or {}
    files = list(ds.GetFileList() or [path])
    driver = ds.GetDriver().ShortName
    ds = None
    if not md:
        raise RPCFormatError(
            f"{path}: no RPC metadata (GDAL {driver} driver found no RPC tags, .RPB, _RPC.TXT or RPC00B); "
            "give the RPC sidecar file instead")
    return md, "gdal", files


def read_rpc_metadata(path: PathLike) -> Dict[str, str]:
    """Read the RPC of an image or of a standalone RPC file as GDAL ``RPC``-domain metadata (METHODS §1).

    Parameters
    ----------
    path : str or path-like
        An image GDAL opens (RPC from TIFF tags, a sidecar GDAL finds next to it, NITF RPC00B, ...) or an RPC
        file without its image, recognised by content (see the module docstring for the formats).

    Returns
    -------
    dict of str to str
        Canonical GDAL RPC keys (see :func:`normalize_rpc_metadata`), numerically equal to what GDAL reports
        for the same RPC; offsets in the RPC00B convention (first pixel centre at 0, 0), as in GDAL.

    Raises
    ------
    RPCFormatError
        Unsupported or malformed input; the one-line message names the file and the missing or bad key.
    """
    spath = os.fspath(path)
    try:
        md, _fmt, files = _read_any(spath)
        result = normalize_rpc_metadata(md, spath)
    except Gf4calError:
        raise
    except RecursionError:
        raise RPCFormatError(f"{spath}: nested too deeply to be an RPC file") from None
    except (ValueError, TypeError, LookupError, OverflowError, ArithmeticError, UnicodeError, KeyError,
            IndexError, AttributeError) as exc:
        # Backstop for malformed input a parser did not foresee: still one line, with the class for a bug report.
        raise RPCFormatError(f"{spath}: cannot read an RPC from this file ({type(exc).__name__}: "
                             f"{str(exc)[:120]})") from None
    _register_input(files + [spath])
    return result


def rpc_file_format(path: PathLike) -> str:
    """The name of the RPC format :func:`read_rpc_metadata` recognises in ``path``
    (``gdal``, ``rpb``, ``rpc_txt``, ``dimap``, ``isd``, ``gdal_xml``, ``json``, ``geom`` or ``alos``)."""
    spath = os.fspath(path)
    md, fmt, _files = _read_any(spath)
    normalize_rpc_metadata(md, spath)
    return fmt


# ----------------------------------------------------------------------------------------------------------------
# Writers
# ----------------------------------------------------------------------------------------------------------------
def rpb_path_for(image_path: PathLike) -> Path:
    """The ``.RPB`` sidecar name GDAL looks for next to ``image_path`` (``scene.tif`` -> ``scene.RPB``)."""
    p = Path(image_path)
    return p.with_suffix(".RPB")


def rpc_txt_path_for(image_path: PathLike) -> Path:
    """The ``_RPC.TXT`` sidecar name GDAL looks for next to ``image_path`` (``scene.tif`` -> ``scene_RPC.TXT``)."""
    p = Path(image_path)
    return p.with_name(p.stem + "_RPC.TXT")


def _metadata_of(rpc: Any) -> Dict[str, str]:
    """Canonical metadata of an RPCModel (anything with ``to_gdal_metadata()``) or a GDAL-key mapping, every
    number re-printed as the shortest string that reads back to the same double."""
    if hasattr(rpc, "to_gdal_metadata"):
        md = rpc.to_gdal_metadata()
        source = "RPC model"
    elif isinstance(rpc, Mapping):
        md = rpc
        source = "RPC metadata"
    elif hasattr(rpc, "rpc"):      # a model composed over an RPC (CompensatedRPC, RecalibratedSensor): no RPC00B
        raise RPCFormatError(f"cannot write {type(rpc).__name__}: it is an RPC composed with a correction; make an "
                             "RPC of it with apply_compensation(model.rpc, model.result) (fold or refit, its error "
                             "reported; recalibrate_rpc for a RecalibratedSensor) and write that .rpc")
    else:
        raise RPCFormatError(f"cannot write {type(rpc).__name__}: give an RPCModel or a dict of GDAL RPC keys")
    canon = normalize_rpc_metadata(md, source)
    out: Dict[str, str] = {}
    for key, value in canon.items():
        if key in COEFF_KEYS:
            out[key] = " ".join(repr(float(t)) for t in value.split())
        else:
            out[key] = repr(float(value))
    return out


def _source_paths_of(rpc: Any) -> List[str]:
    paths = []
    for attr in ("source", "source_path", "path"):
        value = getattr(rpc, attr, None)
        if isinstance(value, (str, os.PathLike)):
            paths.append(os.fspath(value))
    return paths


def _check_output(path: Path, overwrite: bool, inputs: Iterable[str] = ()) -> None:
    real = os.path.realpath(path)
    protected = (_INPUT_FILES - _OUTPUT_FILES) | {os.path.realpath(p) for p in inputs}
    if real in protected:
        raise InputOverwriteError(f"{path}: this is an input file (an RPC or image was read from it); "
                                  "write the new RPC to another path")
    if not path.parent.is_dir():
        raise Gf4calError(f"{path}: the output folder {path.parent} does not exist; create it first")
    if path.exists() and not overwrite:
        raise InputOverwriteError(f"{path}: file exists; choose another path or pass overwrite=True")


def _tmp_name(path: Path, suffix: str = ".tmp") -> Path:
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}{suffix}")


def _commit(tmp: Path, path: Path, overwrite: bool) -> None:
    """Move a finished temporary file into place atomically; without ``overwrite`` never clobber a file that
    appeared meanwhile (a hard link is an atomic create-if-absent)."""
    if overwrite:
        os.replace(tmp, path)
    else:
        try:
            os.link(tmp, path)
            os.unlink(tmp)
        except FileExistsError:
            raise InputOverwriteError(f"{path}: file exists; choose another path or pass overwrite=True") from None
        except OSError:  # file system without hard links
            if path.exists():
                raise InputOverwriteError(
                    f"{path}: file exists; choose another path or pass overwrite=True") from None
            os.replace(tmp, path)
    _OUTPUT_FILES.add(os.path.realpath(path))


def _atomic_write_text(path: Path, text: str, overwrite: bool) -> None:
    tmp = _tmp_name(path)
    try:
        with open(tmp, "x", encoding="ascii", newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        _commit(tmp, path, overwrite)
    finally:
        if tmp.exists():
            tmp.unlink()


def format_rpb(rpc: Any) -> str:
    """The text of a DigitalGlobe ``.RPB`` file for ``rpc`` (RPCModel or GDAL-key mapping), the layout GDAL
    writes; ``errBias``/``errRand`` are written as 0.0 when unknown, as GDAL does, for strict RPB readers."""
    md = _metadata_of(rpc)
    lines = ['satId = "UNKNOWN";', 'bandId = "P";', 'SpecId = "RPC00B";', "BEGIN_GROUP = IMAGE"]
    for gdal_key, rpb_key in _RPB_MAP:
        name = _RPB_NAME[rpb_key]
        if gdal_key in COEFF_KEYS:
            coeffs = md[gdal_key].split()
            lines.append(f"\t{name} = (")
            lines.extend(f"\t\t\t{c}," for c in coeffs[:-1])
            lines.append(f"\t\t\t{coeffs[-1]});")
        else:
            lines.append(f"\t{name} = {md.get(gdal_key, '0.0')};")
    lines += ["END_GROUP = IMAGE", "END;", ""]
    return "\n".join(lines)


def format_rpc_txt(rpc: Any) -> str:
    """The text of a GeoEye-style ``_RPC.TXT`` file for ``rpc`` (the layout GDAL writes)."""
    md = _metadata_of(rpc)
    lines = []
    for key in ("ERR_BIAS", "ERR_RAND") + SCALAR_KEYS:
        if key in md:
            lines.append(f"{key}: {md[key]}")
    for key in COEFF_KEYS:
        lines.extend(f"{key}_{j}: {c}" for j, c in enumerate(md[key].split(), start=1))
    return "\n".join(lines) + "\n"


def write_rpb(rpc: Any, path: PathLike, overwrite: bool = False) -> Path:
    """Write ``rpc`` as a DigitalGlobe ``.RPB`` sidecar (METHODS §1).

    GDAL picks the file up for an image ``scene.tif`` when it is named ``scene.RPB`` (see :func:`rpb_path_for`);
    values are written with the shortest round-trip representation, so GDAL reads back identical doubles.

    Parameters
    ----------
    rpc : RPCModel or mapping
        Anything with ``to_gdal_metadata()``, or a dict of GDAL RPC keys.
    path : path-like
        The sidecar to write, exactly this name.
    overwrite : bool
        Replace an existing file (never a file an RPC or image was read from).

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    InputOverwriteError
        ``path`` exists (and not ``overwrite``) or is an input.
    RPCFormatError
        ``rpc`` is incomplete or malformed.
    """
    out = Path(path)
    text = format_rpb(rpc)
    _check_output(out, overwrite, _source_paths_of(rpc))
    _atomic_write_text(out, text, overwrite)
    return out


def write_rpc_txt(rpc: Any, path: PathLike, overwrite: bool = False) -> Path:
    """Write ``rpc`` as a GeoEye-style ``_RPC.TXT`` sidecar (METHODS §1).

    GDAL picks the file up for an image ``scene.tif`` when it is named ``scene_RPC.TXT`` (see
    :func:`rpc_txt_path_for`). Same guarantees and errors as :func:`write_rpb`.
    """
    out = Path(path)
    text = format_rpc_txt(rpc)
    _check_output(out, overwrite, _source_paths_of(rpc))
    _atomic_write_text(out, text, overwrite)
    return out


def write_rpc_vrt(image_path: PathLike, rpc: Any, vrt_path: PathLike, overwrite: bool = False) -> Path:
    """Write a VRT over the untouched ``image_path`` whose ``RPC`` metadata domain is ``rpc`` (METHODS §1).

    The source's own RPC (tags or sidecars) is replaced, so ``gdalwarp -rpc vrt_path ...`` and
    ``gdal.Transformer(vrt, None, ['METHOD=RPC'])`` use the new model. The image is referenced, not copied
    (by a path relative to the VRT when the image lies in the VRT's folder or below, or when the image path was given
    relative, e.g. ``../scene.tif``; otherwise by its absolute path).

    Parameters
    ----------
    image_path : path-like
        Any raster GDAL opens.
    rpc : RPCModel or mapping
        The new RPC.
    vrt_path : path-like
        The VRT to write.
    overwrite : bool
        Replace an existing VRT (never the image or any other input).

    Returns
    -------
    pathlib.Path
        ``vrt_path``.
    """
    from osgeo import gdal

    md = _metadata_of(rpc)
    out = Path(vrt_path)
    src_name = os.fspath(image_path)
    if not _is_vsi(src_name):
        # absolute, so GDAL stores a path relative to the VRT's folder or an absolute one, never one relative
        # to the current working directory
        src_name = os.path.abspath(src_name)
    src = _gdal_open(src_name)
    if src is None:
        raise Gf4calError(f"{src_name}: GDAL cannot open this image")
    inputs = list(src.GetFileList() or [src_name]) + [src_name] + _source_paths_of(rpc)
    _check_output(out, overwrite, inputs)
    tmp = _tmp_name(out, ".vrt")
    try:
        gdal.PushErrorHandler("CPLQuietErrorHandler")
        try:
            vrt = gdal.Translate(os.fspath(tmp), src, format="VRT")
        except RuntimeError:
            vrt = None
        finally:
            gdal.PopErrorHandler()
        if vrt is None:
            raise Gf4calError(f"{src_name}: GDAL could not build a VRT over this image "
                              f"({gdal.GetLastErrorMsg() or 'unknown error'})")
        vrt.SetMetadata(md, "RPC")  # replaces the whole domain: the source's RPC is dropped
        vrt.FlushCache()
        vrt = None
        src = None
        given = os.fspath(image_path)
        if not _is_vsi(given) and not os.path.isabs(given):     # given relative: keep it relative (to the VRT)
            _relative_source(tmp, src_name, os.path.dirname(os.path.abspath(out)))
        _commit(tmp, out, overwrite)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out


def _relative_source(vrt_file, abs_source: str, vrt_folder: str) -> None:
    """Make the VRT's absolute ``SourceFilename`` of ``abs_source`` relative to ``vrt_folder`` (``../x.tif``)."""
    from xml.sax.saxutils import escape
    text = Path(vrt_file).read_text()
    rel = os.path.relpath(abs_source, vrt_folder)
    old = f'<SourceFilename relativeToVRT="0">{escape(abs_source)}</SourceFilename>'
    if old in text:
        Path(vrt_file).write_text(text.replace(old, f'<SourceFilename relativeToVRT="1">{escape(rel)}</SourceFilename>'))


__all__ = [
    "COEFF_KEYS", "OPTIONAL_KEYS", "REQUIRED_KEYS", "SCALAR_KEYS",
    "format_rpb", "format_rpc_txt", "normalize_rpc_metadata", "read_rpc_metadata", "rpb_path_for",
    "rpc_file_format", "rpc_txt_path_for", "write_rpb", "write_rpc_txt", "write_rpc_vrt",
]
