"""RPC writers: ``.RPB`` and ``_RPC.TXT`` sidecars GDAL reads back to identical doubles, and a VRT over an untouched
image carrying a new RPC. Atomic (temporary in the same folder, then a rename that never clobbers a file that
appeared meanwhile); the output checked by :func:`gdal_gf4cal.outputs.check_output_path` against the files the RPC
was read from (:attr:`RPCModel.source`, :attr:`RPCMetadata.files`) and the image a VRT is built over: no registry
of the process's inputs."""
from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Any, Dict, Iterable, List, Mapping
from xml.sax.saxutils import escape

from osgeo import gdal

from ..errors import Gf4calError, InputOverwriteError, RPCFormatError
from ..outputs import check_output_path
from .canonical import COEFF_KEYS, SCALAR_KEYS, PathLike, _gdal_open, _is_vsi, normalize_rpc_metadata
from .text_formats import _RPB_MAP, _RPB_NAME


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
    """The files ``rpc`` was read from: its ``source`` (``source_path``, ``path``) and, for an
    :class:`~.readers.RPCMetadata`, every file read (an image and its sidecar)."""
    paths = []
    for attr in ("source", "source_path", "path"):
        value = getattr(rpc, attr, None)
        if isinstance(value, (str, os.PathLike)) and os.fspath(value):
            paths.append(os.fspath(value))
    return paths + [os.fspath(p) for p in getattr(rpc, "files", ()) if isinstance(p, (str, os.PathLike))]


def _check_output(path: Path, overwrite: bool, inputs: Iterable[str] = ()) -> None:
    """The output rule (:func:`~gdal_gf4cal.outputs.check_output_path`) against ``inputs``, the files the RPC came
    from (and the image of a VRT), passed explicitly; then the folder must exist."""
    check_output_path(path, overwrite=overwrite, inputs=inputs)
    if not path.parent.is_dir():
        raise Gf4calError(f"{path}: the output folder {path.parent} does not exist; create it first")


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
    text = Path(vrt_file).read_text()
    rel = os.path.relpath(abs_source, vrt_folder)
    old = f'<SourceFilename relativeToVRT="0">{escape(abs_source)}</SourceFilename>'
    if old in text:
        Path(vrt_file).write_text(text.replace(old, f'<SourceFilename relativeToVRT="1">{escape(rel)}</SourceFilename>'))

