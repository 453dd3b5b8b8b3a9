"""Geoid grids through PROJ's own grid names and search path (METHODS §2: heights above a geoid).

One place answers "which grid file converts heights above this geoid to ellipsoidal heights": :func:`find_grid`
looks a geoid up under PROJ's current names (``us_nga_egm96_15.tif``, ``us_nga_egm08_25.tif``) and its legacy ones
(``egm96_15.gtx``, ``egm08_25.gtx``) in PROJ's data directories (``PROJ_DATA``/``PROJ_LIB``, pyproj's data and user
directories, ``/usr/share/proj``), without the network; a path to a user grid is used as it is.
:func:`resolve_geoid` turns a user's choice (``none``, ``egm96``, ``egm2008``, a path, ``auto`` = what the DEM's CRS
declares) into a grid path or ``None``. A declared geoid whose grid is missing raises :class:`GeoidGridMissing`,
which names the grid by its PROJ name; each interface phrases how to pass a grid (:meth:`GeoidGridMissing.phrase`).
"""
from __future__ import annotations

import os
from typing import List, Optional, Sequence, Tuple

import pyproj
from osgeo import gdal

from .errors import DEMError

#: PROJ grid names of each geoid, current name first (PROJ >= 7 / proj-data), then the legacy names.
GEOID_GRID_NAMES = {
    "egm96": ("us_nga_egm96_15.tif", "egm96_15.gtx"),
    "egm2008": ("us_nga_egm08_25.tif", "egm08_25.gtx", "egm08_1.gtx"),
}
#: The words the CLI accepts for "the heights are ellipsoidal, never convert".
NO_GEOID = ("none", "ellipsoid", "ellipsoidal", "false")


class GeoidGridMissing(DEMError):
    """A geoid is declared or asked for, and no grid of it is installed where PROJ looks.

    ``geoid`` is the geoid (``"egm2008"``), ``grids`` its PROJ grid names, ``dirs`` the folders searched. The
    message says how to pass a grid in neutral words (``geoid=<grid path>``); :meth:`phrase` rewrites that part
    for an interface (``--geoid PATH`` at the CLI, a parameter label in QGIS).
    """

    def __init__(self, geoid: str, grids: Sequence[str], dirs: Sequence[str], source: Optional[str] = None,
                 option: str = "geoid=<grid path>"):
        self.geoid, self.grids, self.dirs, self.source = geoid, tuple(grids), tuple(dirs), source
        super().__init__(self._text(option))

    def _text(self, option: str) -> str:
        what = f"{self.source}: its heights are above {self.geoid.upper()}, but" if self.source else \
            f"{self.geoid.upper()}:"
        return (f"{what} the geoid grid {self.grids[0]} (or {', '.join(self.grids[1:])}) is not installed in PROJ's "
                f"data directories ({os.pathsep.join(self.dirs) or 'none'}); install it there (projsync --file "
                f"{self.grids[0]}) or pass the grid with {option}")

    def phrase(self, option: str) -> "GeoidGridMissing":
        """The same error with ``option`` (e.g. ``"--geoid PATH"``) as the way to pass a grid."""
        return GeoidGridMissing(self.geoid, self.grids, self.dirs, self.source, option)


def proj_search_dirs() -> List[str]:
    """PROJ's data directories, in PROJ's order: ``PROJ_DATA`` (or ``PROJ_LIB``), pyproj's data dir, the user's
    PROJ dir, ``/usr/share/proj`` (existing folders, each once)."""
    dirs: List[str] = []
    for env in ("PROJ_DATA", "PROJ_LIB"):
        dirs += [d for d in os.environ.get(env, "").split(os.pathsep) if d]
    try:
        dirs += [d for d in pyproj.datadir.get_data_dir().split(os.pathsep) if d]
    except Exception:  # pyproj raises its own DataDirError when it has none
        pass
    dirs += [pyproj.datadir.get_user_data_dir(), "/usr/share/proj", "/usr/local/share/proj"]
    out: List[str] = []
    for d in dirs:
        if os.path.isdir(d) and os.path.realpath(d) not in [os.path.realpath(x) for x in out]:
            out.append(d)
    return out


def find_grid(geoid: str) -> Tuple[Optional[str], Tuple[str, ...], List[str]]:
    """``(path or None, PROJ names tried, folders searched)`` for ``"egm96"`` / ``"egm2008"`` (no network)."""
    names = GEOID_GRID_NAMES[geoid]
    dirs = proj_search_dirs()
    for name in names:
        for d in dirs:
            path = os.path.join(d, name)
            if os.path.isfile(path):
                return path, names, dirs
    return None, names, dirs


def grid_path(geoid: str, source: Optional[str] = None) -> str:
    """The installed grid of ``geoid`` (a name of :data:`GEOID_GRID_NAMES` or a grid path), or
    :class:`GeoidGridMissing` (:class:`DEMError` for a path that does not exist)."""
    key = str(geoid).strip().lower()
    if key in GEOID_GRID_NAMES:
        path, names, dirs = find_grid(key)
        if path is None:
            raise GeoidGridMissing(key, names, dirs, source)
        return path
    if not os.path.isfile(str(geoid)):
        raise DEMError(f"geoid grid not found: {geoid}; give 'egm96', 'egm2008', 'none' or the path of a .gtx/.tif "
                       "geoid grid")
    return str(geoid)


def declared_geoid(path: str) -> Optional[str]:
    """The geoid a raster's compound CRS declares for its heights: ``"egm96"``, ``"egm2008"`` or None.

    GDAL's GeoTIFF reader reports the vertical part of a CRS only with ``GTIFF_REPORT_COMPD_CS=YES``. A vertical
    datum we cannot convert is an error: using those heights as ellipsoidal would be silently wrong.
    """
    gdal.SetThreadLocalConfigOption("GTIFF_REPORT_COMPD_CS", "YES")
    try:
        ds = gdal.Open(path)
        srs = ds.GetSpatialRef() if ds is not None else None
    except RuntimeError:
        srs = None
    finally:
        gdal.SetThreadLocalConfigOption("GTIFF_REPORT_COMPD_CS", None)
    if srs is None or not srs.IsCompound():
        return None
    code = srs.GetAuthorityCode("COMPD_CS|VERT_CS") or ""
    name = f"{srs.GetAttrValue('VERT_CS') or ''} {srs.GetAttrValue('VERT_DATUM') or ''}".upper()
    if code == "5773" or "EGM96" in name:
        return "egm96"
    if code == "3855" or "EGM2008" in name:
        return "egm2008"
    if "ELLIPSOID" in name:
        return None
    raise DEMError(f"DEM {path}: its heights refer to the vertical datum {name.strip() or code!r}; pass the geoid "
                   "grid of that datum (geoid=<grid path>, --geoid) or geoid=False to use the heights as they are")


def resolve_geoid(choice, dem_path: Optional[str] = None) -> Optional[str]:
    """The grid path a DEM's heights need, from the user's ``choice`` (METHODS §2).

    ``choice``: ``None``/``"auto"`` (what the DEM's CRS declares: a grid for EGM96/EGM2008, None for ellipsoidal or
    no vertical datum; an undeclared-grid datum raises), ``"none"``/``False`` (heights used as they are),
    ``"egm96"``/``"egm2008"`` or a grid path. Raises :class:`GeoidGridMissing` naming the missing grid.
    """
    if choice is False or (isinstance(choice, str) and choice.strip().lower() in NO_GEOID):
        return None
    if choice is None or (isinstance(choice, str) and choice.strip().lower() == "auto"):
        if dem_path is None:
            return None
        declared = declared_geoid(str(dem_path))
        return grid_path(declared, source=str(dem_path)) if declared else None
    return grid_path(str(choice))
