"""Exceptions of gdal_gf4cal.

Every error derives from :class:`Gf4calError` *and* from the builtin it resembles, so callers can catch either.
Messages say what was wrong and what to do; the CLI and the QGIS provider show them as one line.
"""
from __future__ import annotations


class Gf4calError(Exception):
    """Base class of every error raised by gdal_gf4cal."""


class RPCFormatError(Gf4calError, ValueError):
    """An RPC is missing, incomplete or malformed."""


class DEMError(Gf4calError, OSError):
    """A DEM cannot be read, or a point falls outside it / on no-data."""


class GCPError(Gf4calError, ValueError):
    """A GCP set is unreadable, incomplete, too small or inconsistent."""


class DegenerateGeometryError(Gf4calError, ValueError):
    """Observations leave a model unconstrained (collinear / clustered points, too few points)."""


class ConvergenceError(Gf4calError, ArithmeticError):
    """An iterative solution did not converge."""


class InputOverwriteError(Gf4calError, FileExistsError):
    """An output path would overwrite an input (or an existing file without ``overwrite=True``)."""


class CancelledError(Gf4calError):
    """The user cancelled a long operation through the progress callback."""
