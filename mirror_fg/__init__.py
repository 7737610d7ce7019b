"""mirror_fg: camera-to-base calibration through multiple planar mirrors (Hesch et al., ECCV 2010).

Frames: {B} base, {C} camera (OpenCV axes). ``T_cam_base = (R, t)`` with ``Cp = R @ Bp + t`` (metres);
covariances are ``[dtheta (rad), dt (m)]`` with ``R_true = Exp(dtheta) @ R_est`` (docs/formats.md).

Layout: ``core`` (errors, transforms, camera, geometry; numpy only), ``io`` (file formats, one owner
each), ``solver`` (analytical solution, factor graph, LM, marginals, iSAM2), ``vision`` (detection,
tracking), ``tools`` (simulation, Cramer-Rao bounds and planning, reports, Monte Carlo).

The public names below are imported on first use (PEP 562), so ``import mirror_fg`` (and
``mirror-fg --version``) does not load GTSAM, OpenCV, SciPy or the plotting and Dask stacks until a
name that needs them is touched.
"""
from __future__ import annotations

import importlib as _importlib
import logging as _logging
import os as _os
from typing import TYPE_CHECKING as _TYPE_CHECKING, Any as _Any

# Library messages go to the "mirror_fg" logger; applications attach their own handlers.
_logging.getLogger("mirror_fg").addHandler(_logging.NullHandler())

from mirror_fg import _moved

_moved.install()  # the old import paths of moved modules, for one release

#: Each public name and the module it lives in (imported on first access).
_PUBLIC = {
    "AnalyticSolution": "mirror_fg.solver.start.analytic",
    "Calibration": "mirror_fg.solver.result.calibration",
    "Camera": "mirror_fg.core.camera",
    "Dataset": "mirror_fg.data.dataset",
    "DatasetError": "mirror_fg.core.errors",
    "Image": "mirror_fg.data.dataset",
    "IncrementalCalibrator": "mirror_fg.solver.incremental.calibrator",
    "MirrorFgError": "mirror_fg.core.errors",
    "Registry": "mirror_fg.registry.store",
    "SolveError": "mirror_fg.core.errors",
    "SolveOptions": "mirror_fg.solver.options",
    "IncrementalOptions": "mirror_fg.solver.options",
    "Transform": "mirror_fg.core.transform",
    "calibrate": "mirror_fg.solver.calibrate",
    "calibrate_incremental": "mirror_fg.solver.incremental.calibrator",
    "dataset_from_dict": "mirror_fg.io.dataset",
    "initial_estimate": "mirror_fg.solver.start.initial",
    "judge": "mirror_fg.report.verdict",
    "load_dataset": "mirror_fg.io.dataset",
    "load_result": "mirror_fg.io.result",
    "save_dataset": "mirror_fg.io.dataset",
    "solve_analytic": "mirror_fg.solver.start.analytic",
    "write_result": "mirror_fg.io.result",
}

__all__ = sorted(["__version__", "load_capture", *_PUBLIC])


def load_capture(path: str | _os.PathLike[str], progress: bool = False) -> Dataset:
    """Read a ``mirror-fg/capture@1`` file (YAML or JSON) and detect its target in every image or video
    frame: the :class:`Dataset` that ``mirror-fg detect`` would write (``progress``: a bar on stderr).

    Raises DatasetError (one line) on an invalid capture or when no image is kept. The per-image
    detection reports and tracks are in ``mirror_fg.vision.detect.detect_capture``.
    """
    from mirror_fg.io.capture import load_capture as read_capture
    from mirror_fg.vision.detect import detect_capture

    dataset, _reports = detect_capture(read_capture(path), progress=progress)
    return dataset


def _package_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("mirror-fg")
    except PackageNotFoundError:  # a source tree that is not installed
        return "0+unknown"


def __getattr__(name: str) -> _Any:
    if name == "__version__":
        value: _Any = _package_version()
    elif name in _PUBLIC:
        value = getattr(_importlib.import_module(_PUBLIC[name]), name)
    else:
        raise AttributeError(f"module 'mirror_fg' has no attribute {name!r}")
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return list(__all__)


if _TYPE_CHECKING:  # the names as static analysers and IDEs see them
    from mirror_fg.core.camera import Camera  # noqa: F401 - re-exported
    from mirror_fg.core.errors import DatasetError, MirrorFgError, SolveError  # noqa: F401 - re-exported
    from mirror_fg.core.transform import Transform  # noqa: F401 - re-exported
    from mirror_fg.io.dataset import dataset_from_dict, load_dataset, save_dataset  # noqa: F401 - re-exported
    from mirror_fg.data import Dataset, Image  # noqa: F401 - re-exported
    from mirror_fg.io.result import load_result, write_result  # noqa: F401 - re-exported
    from mirror_fg.registry.store import Registry  # noqa: F401 - re-exported
    from mirror_fg.solver.start.analytic import AnalyticSolution, solve_analytic  # noqa: F401 - re-exported
    from mirror_fg.solver.calibrate import calibrate  # noqa: F401 - re-exported
    from mirror_fg.solver.result.calibration import Calibration  # noqa: F401 - re-exported
    from mirror_fg.solver.incremental.calibrator import IncrementalCalibrator, calibrate_incremental  # noqa: F401 - re-exported
    from mirror_fg.solver.start.initial import initial_estimate  # noqa: F401 - re-exported
    from mirror_fg.solver.options import IncrementalOptions, SolveOptions  # noqa: F401 - re-exported
    from mirror_fg.report.verdict import judge  # noqa: F401 - re-exported

    __version__: str
