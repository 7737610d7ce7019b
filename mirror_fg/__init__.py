"""mirror_fg: camera-to-base calibration through multiple planar mirrors (Hesch et al., ECCV 2010).

Frames: {B} base, {C} camera (OpenCV axes). ``T_cam_base = (R, t)`` with ``Cp = R @ Bp + t`` (metres);
covariances are ``[dtheta (rad), dt (m)]`` with ``R_true = Exp(dtheta) @ R_est`` (docs/formats.md).

Layout: ``core`` (errors, transforms, camera, geometry; numpy only), ``io`` (file formats, one owner
each), ``solver`` (analytical solution, factor graph, LM, marginals, iSAM2), ``vision`` (detection,
tracking), ``tools`` (simulation, Cramer-Rao bounds and planning, reports, Monte Carlo).
"""
import logging as _logging
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("mirror-fg")
except PackageNotFoundError:  # a source tree that is not installed
    __version__ = "0+unknown"

# Library messages go to the "mirror_fg" logger; applications attach their own handlers.
_logging.getLogger("mirror_fg").addHandler(_logging.NullHandler())

from mirror_fg.core.errors import DatasetError, MirrorFgError, SolveError
from mirror_fg.core.transform import Transform
from mirror_fg.core.camera import Camera
from mirror_fg.io.dataset import Dataset, Image, dataset_from_dict, load_dataset, save_dataset
from mirror_fg.io.result import load_result, write_result
from mirror_fg.solver.analytic import AnalyticSolution, solve_analytic
from mirror_fg.solver.calibration import Calibration
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.initial import initial_estimate
from mirror_fg.solver.incremental import IncrementalCalibrator, calibrate_incremental

__all__ = [
    "__version__",
    "AnalyticSolution",
    "Calibration",
    "Camera",
    "Dataset",
    "DatasetError",
    "Image",
    "IncrementalCalibrator",
    "MirrorFgError",
    "SolveError",
    "Transform",
    "calibrate",
    "calibrate_incremental",
    "dataset_from_dict",
    "initial_estimate",
    "load_dataset",
    "load_result",
    "save_dataset",
    "solve_analytic",
    "write_result",
]
