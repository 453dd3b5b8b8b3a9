"""Readers of the XML RPC formats: GDAL VRT/PAM ``<Metadata domain="RPC">``, Maxar ISD, Pleiades/SPOT DIMAP v2/v3
and Pleiades DIMAP v1.4 (``PHR_Dimap_Document``)."""
from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Any, Dict, Optional

from ..errors import RPCFormatError
from .canonical import _N_COEFF, COEFF_KEYS, _missing, _number


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

