"""mirror_fg: camera-to-base calibration through multiple planar mirrors (Hesch et al., ECCV 2010).

Frames: {B} base, {C} camera (OpenCV axes). ``T_cam_base = (R, t)`` with ``Cp = R @ Bp + t`` (metres);
covariances are ``[dtheta (rad), dt (m)]`` with ``R_true = Exp(dtheta) @ R_est`` (docs/formats.md).
"""
from mirror_fg.core.errors import DatasetError, MirrorFgError, SolveError
from mirror_fg.solver.analytic import AnalyticSolution, solve_analytic
from mirror_fg.io.dataset import (
    Camera, Dataset, Image, dataset_from_dict, load_dataset, load_result, save_dataset, write_result,
)
from mirror_fg.solver.graph import Calibration, calibrate, initial_estimate
from mirror_fg.solver.incremental import IncrementalCalibrator

__all__ = [
    "AnalyticSolution", "Calibration", "IncrementalCalibrator", "Camera", "Dataset", "DatasetError", "Image", "SolveError",
    "calibrate", "dataset_from_dict", "initial_estimate", "load_dataset", "load_result", "save_dataset", "solve_analytic", "write_result",
]
