"""One observation table for every image of a job (METHODS §4, §7, §8), and its one-image view, the GCP table.

The observation table is a :class:`pandas.DataFrame` in **long format**, one row per (point, image) observation, as
AROSICS's ``Tie_Point_Grid`` keeps one tie-point table with its filters in levels:

=================  ========================================================================================
``point_id``       str; rows with the same ``point_id`` are the same ground point (a tie point across images,
                   or one GCP seen in several images)
``image_id``       str; the image the observation is in (its file name for the block-calibration ``OBS`` files)
``kind``           ``"gcp"`` (ground coordinates known) or ``"tie"`` (ground coordinates estimated)
``sample, line``   float px, GDAL pixel convention (centre of the first pixel at 0.5)
``sigma``          float px, a-priori precision of the image measurement (default 1.0)
``role``           ``"control"`` or ``"check"``
``lon, lat, h``    WGS84 degrees and ellipsoidal metres; the same on every row of one point; NaN for ties until
                   they are estimated (§7 intersection, §8 block adjustment)
=================  ========================================================================================

Outlier levels (optional, absent until a filter has run): ``outlier_<level>`` (bool, one column per filter level
that ran, e.g. ``outlier_match``, ``outlier_reject``, ``outlier_snooping``), ``outlier`` (bool, any level) and
``outlier_level`` (str: the first level, in :data:`OUTLIER_LEVELS` order, that flagged the row; ``""`` if kept).
Filters are cumulative: a row flagged at one level stays flagged. Use :func:`flag_outliers`. Any other column
(truth, quality, ...) is carried through untouched.

The GCP table (DESIGN.md "GCP table schema") is the view of one image: :func:`gcp_view` and :func:`from_gcps`
convert losslessly between the two (extra columns kept). Its schema lives here (:data:`SCHEMA`,
:func:`make_gcps`, :func:`validate_gcps`, :func:`fill_heights`) because both :mod:`gdal_gf4cal.gcp` and
:mod:`gdal_gf4cal.gcp_formats` build on it; this module imports neither (no import cycle).

Files: :func:`read_observations` / :func:`write_observations` (CSV, GeoPackage). The block-calibration ``OBS``
files (columns ``point_id, image, sample, line`` and, for GCPs, ``lon, lat, h``; optional ``role, sigma``) read
as they are: ``image`` is taken as ``image_id`` and ``kind`` is inferred (``gcp`` where lon/lat are given, else
``tie``).
"""
from __future__ import annotations

import os
from typing import Iterable, Mapping, Optional, Sequence

import geopandas as gpd
import numpy as np
import pandas as pd

from .atomic import atomic_output
from .errors import GCPError
from .estimation.result import ESTIMATE_LEVELS
from .outputs import check_output_path

__all__ = ["OBS_SCHEMA", "KINDS", "OUTLIER_LEVELS", "SCHEMA", "REQUIRED", "ROLES",
           "validate_observations", "read_observations", "write_observations", "gcp_view", "from_gcps",
           "from_gcp_views", "image_ids", "select_images", "flag_outliers", "make_gcps", "validate_gcps", "fill_heights",
           "to_geodataframe"]

# ----------------------------------------------------------------------------------------------------------------
# the one-image view: the GCP table schema (DESIGN.md "GCP table schema")
# ----------------------------------------------------------------------------------------------------------------
REQUIRED = ("lon", "lat", "sample", "line")
SCHEMA = ("id", "lon", "lat", "h", "sample", "line", "role", "sigma")
ROLES = ("control", "check")


def make_gcps(lon, lat, h, sample, line, *, ids: Optional[Sequence] = None, role="control", sigma=1.0, **extra):
    """Build a GCP table (a DataFrame in the GCP schema) from arrays (extra keyword arrays become columns)."""
    lon = np.asarray(lon, dtype=float).ravel()
    n = lon.size
    data = {
        "id": [str(i) for i in (ids if ids is not None else range(1, n + 1))],
        "lon": lon,
        "lat": np.asarray(lat, dtype=float).ravel(),
        "h": np.broadcast_to(np.asarray(h, dtype=float), (n,)).copy() if np.ndim(h) == 0 else
        np.asarray(h, dtype=float).ravel(),
        "sample": np.asarray(sample, dtype=float).ravel(),
        "line": np.asarray(line, dtype=float).ravel(),
        "role": np.broadcast_to(np.asarray(role, dtype=object), (n,)).copy(),
        "sigma": np.broadcast_to(np.asarray(sigma, dtype=float), (n,)).copy(),
    }
    for key, value in extra.items():
        data[key] = np.broadcast_to(np.asarray(value), (n,)).copy() if np.ndim(value) == 0 else np.asarray(value)
    return pd.DataFrame(data)


def to_geodataframe(table):
    """The table as a :class:`geopandas.GeoDataFrame` in EPSG:4326 with a point geometry from ``lon, lat`` (none
    where they are not finite: tie points not yet estimated), for export. GCP and observation tables are plain
    DataFrames: the geometry is built here only (public ``geopandas.points_from_xy``), so that a 1e6-point job
    does not pay for 1e6 shapely objects it never uses."""
    df = pd.DataFrame(table).drop(columns="geometry", errors="ignore")
    lon, lat = df["lon"].to_numpy(float), df["lat"].to_numpy(float)
    geometry = gpd.points_from_xy(lon, lat, crs="EPSG:4326")
    missing = ~(np.isfinite(lon) & np.isfinite(lat))
    if missing.any():
        geometry[missing] = None
    return gpd.GeoDataFrame(df, geometry=geometry, crs="EPSG:4326")


def fill_heights(gcps, dem, *, source: str = "GCPs"):
    """Take missing (NaN / absent) heights from ``dem`` (ellipsoidal; geoid-aware through the DEM).

    Raises :class:`GCPError` if the DEM has no value under a GCP that needs one.
    """
    df = gcps.copy()
    if "h" not in df.columns:
        df["h"] = np.nan
    h = np.asarray(df["h"], dtype=float)
    miss = ~np.isfinite(h)
    if miss.any():
        if dem is None:
            raise GCPError(f"{source}: {int(miss.sum())} GCP(s) without height; give a DEM (--dem) to take them from")
        try:
            fill = np.asarray(dem.height(np.asarray(df["lon"], float)[miss], np.asarray(df["lat"], float)[miss]),
                              dtype=float)
        except GCPError:
            raise
        except Exception as exc:  # DEMError and friends: keep one line
            raise GCPError(f"{source}: cannot take GCP heights from the DEM: {str(exc).splitlines()[0]}") from None
        if not np.all(np.isfinite(fill)):
            raise GCPError(f"{source}: the DEM has no height under {int((~np.isfinite(fill)).sum())} GCP(s); "
                           "give their heights or a DEM that covers them")
        h = h.copy()
        h[miss] = fill
        df["h"] = h
    return df


def _clean_roles(role):
    """The role column filled (``control``), as text, stripped and lower-cased: on its distinct values when they
    are all text (one GCP table of 1e6 rows has one or two roles), else value by value."""
    codes, uniques = pd.factorize(role, use_na_sentinel=True)
    if all(type(u) is str for u in uniques):
        clean = np.array([u.strip().lower() for u in uniques] + ["control"], dtype=object)
        return pd.Series(clean[codes], index=role.index, name=role.name)
    return role.fillna("control").astype(str).str.strip().str.lower()


def validate_gcps(gdf, *, source: str = "GCPs", dem=None, need_height: bool = True):
    """Check and complete a GCP table: required columns, finite numbers, ids, roles, sigma, heights.

    A missing or NaN height is taken from ``dem`` (a :class:`gdal_gf4cal.dem.DEM`, geoid-aware) when given,
    else it is an error. Returns a new DataFrame following the schema (:func:`to_geodataframe` for a geometry).
    """
    df = pd.DataFrame(gdf).copy()
    df.columns = [str(c).strip() for c in df.columns]
    lower = {c.lower(): c for c in df.columns}
    df = df.rename(columns={lower[k]: k for k in ("id", "lon", "lat", "h", "sample", "line", "role", "sigma")
                            if k in lower and lower[k] != k})
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise GCPError(f"{source}: missing column(s) {', '.join(missing)}; expected "
                       "id,lon,lat,h,sample,line[,role][,sigma]")
    if len(df) == 0:
        raise GCPError(f"{source}: no GCPs")
    for c in ("lon", "lat", "sample", "line") + (("h",) if "h" in df.columns else ()):
        values = pd.to_numeric(df[c], errors="coerce").astype(float)
        bad = ~np.isfinite(values.to_numpy())
        if c != "h" and bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise GCPError(f"{source}: column {c} has a missing, non-numeric or infinite value (row {row + 1})")
        df[c] = values
    if "id" not in df.columns:
        df["id"] = [str(i) for i in range(1, len(df) + 1)]
    df["id"] = df["id"].astype(str)
    if df["id"].duplicated().any():
        raise GCPError(f"{source}: duplicate GCP id {df['id'][df['id'].duplicated()].iloc[0]!r}")
    if "h" not in df.columns:
        df["h"] = np.nan
    if not np.all(np.isfinite(df["h"].to_numpy())):
        if dem is None:
            if need_height:
                raise GCPError(f"{source}: {int((~np.isfinite(df['h'].to_numpy())).sum())} GCP(s) without height; "
                               "give a DEM (--dem) to take heights from it")
        else:
            # Errors when the DEM has no value under a GCP (never a NaN height from a nodata="nan" DEM).
            df = fill_heights(df, dem, source=source)
    if ((df["lat"].abs() > 90) | (df["lon"].abs() > 360)).any():
        swapped = bool((df["lon"].abs() <= 90).all() and (df["lat"].abs() <= 360).all())
        raise GCPError(f"{source}: lon/lat out of range; GCP ground coordinates must be WGS84 degrees "
                       + ("(lon and lat look swapped: swap the columns)" if swapped else
                          "(reproject the layer to EPSG:4326 or give its CRS)"))
    if "role" not in df.columns:
        df["role"] = "control"
    df["role"] = _clean_roles(df["role"])
    bad = ~df["role"].isin(ROLES)
    if bad.any():
        raise GCPError(f"{source}: role {df['role'][bad].iloc[0]!r} is not 'control' or 'check'")
    if "sigma" not in df.columns:
        df["sigma"] = 1.0
    df["sigma"] = pd.to_numeric(df["sigma"], errors="coerce").fillna(1.0).astype(float)
    if (df["sigma"] <= 0).any():
        raise GCPError(f"{source}: sigma must be positive")
    if "geometry" in df.columns:
        df = df.drop(columns="geometry")
    ordered = list(SCHEMA) + [c for c in df.columns if c not in SCHEMA]
    return df[ordered].reset_index(drop=True)


# ----------------------------------------------------------------------------------------------------------------
# the observation table
# ----------------------------------------------------------------------------------------------------------------
OBS_SCHEMA = ("point_id", "image_id", "kind", "sample", "line", "sigma", "role", "lon", "lat", "h")
KINDS = ("gcp", "tie")
#: Filter levels in the order they run (cumulative): the matcher's filters, then the estimate's levels
#: (:data:`gdal_gf4cal.estimation.ESTIMATE_LEVELS`: high-breakdown start, data snooping, IRLS rejection).
OUTLIER_LEVELS = ("match",) + ESTIMATE_LEVELS
_ALIASES = {"image": "image_id", "img": "image_id", "image_name": "image_id", "id": "point_id",
            "point": "point_id", "col": "sample", "row": "line", "height": "h"}


def _basename_key(name) -> str:
    """An image's key for matching ids to paths: the file name without folder and extension, case-folded."""
    base = os.path.basename(str(name).replace("\\", "/"))
    return os.path.splitext(base)[0].casefold()


def validate_observations(table, *, source: str = "observations", dem=None, need_height: bool = True,
                          return_codes: bool = False):
    """Check and complete an observation table (module docstring); returns a new DataFrame (with
    ``return_codes``: and ``{"point_id": codes, "image_id": codes}``, the ids' ``pd.factorize`` codes).

    Parameters
    ----------
    table : DataFrame with at least ``point_id, image_id, sample, line`` (``image`` and ``id`` are accepted as the
        names of ``image_id`` and ``point_id``); ``lon, lat`` (and ``h``) on GCP rows.
    dem : DEM to take missing GCP heights from (geoid-aware); without one a GCP without height is an error when
        ``need_height`` is true.

    Raises
    ------
    GCPError
        One line naming the problem and the fix: missing columns, NaN or non-numeric values, unknown kind or role,
        non-positive sigma, duplicate ``(point_id, image_id)``, a tie point seen by only one image, a GCP whose
        ground coordinates differ between its rows, a GCP without lon/lat.
    """
    df = _renamed_observation_columns(table, source)
    if len(df) == 0:
        raise GCPError(f"{source}: no observations")
    codes = _check_ids_and_numbers(df, source)
    gcp = _checked_kinds(df, source)
    _check_points(df, gcp, source, codes)
    if gcp.any():
        _check_gcp_ground(df, gcp, dem, need_height, source)
    _check_roles_sigma_flags(df, source)
    df.index = pd.RangeIndex(len(df))                          # columns already in schema order: no copy
    return (df, codes) if return_codes else df


def _renamed_observation_columns(table, source):
    """A copy of the table without geometry, its column names stripped and brought to the schema's (any case,
    aliases such as ``image``, ``id``, ``col``/``row``), the required columns checked."""
    df = pd.DataFrame(table)
    if "geometry" in df.columns:
        df = df.drop(columns="geometry")
    df = df.set_axis([str(c).strip() for c in df.columns], axis=1, copy=False)
    lower = {c.lower(): c for c in df.columns}
    rename = {lower[k]: k for k in OBS_SCHEMA + ("outlier", "outlier_level") if k in lower and lower[k] != k}
    for alias, name in _ALIASES.items():
        if alias in lower and name not in df.columns and name not in rename.values():
            rename[lower[alias]] = name
    df = df.rename(columns=rename)
    missing = [c for c in ("point_id", "image_id", "sample", "line") if c not in df.columns]
    if missing:
        raise GCPError(f"{source}: missing column(s) {', '.join(missing)}; expected "
                       "point_id,image,sample,line[,lon,lat,h][,role][,sigma]")
    extra = [c for c in df.columns if c not in OBS_SCHEMA]
    return df.reindex(columns=list(OBS_SCHEMA) + extra, copy=True)  # the one copy; absent columns NaN, filled below


def _clean_uniques(col: pd.Series, lower: bool = False):
    """``(codes, clean)``: the rows' ``pd.factorize`` codes (-1 where missing) and the distinct values as stripped
    (and lower-cased) text: every check of a text column made once per distinct value, not per row."""
    if pd.api.types.infer_dtype(col, skipna=True) != "string":
        col = col.where(col.isna(), col.astype(str))           # numbers as their text, as before (1 and 1.0 differ)
    codes, uniq = pd.factorize(col.to_numpy(), use_na_sentinel=True)
    clean = pd.Index(uniq).astype(str).str.strip()
    return codes, (clean.str.lower() if lower else clean).to_numpy(object)


def _clean_text_codes(col: pd.Series, lower: bool = False):
    """``(text, codes, blank)``: the column as stripped (and lower-cased) text, NaN kept; the rows' codes of the
    cleaned values in order of first appearance (-1 where missing); the rows missing or blank once cleaned."""
    codes, clean = _clean_uniques(col, lower)
    out = np.append(clean, np.nan)[codes]                      # code -1 (missing): the NaN appended
    merged = np.append(pd.factorize(clean)[0], -1)[codes]      # values equal once cleaned: one code
    blank = np.append(clean == "", True)[codes]
    return pd.Series(out, index=col.index, name=col.name), merged, blank


def _check_ids_and_numbers(df, source) -> dict:
    """Ids as stripped text, never empty; coordinates numeric (in place), image positions finite. Returns the ids'
    codes (``{column: pd.factorize codes}``)."""
    codes = {}
    for c in ("point_id", "image_id"):
        text, codes[c], bad = _clean_text_codes(df[c])
        if bad.any():
            raise GCPError(f"{source}: column {c} is empty on row {int(np.flatnonzero(bad)[0]) + 1}; "
                           "give every observation a point id and an image")
        df[c] = text
    for c in ("sample", "line", "lon", "lat", "h"):
        if c not in df.columns:
            df[c] = np.nan
        values = pd.to_numeric(df[c], errors="coerce").astype(float)
        if c in ("sample", "line"):
            bad = ~np.isfinite(values.to_numpy())
            if bad.any():
                raise GCPError(f"{source}: column {c} has a missing, non-numeric or infinite value "
                               f"(row {int(np.flatnonzero(bad)[0]) + 1})")
        df[c] = values
    return codes


def _checked_kinds(df, source) -> np.ndarray:
    """The ``kind`` column filled (in place; blank or absent: ``gcp`` where lon/lat are given, else ``tie``) and
    checked; returns the GCP rows' mask."""
    has_ground = np.isfinite(df["lon"].to_numpy()) & np.isfinite(df["lat"].to_numpy())
    gcp = has_ground.copy()                                     # absent or blank kind: inferred
    if "kind" in df.columns:
        codes, clean = _clean_uniques(df["kind"], lower=True)
        bad = np.append(~np.isin(clean, KINDS + ("",)), False)[codes]
        if bad.any():
            raise GCPError(f"{source}: kind {clean[codes[np.flatnonzero(bad)[0]]]!r} is not 'gcp' or 'tie'")
        given = np.append(clean != "", False)[codes]
        gcp[given] = np.append(clean == "gcp", False)[codes][given]
    df["kind"] = np.where(gcp, "gcp", "tie").astype(object)
    if (gcp & ~has_ground).any():
        row = int(np.flatnonzero(gcp & ~has_ground)[0])
        raise GCPError(f"{source}: GCP {df['point_id'].iloc[row]!r} has no lon/lat (row {row + 1}); give its ground "
                       "coordinates or make it a tie point")
    if ((df["lat"].abs() > 90) | (df["lon"].abs() > 360)).any():
        raise GCPError(f"{source}: lon/lat out of range; ground coordinates must be WGS84 degrees")
    return gcp


def _check_points(df, gcp, source, codes) -> None:
    """One observation per point and image, one kind per point, tie points seen by two images or more (``codes``:
    the ids' from :func:`_check_ids_and_numbers`)."""
    point, image = codes["point_id"], codes["image_id"]
    key = point.astype(np.int64) * max(int(image.max()) + 1, 1) + image
    _, first, count = np.unique(key, return_index=True, return_counts=True)
    if (count > 1).any():
        dup = np.ones(len(df), bool)
        dup[first] = False
        r = df.iloc[int(np.flatnonzero(dup)[0])]
        raise GCPError(f"{source}: point {r['point_id']!r} is measured twice in image {r['image_id']!r}; "
                       "keep one observation per point and image")
    n_pts = int(point.max()) + 1
    n_gcp = np.bincount(point, weights=gcp.astype(float), minlength=n_pts)
    n_images = np.bincount(point, minlength=n_pts)
    mixed = (n_gcp > 0) & (n_gcp < n_images)
    if mixed.any():
        row = int(np.flatnonzero(mixed[point])[0])
        raise GCPError(f"{source}: point {df['point_id'].iloc[row]!r} is both a GCP "
                       "and a tie point; give it lon/lat on every row or on none")
    lone_tie = (~gcp) & (n_images[point] < 2)
    if lone_tie.any():
        raise GCPError(f"{source}: tie point {df['point_id'].iloc[int(np.flatnonzero(lone_tie)[0])]!r} is seen by "
                       "only one image; a tie point needs two or more (drop it or give its lon/lat to make it a GCP)")


def _check_gcp_ground(df, gcp, dem, need_height, source) -> None:
    """One set of ground coordinates per GCP; missing heights from the DEM (in place) or an error."""
    grouped = df[gcp].groupby("point_id", sort=False)[["lon", "lat", "h"]]
    spread = (grouped.max() - grouped.min()).fillna(0.0)       # NaN heights are filled below, not compared
    incons = (spread.to_numpy() > 0).any(axis=1)
    if incons.any():
        raise GCPError(f"{source}: GCP {spread.index[incons][0]!r} has different lon/lat/h on its rows; "
                       "one ground point has one set of coordinates")
    h = df["h"].to_numpy()
    if (gcp & ~np.isfinite(h)).any():
        if dem is not None:
            filled = fill_heights(df[gcp], dem, source=source)
            h = h.copy()
            h[gcp] = filled["h"].to_numpy(float)
            df["h"] = h
        elif need_height:
            n = int(df.loc[gcp & ~np.isfinite(h), "point_id"].nunique())
            raise GCPError(f"{source}: {n} GCP(s) without height; give h or a DEM (--dem) to take heights from")


def _check_roles_sigma_flags(df, source) -> None:
    """Roles (filled ``control``), positive sigmas (filled 1 px) and the outlier flags as booleans, in place."""
    if "role" not in df.columns:
        df["role"] = "control"
    codes, clean = _clean_uniques(df["role"], lower=True)
    clean = np.append(np.where(clean == "", "control", clean).astype(object), "control")   # missing: control
    bad = ~np.isin(clean, ROLES)
    if bad.any():
        raise GCPError(f"{source}: role {clean[np.flatnonzero(bad)[0]]!r} is not 'control' or 'check'")
    df["role"] = clean[codes]
    if "sigma" not in df.columns:
        df["sigma"] = 1.0
    df["sigma"] = pd.to_numeric(df["sigma"], errors="coerce").fillna(1.0).astype(float)
    if not (df["sigma"] > 0).all():
        raise GCPError(f"{source}: sigma must be positive (px)")
    level_cols = [c for c in df.columns if c.startswith("outlier_") and c != "outlier_level"]
    for c in level_cols + (["outlier"] if "outlier" in df.columns else []):
        df[c] = _as_bool(df[c], c, source)
    if "outlier_level" in df.columns:
        df["outlier_level"] = df["outlier_level"].fillna("").astype(str)


def _as_bool(col, name, source):
    if col.dtype == bool:
        return col
    text = col.astype(str).str.strip().str.lower()
    mapping = {"true": True, "1": True, "1.0": True, "yes": True, "false": False, "0": False, "0.0": False,
               "no": False, "": False, "nan": False, "none": False}
    out = text.map(mapping)
    if out.isna().any():
        raise GCPError(f"{source}: column {name} must be true/false, not {col[out.isna()].iloc[0]!r}")
    return pd.Series(out.to_numpy(bool), index=col.index, name=name)


def image_ids(table) -> list:
    """The image ids of a table, in order of first appearance."""
    return list(dict.fromkeys(table["image_id"].astype(str)))


def _resolve_image(table, image_id, source="observations") -> str:
    ids = image_ids(table)
    if image_id is None:
        if len(ids) == 1:
            return ids[0]
        raise GCPError(f"{source}: observations of {len(ids)} images ({', '.join(ids[:5])}"
                       f"{', ...' if len(ids) > 5 else ''}); say which image")
    image_id = str(image_id)
    if image_id in ids:
        return image_id
    key = _basename_key(image_id)
    match = [i for i in ids if _basename_key(i) == key]
    if len(match) == 1:
        return match[0]
    raise GCPError(f"{source}: no observations in image {image_id!r}; images in the table: "
                   f"{', '.join(ids[:8])}{', ...' if len(ids) > 8 else ''}")


def gcp_view(table, image_id: Optional[str] = None, *, kinds: Iterable[str] = ("gcp",)):
    """The GCP table (one-image view) of ``image_id``: a DataFrame in the GCP schema, extra columns kept.

    ``image_id`` may be the id itself or a path/file name whose stem matches one id; it may be omitted when the
    table holds one image. Only rows of ``kinds`` are returned (tie points have no ground coordinates until they
    are estimated; pass ``kinds=("gcp", "tie")`` once they are). Inverse of :func:`from_gcps`.
    """
    image_id = _resolve_image(table, image_id)
    kinds = tuple(kinds)
    rows = table[(table["image_id"].astype(str) == image_id) & table["kind"].isin(kinds)]
    if len(rows) == 0:
        raise GCPError(f"image {image_id!r} has no {' or '.join(kinds)} observations")
    if not (np.isfinite(rows["lon"].to_numpy(float)).all() and np.isfinite(rows["lat"].to_numpy(float)).all()):
        raise GCPError(f"image {image_id!r}: some points have no ground coordinates yet; estimate them first")
    df = rows.drop(columns=[c for c in ("image_id", "kind", "geometry") if c in rows.columns])
    df = df.rename(columns={"point_id": "id"})
    ordered = list(SCHEMA) + [c for c in df.columns if c not in SCHEMA]
    return df[ordered].reset_index(drop=True)


def from_gcps(gdf, image_id: str, *, kind: str = "gcp"):
    """The observation table of one image's GCP table (inverse of :func:`gcp_view`; every column kept).

    ``image_id`` is the image's id (its file name, as in the ``OBS`` files). The GCP table is validated first
    (:func:`validate_gcps`, heights may be NaN).
    """
    if kind not in KINDS:
        raise GCPError(f"kind must be 'gcp' or 'tie', not {kind!r}")
    g = validate_gcps(gdf, need_height=False)
    df = pd.DataFrame(g).rename(columns={"id": "point_id"})
    df.insert(1, "image_id", str(image_id))
    df.insert(2, "kind", kind)
    ordered = list(OBS_SCHEMA) + [c for c in df.columns if c not in OBS_SCHEMA]
    return df[ordered].reset_index(drop=True)


def from_gcp_views(views: Mapping[str, object], *, validate: bool = True):
    """One table from ``{image_id: GCP table}`` (e.g. :func:`gdal_gf4cal.simulate.simulate_gcps`'s result).

    GCP ids shared between images become the same ``point_id`` (one ground point, several observations).
    """
    if not views:
        raise GCPError("no GCP tables to combine")
    table = pd.concat([from_gcps(g, image_id) for image_id, g in views.items()], ignore_index=True)
    return validate_observations(table, need_height=False) if validate else table


def flag_outliers(table, mask, level: str):
    """Flag rows as outliers at filter ``level`` (cumulative levels, as AROSICS's L1/L2/L3 outliers).

    Sets ``outlier_<level>`` to ``mask`` (OR-ed with any earlier flag of that level), ``outlier`` to the OR of every
    level and ``outlier_level`` to the first level (in :data:`OUTLIER_LEVELS` order, then in order of appearance)
    that flagged the row. Returns a new table.
    """
    out = table.copy()
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (len(out),):
        raise GCPError(f"outlier mask has {mask.size} values for {len(out)} observations")
    col = f"outlier_{level}"
    out[col] = (out[col].to_numpy(bool) | mask) if col in out.columns else mask
    levels = [c[len("outlier_"):] for c in out.columns if c.startswith("outlier_") and c != "outlier_level"]
    levels.sort(key=lambda lv: (OUTLIER_LEVELS.index(lv) if lv in OUTLIER_LEVELS else len(OUTLIER_LEVELS)))
    first = np.full(len(out), "", dtype=object)
    for lv in reversed(levels):
        first = np.where(out[f"outlier_{lv}"].to_numpy(bool), lv, first)
    out["outlier"] = first != ""
    out["outlier_level"] = first.astype(object)
    return out


# ----------------------------------------------------------------------------------------------------------------
# files
# ----------------------------------------------------------------------------------------------------------------
def read_observations(path, *, images: Optional[Iterable[str]] = None, dem=None, need_height: bool = True,
                      layer: Optional[str] = None):
    """Read an observation table from CSV (header required) or GeoPackage and validate it.

    Parameters
    ----------
    images : keep only these images (ids, file names or paths: matched on the file stem when not exact); tie
        points left with a single observation are dropped. Every image named must have observations.
    dem, need_height : see :func:`validate_observations`.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise GCPError(f"observation file not found: {path}")
    ext = os.path.splitext(path)[1].lower()
    try:
        if ext in (".csv", ".txt"):
            text = {c: str for c in ("point_id", "image_id", "image", "id", "kind", "role", "outlier_level")}
            df = pd.read_csv(path, skipinitialspace=True, comment="#", dtype=text,   # ids keep leading zeros
                             float_precision="round_trip")                 # floats read back identical
        elif ext in (".gpkg",):
            df = gpd.read_file(path, layer=layer) if layer else gpd.read_file(path)
            df = pd.DataFrame(df.drop(columns="geometry", errors="ignore"))
        else:
            raise GCPError(f"{path}: observation files are .csv or .gpkg")
    except GCPError:
        raise
    except Exception as exc:  # pandas/pyogrio raise many types; report one line
        raise GCPError(f"cannot read observations from {path}: {str(exc).splitlines()[0]}") from None
    table = validate_observations(df, source=path, dem=dem, need_height=need_height)
    if images is not None:
        table = select_images(table, images, source=path)
    return table


def select_images(table, images: Iterable[str], *, source: str = "observations"):
    """Keep the observations of ``images`` (ids or paths, see :func:`read_observations`); drop lone tie points."""
    keep_ids = [_resolve_image(table, im, source) for im in images]
    out = table[table["image_id"].isin(keep_ids)]
    n = out.groupby("point_id", sort=False)["image_id"].transform("size").to_numpy()
    out = out[(out["kind"] == "gcp").to_numpy() | (n >= 2)]
    return out.reset_index(drop=True)


def write_observations(table, path, *, overwrite: bool = False, layer: str = "observations") -> str:
    """Write an observation table to ``.csv`` or ``.gpkg`` (by extension), atomically.

    Every column is written; floats in CSV use the shortest repr, so they read back identical. The GeoPackage
    layer has a point geometry where lon/lat are known (none for tie points not yet estimated). Raises
    :class:`~gdal_gf4cal.errors.InputOverwriteError` if ``path`` exists and ``overwrite`` is false.
    """
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".csv", ".gpkg"):
        raise GCPError(f"cannot write observations as {ext!r}; use .csv or .gpkg")
    check_output_path(path, overwrite=overwrite)
    table = validate_observations(table, need_height=False)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with atomic_output(path) as tmp:
        if ext == ".csv":
            table.to_csv(tmp, index=False)
        else:
            to_geodataframe(table).to_file(tmp, layer=layer, driver="GPKG")
    return path
