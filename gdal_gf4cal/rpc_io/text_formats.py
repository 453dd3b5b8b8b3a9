"""Readers of the text RPC formats: DigitalGlobe ``.RPB``, ``_RPC.TXT`` / ``KEY=value`` lists, OSSIM ``.geom``,
ALOS fixed-width records (each returns a raw GDAL-key dict; :func:`~.readers.read_rpc_metadata` validates it)."""
from __future__ import annotations

import re
from typing import Dict, List

from ..errors import RPCFormatError
from .canonical import _N_COEFF, COEFF_KEYS, OPTIONAL_KEYS, SCALAR_KEYS, _missing

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

