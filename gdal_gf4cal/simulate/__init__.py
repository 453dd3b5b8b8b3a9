"""Rigorous sensor simulator: the test bed with known truth (METHODS §10).

``make_scene`` builds the rigorous models (a *current* and a *true* one per image) and the terrain in memory;
``write_scene`` also fits the scene RPC from the current model, draws GCPs from the true model and writes the
files. See DESIGN.md, section "Simulator API".
"""
from .cameras import PiecewiseCamera, camera_from_dict, crop_camera, shift_coefficients
from .models import Attitude, CircularOrbit, FrameModel, PushbroomModel
from .render import render_image, texture_value, write_reference_ortho
from .scene import ImageResult, SceneResult, check_grid, simulate_gcps, write_placeholder_tif, write_scene
from .sensors import SENSORS, SimImage, SimScene, SimulationError, make_scene
from .jl1 import block_observations          # registers jl1 in SENSORS
from . import gf7  # noqa: F401  (registers gf7 in SENSORS)

__all__ = [
    "Attitude", "block_observations", "CircularOrbit", "FrameModel", "ImageResult", "PiecewiseCamera", "PushbroomModel", "SENSORS",
    "SceneResult", "SimImage", "SimScene", "SimulationError", "camera_from_dict", "check_grid", "crop_camera",
    "make_scene", "render_image", "shift_coefficients", "simulate_gcps", "texture_value", "write_placeholder_tif",
    "write_reference_ortho", "write_scene",
]
