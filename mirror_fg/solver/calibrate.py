"""``calibrate``: the one batch pipeline (``pipeline.py``: screen -> solve -> final check -> finish),
driven by a :class:`~mirror_fg.solver.options.SolveOptions` and the problem the data are:

- the paper's tree (``tree_problem.py``): consensus (``consensus.py``) -> analytical solution (Sects.
  4-5, ``initial.py``) -> Levenberg-Marquardt (eq. 23) with its restarts (``lm.py``) -> marginals ->
  residuals -> final check (``rechecks.py``) -> what the data contradict (``consistency.py``);
- the same with intrinsics estimated (``camera.estimate``, ``pixel_problem.py``): its screen is this
  pipeline with the intrinsics fixed, its solve the joint LM with pixel factors;
- anything else (``views_solve.py``): direct views, fixed mirrors, any order of reflections, no known
  target, several cameras, by the general view model (``views.py``).

Each gives a :class:`~mirror_fg.solver.result.calibration.Calibration`, with everything left out in ``excluded``.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.dataset_fields import check_cameras_named
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.data import Dataset
from mirror_fg.solver.screen.camera_labels import check_camera_labels
from mirror_fg.solver.result.calibration import Calibration
from mirror_fg.solver.fit.dispersion import dispersion_of_calibration
from mirror_fg.solver.fit.placement_covariance import placement_covariances
from mirror_fg.solver.model.graph import InitialEstimate
from mirror_fg.solver.options import STAGES, Linearization, Progress, SolveOptions
from mirror_fg.solver.pipeline import run_pipeline
from mirror_fg.solver.batch.pixel_problem import PixelProblem
from mirror_fg.solver.screen.rechecks import MAX_RECHECKS  # noqa: F401 (public here as before)
from mirror_fg.solver.batch.tree_problem import TreeProblem
from mirror_fg.solver.batch.views_solve import calibrate_views

__all__ = ["as_dataset", "calibrate", "calibrate_with_intrinsics", "Progress", "SolveOptions", "STAGES"]

logger = logging.getLogger("mirror_fg")




def as_dataset(data: Dataset | Mapping[str, Any], what: str = "calibrate()") -> Dataset:
    """``data`` as a :class:`Dataset` (a dataset@1 dictionary is validated) that the solver can take.

    Raises DatasetError on anything else.
    """
    if isinstance(data, Mapping):
        data = dataset_from_dict(data, source="<dataset dict>")
    if not isinstance(data, Dataset):
        raise DatasetError(f"{what}: expected a mirror_fg.Dataset or a dataset@1 dictionary, got {type(data).__name__}")
    return data


def calibrate(
    dataset: Dataset | Mapping[str, Any],
    *,
    initial: InitialEstimate | None = None,
    robust: str | None = None,
    compute_covariance: bool = True,
    max_iterations: int = 100,
    on_iteration: Callable[[int, float, float], None] | None = None,
    fast: bool = True,
    progress: Progress | None = None,
    diagnose: bool = True,
    options: SolveOptions | None = None,
) -> Calibration:
    """Analytical solution (Sects. 4-5), then the MLE by Levenberg-Marquardt (eq. 23) and Marginals.

    initial: start the MLE from these values instead of the analytical solution (e.g. the ground truth).
    robust: ``None``, ``"huber"`` or ``"cauchy"`` kernel on every measurement (another name: ValueError).
    on_iteration: called with ``(iteration, error_before, error_after)`` after each LM iteration. fast:
    stacked vectorised factors (default) or the per-measurement reference factors (same estimates). progress: called
    ``progress(stage, done, total)`` per stage (:data:`STAGES`): nodes of the mirror tree scored,
    LM iterations (of ``max_iterations``), marginals (0 then 1 of 1). Stage times are logged on the
    ``"mirror_fg"`` logger (INFO).

    Images or fiducials that disagree with the rest (a wrong corner order, a gross corner, an image
    inconsistent with the other placements of its mirror) are left out before the solve, measurements
    far off the solution (``consensus.FINAL_SIGMAS``) after it, and the solve repeated: each is in
    ``Calibration.excluded`` with its reason (``consensus.py``); with nothing left out the answer is
    exactly that of the solve alone. ``Calibration.inconsistency`` names what the data contradict
    (``consistency.diagnose_inconsistency``): where the final cost is implausible, a split of the images
    (in capture order) into groups each consistent alone, else two images labelled as one placement whose
    mirrors differ; whatever the cost, a split at a boundary between placements of mirror 1 whose two
    sides' poses differ beyond their covariances (a camera that moved). A few dozen solves of the groups
    at most: ``diagnose=False`` skips it, e.g. for a first solve that is expected to fit badly.
    Whether the result may be written is :func:`~mirror_fg.solver.result.calibration.require_converged`'s call.

    options: all of the settings above in one :class:`~mirror_fg.solver.options.SolveOptions` (then give
    none of them separately: TypeError); ``fast=True`` is ``linearization="eliminated"``, ``fast=False``
    ``"reference"``, and ``SolveOptions(linearization="stacked")`` the stacked factors without elimination.
    """
    separate = (robust, compute_covariance, max_iterations, on_iteration, fast, progress, diagnose)
    if options is None:
        options = SolveOptions(robust=robust, compute_covariance=compute_covariance, max_iterations=max_iterations,
                               on_iteration=on_iteration, progress=progress, diagnose=diagnose,
                               linearization=Linearization.ELIMINATED if fast else Linearization.REFERENCE)
    elif separate != (None, True, 100, None, True, None, True):
        raise TypeError("calibrate(): give the settings either in options= or as separate arguments, not both")
    dataset = as_dataset(dataset)
    # A rig camera no image names has nothing to estimate it from (a dataset of new images for verify may
    # leave cameras out: the check is the calibration's, not the file's).
    check_cameras_named(dataset.cameras, (image.camera for image in dataset.images), dataset.source)
    if dataset.robot is not None:  # a robot arm (docs/formats.md "Robot arms"): mounts from joint states
        from mirror_fg.solver.batch.robot_solve import calibrate_robot
        return calibrate_robot(dataset, initial, options)  # type: ignore[arg-type]
    if not dataset.is_tree:  # direct views, fixed mirrors, any order, no known target, several cameras
        check_camera_labels(dataset)  # a rig image naming the wrong camera, before any plane is started
        calibration = calibrate_views(dataset, initial, options)
    elif dataset.camera is not None and dataset.camera.estimate:  # intrinsics estimated too (camera.estimate)
        calibration = calibrate_with_intrinsics(dataset, initial=initial, options=options)
    else:
        calibration = run_pipeline(TreeProblem(initial, options), dataset)
    if options.compute_covariance and calibration.covariance is not None:  # what verify divides its test by
        if calibration.dispersion is None:  # else the solve's own model gave it (views_solve.py)
            calibration.dispersion = dispersion_of_calibration(dataset, calibration)
        calibration.placement_covariances = placement_covariances(dataset, calibration)  # a mirror that stands still
    return calibration


def calibrate_with_intrinsics(
    dataset: Dataset,
    *,
    initial: InitialEstimate | None = None,
    robust: str | None = None,
    compute_covariance: bool = True,
    max_iterations: int = 100,
    on_iteration: Callable[[int, float, float], None] | None = None,
    progress: Progress | None = None,
    options: SolveOptions | None = None,
) -> Calibration:
    """The MLE of every unknown and of the intrinsics named in ``dataset.camera.estimate`` (module
    docstring, second paragraph). Arguments as :func:`calibrate`; ``initial`` starts the
    fixed-intrinsics stage (pose, mirrors, points), the intrinsics start at the camera's values.

    Measurements or images that ``calibrate`` leaves out at the start (far off even with the start
    intrinsics' sigma, see ``intrinsics.START_SIGMA_FRACTION``) or that end far off the joint solution
    (``consensus.final_check``) are left out, as ``calibrate`` does, and listed in ``excluded``.

    Raises DatasetError (a fisheye camera, unmodelled distortion terms) or SolveError (unobservable
    intrinsics, an indeterminant system); warns
    :class:`~mirror_fg.solver.batch.intrinsics_observability.WeakIntrinsicsWarning` on weak ones.
    ``options``: the settings in one :class:`SolveOptions` instead (its ``linearization`` and ``diagnose``
    are not used: the start takes the default factors, the joint solve pixel factors).
    """
    if options is None:
        options = SolveOptions(robust=robust, compute_covariance=compute_covariance, max_iterations=max_iterations,
                               on_iteration=on_iteration, progress=progress)
    return run_pipeline(PixelProblem(initial, options, calibrate), dataset)
