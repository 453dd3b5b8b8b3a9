"""The public RPC readers: format detection by content, the JSON and GDAL readers, :func:`read_rpc_metadata`
(returns :class:`RPCMetadata`: the canonical dict that knows the files it was read from, so the writers can refuse
to replace them without any process-wide registry) and :func:`rpc_file_format`."""
from __future__ import annotations

import json
import os
import re
import xml.etree.ElementTree as ET
from typing import Any, Dict, List, Tuple

from ..errors import Gf4calError, RPCFormatError
from .canonical import (
    OPTIONAL_KEYS,
    REQUIRED_KEYS,
    PathLike,
    _gdal_open,
    _is_vsi,
    _missing,
    _read_bytes,
    normalize_rpc_metadata,
)
from .text_formats import _ALOS_RE, _parse_alos, _parse_geom, _parse_rpb, _parse_rpc_txt
from .xml_formats import _first_named, _iter_named, _local, _parse_dimap, _parse_gdal_xml, _parse_isd

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


class RPCMetadata(dict):
    """The canonical RPC dictionary :func:`read_rpc_metadata` returns (a plain ``dict`` of GDAL RPC keys) that also
    knows where it came from: ``source`` (the path given) and ``files`` (every file read, e.g. an image and the
    sidecar GDAL found beside it). The writers refuse to replace those files; ``dict(md)`` is a copy without them."""

    def __init__(self, data, source: str = "", files: Tuple[str, ...] = ()):
        super().__init__(data)
        self.source = source
        self.files = tuple(files)

    def __reduce__(self):
        return (type(self), (dict(self), self.source, self.files))


def read_rpc_metadata(path: PathLike) -> Dict[str, str]:
    """Read the RPC of an image or of a standalone RPC file as GDAL ``RPC``-domain metadata (METHODS §1).

    Parameters
    ----------
    path : str or path-like
        An image GDAL opens (RPC from TIFF tags, a sidecar GDAL finds next to it, NITF RPC00B, ...) or an RPC
        file without its image, recognised by content (see the module docstring for the formats).

    Returns
    -------
    RPCMetadata (a dict of str to str)
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
    return RPCMetadata(result, spath, [f for f in files + [spath] if f and not _is_vsi(str(f))])


def rpc_file_format(path: PathLike) -> str:
    """The name of the RPC format :func:`read_rpc_metadata` recognises in ``path``
    (``gdal``, ``rpb``, ``rpc_txt``, ``dimap``, ``isd``, ``gdal_xml``, ``json``, ``geom`` or ``alos``)."""
    spath = os.fspath(path)
    md, fmt, _files = _read_any(spath)
    normalize_rpc_metadata(md, spath)
    return fmt


# ----------------------------------------------------------------------------------------------------------------
# Writers
