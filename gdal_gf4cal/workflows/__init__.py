"""The workflows layer: every file-to-file job, called by the CLI and the QGIS algorithms and nothing else
(DESIGN.md "Workflows"). Each job takes paths and options, reads its inputs, calls the engine, writes every
output under one :class:`~gdal_gf4cal.outputs.OutputSet` (all or nothing, never over an input, never over an
existing file without ``overwrite=True``) and returns its report dict (with ``warnings``: a list of one-line str).
"""
from __future__ import annotations

from .apply import apply_block_calibration, apply_calibration
from .assess import assess_accuracy
from .block import block_adjust
from .bundle import bundle_adjust
from .calibrate import calibrate_lookangle_files
from .collect import collect_gcps_file
from .experiment import run_experiment
from .intersect import intersect_files, read_tie_points
from .ortho import orthorectify
from .panms import register_pan_ms
from .refine import output_kind, refine_rpc, write_refined_rpc
from .simulate import simulate_scene

__all__ = ["apply_block_calibration", "apply_calibration", "assess_accuracy", "block_adjust", "bundle_adjust", "calibrate_lookangle_files", "collect_gcps_file",
           "run_experiment", "intersect_files", "read_tie_points", "orthorectify", "register_pan_ms", "output_kind", "refine_rpc",
           "write_refined_rpc", "simulate_scene"]
