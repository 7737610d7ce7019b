"""Incremental calibration with iSAM2: the estimate and its 3-sigma bounds firm up image by image.

:class:`IncrementalCalibrator` is the one public calibrator for every set-up: it holds the images given
so far and a backend, ``backend``, that keeps the graph and iSAM2:

- the paper's tree (``Dataset.is_tree``): :class:`~mirror_fg.solver.incremental.tree.TreeIncrementalCalibrator`
  (the analytic start, consensus screening of each image, start-up and settling: ``tree.py``; its graph
  of the one model's view factors with the last mirror's placements eliminated: ``graph.py``);
- anything else (any reflection order, rigs, no known target):
  :class:`~mirror_fg.solver.incremental.views.ViewsIncrementalCalibrator` (the propagation start, one
  view factor per image: ``views.py``).

A calibrator made for the tree that is given an image off the tree (a direct view, a single reflection,
``reflections``) takes the general backend from then on, fed every image given so far in order: the
answer is what the general backend would have given from the first image. Both backends use the same
iSAM2 settings (``state.new_isam2``). ``calibrate_incremental`` streams a whole dataset.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from mirror_fg.core.errors import SolveError
from mirror_fg.data import Dataset, Image
from mirror_fg.io.dataset_fields import check_cameras_named
from mirror_fg.solver.start.analytic import AnalyticSolution
from mirror_fg.solver.calibrate import as_dataset
from mirror_fg.solver.result.calibration import require_converged
from mirror_fg.solver.result.calibration import Calibration, Exclusion
from mirror_fg.solver.screen.consistency import diagnose_inconsistency, misfits_split
from mirror_fg.solver.incremental.state import RelinearizeThresholds
from mirror_fg.solver.incremental.tree import LeavesTheTree, TreeIncrementalCalibrator
from mirror_fg.solver.incremental.views import ViewsIncrementalCalibrator, calibrate_views_incremental
from mirror_fg.solver.options import IncrementalOptions
from mirror_fg.solver.start.placement_tree import complete_tree

if TYPE_CHECKING:
    from mirror_fg.solver.information.suggest import Reach, Suggestions

__all__ = ["IncrementalCalibrator", "calibrate_incremental", "complete_tree"]


class IncrementalCalibrator:
    """Camera-to-base calibration that takes images one at a time (iSAM2), for any set-up.

    ``dataset`` gives the camera(s), fiducials, number of mirrors, pixel sigma and scale; its images are
    not calibrated (they name the points and placements to expect). ``points``: the reconstruction point
    names images may use; ``None`` takes the names in ``dataset.images`` when it has images (any other
    non-fiducial name is then refused as unknown) and accepts any non-fiducial name when it has none.
    ``robust``: ``None``, ``"huber"`` or ``"cauchy"`` kernel as in ``calibrate``. ``thresholds``: iSAM2
    relinearisation thresholds. ``seed``: for the tree's P3P hypotheses.

    ``add_image(image)`` returns ``None`` until the start exists (:attr:`status` says what it waits for,
    :attr:`startup_error` why the latest start failed), then a cheap ``Calibration`` after every image;
    ``calibration(full=True)`` adds mirror and point covariances and residuals over every image in the
    graph; ``marginal_covariance()`` gives covariances on demand.
    """

    def __init__(self, dataset: Dataset | Mapping[str, Any], options: IncrementalOptions | None = None, *,
                 points: Iterable[str] | None = None, robust: str | None = None,
                 thresholds: RelinearizeThresholds | None = None, seed: int = 0) -> None:
        dataset = as_dataset(dataset, "IncrementalCalibrator()")
        #: The settings (:class:`~mirror_fg.solver.options.IncrementalOptions`): ``options``, or the keywords.
        self.options = _options_of(options, points=points, robust=robust, thresholds=thresholds, seed=seed)
        self._dataset = dataset
        self._given: list[Image | Mapping[str, Any]] = []  # every image the backend took, in order (handed over on leaving the tree)
        #: The graph and iSAM2: ``TreeIncrementalCalibrator`` or ``ViewsIncrementalCalibrator``.
        self.backend: TreeIncrementalCalibrator | ViewsIncrementalCalibrator = (
            TreeIncrementalCalibrator(dataset, **self.options.backend_options()) if dataset.is_tree
            else ViewsIncrementalCalibrator(dataset, **self.options.backend_options()))

    def add_image(self, image: Image | Mapping[str, Any]) -> Calibration | None:
        """Take one image's observations (a ``mirror_fg.Image`` or its dataset@1 dict).

        Returns ``None`` while the start cannot be formed (:attr:`status` says why), else the current
        ``Calibration`` (the cheap one, see :meth:`calibration`). Raises ``DatasetError`` on bad input
        (unknown point name, non-finite value, an id already given) before anything changes. Trouble
        solving never raises here: the calibrator keeps its estimate and retries with later images.
        """
        try:
            estimate = self.backend.add_image(image)
        except LeavesTheTree:
            # The tree backend took nothing: the general backend from here on, fed every image so far.
            self.backend = ViewsIncrementalCalibrator(replace(self._dataset, images=[]),
                                                      **self.options.backend_options())
            for earlier in self._given:
                self.backend.add_image(earlier)
            estimate = self.backend.add_image(image)
        self._given.append(image)  # as it came: the general backend validates it again on a hand-over
        return estimate

    # --- the backend's state, read-only ---------------------------------------------------------------

    @property
    def dataset(self) -> Dataset:
        """The calibration's camera(s), fiducials and noise, with the images in the graph."""
        return self.backend.dataset

    @property
    def started(self) -> bool:
        """Whether the start exists and there is an estimate."""
        return self.backend.started

    @property
    def settled(self) -> bool:
        """Whether iSAM2 runs on its own (for the tree: the start-up's LM solution was a clean minimum)."""
        return self.backend.settled

    @property
    def num_images(self) -> int:
        """Images whose factors are in the graph."""
        return self.backend.num_images

    @property
    def waiting_images(self) -> list[str]:
        """Ids of accepted images not in the graph yet."""
        return self.backend.waiting_images

    @property
    def status(self) -> str:
        """One line on where the calibrator stands; before the start, what it waits for."""
        return self.backend.status

    @property
    def excluded(self) -> list[Exclusion]:
        """Images or measurements refused or left out, each with its reason."""
        return self.backend.excluded

    @property
    def misfits(self) -> list[Image]:
        """Images refused as inconsistent with the estimate (a camera or board that moved?)."""
        return self.backend.misfits

    @property
    def startup_error(self) -> Exception | None:
        """Why the latest start failed (``None`` after a successful one)."""
        return self.backend.startup_error

    @property
    def restarts(self) -> int:
        return self.backend.restarts

    @property
    def timings(self) -> dict[str, float]:
        return self.backend.timings

    @property
    def analytic(self) -> AnalyticSolution | None:
        """The tree's analytical solution of the latest start-up (``None`` before it, and off the tree)."""
        return self.backend.analytic if isinstance(self.backend, TreeIncrementalCalibrator) else None

    def calibration(self, full: bool = False) -> Calibration:
        """The estimate (``full=False``: cheap, camera pose covariances only; ``full=True``: relinearised
        to convergence, every covariance and residual). SolveError before the start."""
        return self.backend.calibration(full=full)

    def marginal_covariance(self, unknown: tuple[int, int] | str | None = None) -> np.ndarray:
        """iSAM2's marginal covariance of ``unknown``: ``None`` the (first) camera's pose (6x6, the
        uncertainty convention of docs/formats.md), a camera name, ``(l, m)`` a mirror vector, a point."""
        return self.backend.marginal_covariance(unknown)

    def suggest_next(self, count: int = 3, reach: Reach | None = None) -> Suggestions:
        """The mirror placements to try next (``mirror-fg plan --next``), for the paper's tree."""
        if not isinstance(self.backend, TreeIncrementalCalibrator):
            raise SolveError(f"{self._dataset.source}: suggestions for the next placement need the paper's tree "
                             "(plan --kind gives the bounds of other set-ups)")
        return self.backend.suggest_next(count=count, reach=reach)

    def __repr__(self) -> str:
        return f"IncrementalCalibrator({self._dataset.source!r}: {len(self._given)} image(s) given; {self.status})"


def calibrate_incremental(
    dataset: Dataset | Mapping[str, Any],
    *,
    robust: str | None = None,
    on_estimate: Callable[[int, Calibration], None] | None = None,
    on_wait: Callable[[int, str], None] | None = None,
    accept_poor_fit: bool = False,
    options: IncrementalOptions | None = None,
) -> Calibration:
    """Stream ``dataset``'s images in file order through :class:`IncrementalCalibrator` and return the
    full final calibration (``calibration(full=True)``).

    ``on_estimate(index, estimate)`` is called after every image (1-based index) once an estimate
    exists, ``on_wait(index, reason)`` after every image before that (``IncrementalCalibrator.status``).
    Refuses what the batch path refuses, with the same errors and the same rule
    (:func:`~mirror_fg.solver.result.calibration.require_converged`): bad input is DatasetError (at load or in
    ``add_image``); a final estimate that did not converge, or (unless ``accept_poor_fit``) fits more than
    ``POOR_FIT_RATIO`` times worse than the noise model allows, is SolveError. What the data contradict
    is in ``inconsistency`` as in the batch (``consistency.diagnose_inconsistency``), after the images
    refused as inconsistent with the estimate are asked whether they fit a pose of their own.
    """
    dataset = as_dataset(dataset)
    options = _options_of(options, robust=robust, accept_poor_fit=accept_poor_fit)
    check_cameras_named(dataset.cameras, (image.camera for image in dataset.images), dataset.source)
    if not dataset.is_tree:  # the general view model (incremental/views.py)
        return calibrate_views_incremental(dataset, robust=options.robust, on_estimate=on_estimate, on_wait=on_wait,
                                           accept_poor_fit=options.accept_poor_fit)
    calibrator = IncrementalCalibrator(dataset, options)
    started = False
    for index, image in enumerate(dataset.images, start=1):
        estimate = calibrator.add_image(image)
        if estimate is not None:
            started = True
            if on_estimate is not None:
                on_estimate(index, estimate)
        elif on_wait is not None:
            on_wait(index, calibrator.status)
    if not started:
        raise SolveError(f"{dataset.source}: the images never allowed an analytical solution "
                         f"({calibrator.status})")
    calibration = calibrator.calibration(full=True)
    if calibration.converged:
        order = {image.id: i for i, image in enumerate(dataset.images)}
        in_graph = sorted((im for im in calibrator.dataset.images if im.id in order), key=lambda im: order[im.id])
        solve_options = options.solve_options()
        calibration.inconsistency = (misfits_split(dataset, in_graph, calibrator.misfits, solve_options)
                                     or diagnose_inconsistency(replace(dataset, images=in_graph), calibration,
                                                               options=solve_options))
    return require_converged(calibration, dataset.source, "iSAM2", accept_poor_fit=options.accept_poor_fit)


def _options_of(options: IncrementalOptions | None, **keywords: Any) -> IncrementalOptions:
    """``options``, or an :class:`IncrementalOptions` of the keywords given instead (both: TypeError)."""
    defaults = IncrementalOptions()
    given = {k: v for k, v in keywords.items() if v != getattr(defaults, k)}
    if options is None:
        return IncrementalOptions(**keywords)
    if given:
        raise TypeError(f"give the settings in options= or as keywords, not both ({', '.join(sorted(given))})")
    return options
