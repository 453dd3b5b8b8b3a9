"""The canonical RPC dictionary (GDAL's ``RPC`` metadata-domain keys, string values) and the file access the
readers share (local or ``/vsi`` paths, quiet GDAL opens)."""
from __future__ import annotations

import math
import os
import re
from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

from osgeo import gdal

from ..errors import RPCFormatError

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


def _gdal_open(path: str):
    """gdal.OpenEx as a raster (None if GDAL cannot), quiet, whatever the caller's exception mode."""
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

