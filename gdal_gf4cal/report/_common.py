"""Shared parts of the report writers: standard residual column names, colours, atomic temporaries and
the GCP table normalised (lon/lat, residual pairs, pixel size)."""
from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Optional, Tuple, Union

import numpy as np
from pyproj import CRS

from ..errors import GCPError
from ..geodesy import crs_transformer

STANDARD_BEFORE = ("res_sample_before", "res_line_before")
STANDARD_AFTER = ("res_sample_after", "res_line_after")
#: Residual fields of the ``gcps`` layer, in order (pixels).
RESIDUAL_FIELDS = ("res_sample_before", "res_line_before", "res_px_before",
                   "res_sample_after", "res_line_after", "res_px_after")
_BASE_FIELDS = ("id", "lon", "lat", "h", "sample", "line", "role", "sigma")
# Colours of the magnitude classes (ColorBrewer RdYlBu, reversed: small residuals blue, large red).
_RAMP = ("#2c7bb6", "#00a6ca", "#90eb9d", "#f9d057", "#f29e2e", "#d7191c")
_ROLE_COLOURS = {"control": "#1f4fd1", "check": "#18a025"}
_OUTLIER_COLOUR = "#e4002b"
_FOOTPRINT_COLOUR = "#555555"

PathLike = Union[str, os.PathLike]



# ----------------------------------------------------------------------------------------------------------------
# atomic writing
# ----------------------------------------------------------------------------------------------------------------
def _temp_path(path: Path) -> Path:
    """A fresh path in the destination folder (so that os.replace is atomic), with the same suffix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    os.unlink(tmp)  # GDAL drivers want to create the file themselves
    return Path(tmp)


def _cleanup(tmp: Path) -> None:
    for p in (tmp, Path(str(tmp) + "-wal"), Path(str(tmp) + "-shm"), Path(str(tmp) + "-journal")):
        try:
            p.unlink()
        except FileNotFoundError:
            pass




# ----------------------------------------------------------------------------------------------------------------
# the GCP table in, normalised
# ----------------------------------------------------------------------------------------------------------------
def _column(df, name) -> Optional[np.ndarray]:
    if name is None or name not in df.columns:
        return None
    return np.asarray(df[name].to_numpy(), dtype=float)


def _lonlat(df) -> Tuple[np.ndarray, np.ndarray]:
    """Ground longitude/latitude (WGS84) from the ``lon``/``lat`` columns, else from the geometry."""
    if "lon" in df.columns and "lat" in df.columns:
        return _column(df, "lon"), _column(df, "lat")
    geom = getattr(df, "geometry", None) if "geometry" in df.columns else None
    if geom is None:
        raise GCPError("the GCP table has neither lon/lat columns nor a point geometry; give the ground positions")
    if getattr(df, "crs", None) is not None and not df.crs.equals("EPSG:4326"):
        geom = geom.to_crs("EPSG:4326")
    return np.asarray(geom.x, dtype=float), np.asarray(geom.y, dtype=float)


def _residual_pair(df, names) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    if names is None:
        return None
    s, l = _column(df, names[0]), _column(df, names[1])
    if s is None or l is None:
        return None
    return s, l


def _transformer(crs):
    crs = CRS.from_user_input(crs)
    if crs.equals(CRS.from_epsg(4326)):
        return crs, None
    return crs, crs_transformer("EPSG:4326", crs)


def _pixel_size(x, y, sample, line, fallback) -> Tuple[float, float, str]:
    """Map units per pixel along the sample and line axes, from an affine fit of map (x, y) on (sample, line)."""
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(sample) & np.isfinite(line)
    if ok.sum() >= 3:
        A = np.column_stack([np.ones(ok.sum()), sample[ok], line[ok]])
        # Condition check: collinear GCPs give no pixel size along one axis.
        if np.linalg.matrix_rank(A - np.r_[0, A[:, 1:].mean(0)], tol=1e-6 * max(np.ptp(A[:, 1:]), 1.0)) == 3:
            cx, *_ = np.linalg.lstsq(A, x[ok], rcond=None)
            cy, *_ = np.linalg.lstsq(A, y[ok], rcond=None)
            ps, pl = float(np.hypot(cx[1], cy[1])), float(np.hypot(cx[2], cy[2]))
            if ps > 0 and pl > 0 and math.isfinite(ps) and math.isfinite(pl):
                return ps, pl, "affine fit of the GCPs' map positions on their image positions"
    if fallback is not None:
        ps, pl = (float(fallback), float(fallback)) if np.isscalar(fallback) else map(float, fallback)
        return ps, pl, "given pixel size"
    return 1.0, 1.0, "unknown (fewer than 3 non-collinear GCPs): 1 map unit per pixel assumed"


def _nice(v: float) -> float:
    """Round to two significant digits (a factor a reader can quote)."""
    if not math.isfinite(v) or v <= 0:
        return 1.0
    e = math.floor(math.log10(v)) - 1
    return round(v / 10 ** e) * 10 ** e


def _as_bool_array(values) -> np.ndarray:
    a = np.asarray(values)
    if a.dtype.kind == "b":
        return a
    if a.dtype.kind in "iuf":
        return np.nan_to_num(a.astype(float), nan=0.0) != 0
    return np.array([str(v).strip().lower() in ("1", "true", "yes", "t") for v in a], dtype=bool)
