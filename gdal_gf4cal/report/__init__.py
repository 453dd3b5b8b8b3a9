"""GIS-ready outputs: residual GeoPackages with default QGIS styles, residual plots and ``report.json``.

Three writers, each atomic (temporary file in the destination folder, then :func:`os.replace`):

* :func:`write_residuals_gpkg` - a GeoPackage a GIS user can open at once: GCP points, residual vectors drawn as
  arrows coloured by magnitude, the scene footprint, and their default QGIS styles in ``layer_styles``.
* :func:`plot_residuals` - a PNG of the residual vectors in image space, before and after (like Fig. 5 of the GF4
  paper, seed 000), with a scale arrow.
* :func:`write_report_json` - a JSON report that accepts NumPy scalars/arrays (NaN becomes ``null``).

Residuals are ``measured - predicted`` in pixels, per axis (METHODS §0, §6). Image coordinates follow GDAL's pixel
convention (centre of the first pixel at 0.5, 0.5).

**Direction of the residual vectors on the map.** A residual ``(res_sample, res_line)`` is drawn from the GCP's
ground position with *sample -> east* and *line -> south* (image rows go down), each axis scaled by the mean
ground size of one pixel along that image axis (estimated from the GCPs themselves by an affine fit), times an
exaggeration factor. For a north-up image this is the residual's true ground direction; for a rotated image (e.g.
a descending or geostationary view) it is the image-space direction laid on the map, which is what one wants when
comparing residual patterns with the detector layout.

A package: :mod:`.styles` (QML/SLD), :mod:`.gpkg`, :mod:`.plot`, :mod:`.json`; it never imports
qgis, PyQt or the estimation modules (callers pass what it needs); the styles are written as QGIS QML (and OGC SLD) text.
"""
from __future__ import annotations

from ._common import PathLike, RESIDUAL_FIELDS, STANDARD_AFTER, STANDARD_BEFORE, _RAMP  # noqa: F401 (kept importable)
from .gpkg import footprint_from_rpc, write_points_layer, write_residuals_gpkg
from .json import write_report_json
from .plot import plot_residuals, plot_seams

__all__ = [
    "write_residuals_gpkg", "plot_residuals", "write_report_json", "footprint_from_rpc", "plot_seams",
    "write_points_layer",
    "RESIDUAL_FIELDS", "STANDARD_BEFORE", "STANDARD_AFTER",
]
