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
never replace a file the RPC was read from (:class:`InputOverwriteError`: the model's ``source``, the files a
:class:`RPCMetadata` was read from, the image a VRT is built over; no process-wide registry).

A package: :mod:`.canonical` (keys, canonical form), :mod:`.text_formats` and :mod:`.xml_formats` (parsers by
format), :mod:`.readers` (detection, JSON, GDAL, the public readers), :mod:`.writers`.
"""
from __future__ import annotations

from .canonical import COEFF_KEYS, OPTIONAL_KEYS, REQUIRED_KEYS, SCALAR_KEYS, normalize_rpc_metadata
from .readers import RPCMetadata, read_rpc_metadata, rpc_file_format
from .writers import format_rpb, format_rpc_txt, rpb_path_for, rpc_txt_path_for, write_rpb, write_rpc_txt, write_rpc_vrt

__all__ = [
    "COEFF_KEYS", "OPTIONAL_KEYS", "REQUIRED_KEYS", "SCALAR_KEYS", "RPCMetadata",
    "format_rpb", "format_rpc_txt", "normalize_rpc_metadata", "read_rpc_metadata", "rpb_path_for",
    "rpc_file_format", "rpc_txt_path_for", "write_rpb", "write_rpc_txt", "write_rpc_vrt",
]
