"""gdal_gf4cal: geometric calibration of optical satellite images from their RPC, a DEM and control points.

See DESIGN.md for the module map and ../shared/METHODS.md (METHODS §n in docstrings) for the equations.
"""
from __future__ import annotations

from .errors import (
    CancelledError,
    ConvergenceError,
    DEMError,
    DegenerateGeometryError,
    GCPError,
    Gf4calError,
    InputOverwriteError,
    RPCFormatError,
)

from .rpc import RPCModel
from .rpc_io import read_rpc_metadata, write_rpc_vrt
from .dem import DEM
from .camera import LookAngleModel
from .gcp import make_gcps, read_gcps, write_gcps
from .rpc_fit import FitReport, fit_rpc, fit_rpc_from_model
from .lookangle import LookAngleCalibration, calibrate_lookangle, compare_lookangle, recalibrate_rpc
from .compensation import (CompensatedRPC, CompensationModel, CompensationResult, apply_compensation,
                           fit_compensation)
from .intersection import IntersectionResult, intersect
from .matching import collect_gcps
from .workflows import (apply_calibration, assess_accuracy, calibrate_lookangle_files, collect_gcps_file,
                        intersect_files, read_tie_points, refine_rpc, run_experiment, simulate_scene,
                        write_refined_rpc)

__version__ = "0.1.0"

__all__ = [
    "CancelledError", "ConvergenceError", "DEMError", "DegenerateGeometryError", "GCPError", "Gf4calError",
    "InputOverwriteError", "RPCFormatError", "__version__",
    "RPCModel", "read_rpc_metadata", "write_rpc_vrt", "DEM", "LookAngleModel", "make_gcps", "read_gcps", "write_gcps",
    "FitReport", "fit_rpc", "fit_rpc_from_model",
    "LookAngleCalibration", "calibrate_lookangle", "compare_lookangle", "recalibrate_rpc",
    "CompensatedRPC", "CompensationModel", "CompensationResult", "apply_compensation", "fit_compensation",
    "refine_rpc", "IntersectionResult", "intersect",
    "collect_gcps",
    "apply_calibration", "assess_accuracy", "calibrate_lookangle_files", "collect_gcps_file", "intersect_files",
    "read_tie_points", "run_experiment", "simulate_scene", "write_refined_rpc",
]
