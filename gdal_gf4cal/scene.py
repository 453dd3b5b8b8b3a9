"""An opened input, as the workflows pass it around instead of reopening it: :class:`Scene`.

``Scene.open(path)`` opens the input once (GDAL raster, quietly): its pixel size, the files it is made of (the image
and the sidecars GDAL reads with it: inputs no output may replace) and its key (the name of its outputs,
:func:`gdal_gf4cal.outputs.scene_stem`). A standalone RPC file (``.RPB``, ``_RPC.TXT``, ``.json``, ``.geom``...)
is a scene without pixels (``size`` None, no dataset). ``scene.with_rpc(rpc)`` adds the RPC of the image's own
pixel grid through :func:`gdal_gf4cal.crop.image_rpc` (the crop rules, the RPC beside it) and its note, as a new
value, so a job can check its outputs between opening and reading.
"""
from __future__ import annotations

import dataclasses
import os
from typing import Any, Optional, Tuple

from ._gdal import try_open_raster
from .crop import image_rpc
from .outputs import scene_stem

__all__ = ["Scene", "open_input"]

#: Inputs taken as standalone RPC files without opening them as rasters.
RPC_FILE_SUFFIXES = (".rpb", "_rpc.txt", ".txt", ".json", ".geom")


def open_input(path) -> Tuple[Any, Optional[Tuple[int, int]], list]:
    """``(dataset, (width, height), files)`` when GDAL opens ``path`` as a raster with pixels (``files``: the path
    and every file GDAL reads with it), else ``(None, None, [path])`` (a standalone RPC file)."""
    path = os.fspath(path)
    if path.lower().endswith(RPC_FILE_SUFFIXES):
        return None, None, [path]
    ds = try_open_raster(path)
    if ds is None or ds.RasterCount == 0 or ds.RasterXSize <= 1:
        return None, None, [path]
    return ds, (ds.RasterXSize, ds.RasterYSize), [path] + list(ds.GetFileList() or [])


@dataclasses.dataclass(frozen=True)
class Scene:
    """One opened input (module docstring): ``path`` as given, ``key`` (its outputs' name), ``size`` (width,
    height; None for a standalone RPC file), ``files`` (the inputs it is made of), ``dataset`` (the open GDAL
    raster, None without pixels), ``rpc`` and ``note`` once :meth:`with_rpc` has read the RPC."""
    path: str
    key: str
    size: Optional[Tuple[int, int]]
    files: Tuple[str, ...]
    dataset: Any = dataclasses.field(default=None, repr=False, compare=False)
    rpc: Any = None
    note: Optional[str] = None

    @classmethod
    def open(cls, path) -> "Scene":
        """Open ``path`` once (see :func:`open_input`)."""
        ds, size, files = open_input(path)
        return cls(os.fspath(path), scene_stem(path), size, tuple(files), ds)

    @property
    def is_image(self) -> bool:
        """True when the input has pixels (an image), False for a standalone RPC file."""
        return self.size is not None

    def with_rpc(self, rpc=None) -> "Scene":
        """This scene with the RPC of its own pixel grid (:func:`~gdal_gf4cal.crop.image_rpc`: ``rpc`` None, a
        path or a model) and the note saying what was applied; an RPC file given apart joins ``files``."""
        model, note = image_rpc(self.path, rpc)
        extra = (os.fspath(rpc),) if isinstance(rpc, (str, os.PathLike)) else ()
        return dataclasses.replace(self, rpc=model, note=note, files=self.files + extra)

    def __reduce__(self):
        """Pickled (to a Dask worker) without the GDAL dataset, which is reopened there."""
        return (_reopen, (self.path, self.rpc, self.note, self.files))


def _reopen(path, rpc, note, files) -> Scene:
    return dataclasses.replace(Scene.open(path), rpc=rpc, note=note, files=tuple(files))
