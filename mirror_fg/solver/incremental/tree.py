"""The paper's tree on iSAM2: the backend of ``incremental.IncrementalCalibrator`` for tree data.

Same unknowns, measurement model and noise as the batch pipeline (``calibrate.py``): ``X(0)`` is
``T_cam_base`` (camera <- base, ``Cp = R Bp + t``, metres), ``V(i)`` one placement per configuration
``(l, m)`` (the plane of its mirror vector, camera frame, metres), ``L(j)`` one reconstruction point (base
frame, metres); keys are numbered in the order the unknowns get a value. As in the batch, the last mirror's
placements (one per image, typically) are eliminated inside their views' factors (the one model's
eliminated stacks, ``factors/view_eliminated.py``: a Schur complement) and
are not iSAM2 unknowns: iSAM2 holds ``X(0)``, the placements of mirrors 1..Nv-1 and the points, so an
update costs about the same at the 10,000th image as at the 1,000th (``graph.py`` explains the
blocks of placements and their merging). With a robust kernel (or for a placement seen under two
parents) the placements stay iSAM2 unknowns with the model's stacked factors (``view_factors.py``).
Each update is built from its new measurements only.

Life of an image (``TreeIncrementalCalibrator.add_image``):

1. It is validated (``dataset.validate_image``) and refused with ``DatasetError`` on bad input, leaving
   the calibrator as it was. Then the batch consensus checks it (``consensus.py``; images with >= 4
   fiducials): its gross fiducials are dropped, and an image whose corner order is wrong (bad PnP fit,
   the board seen from behind unlike the images so far) or that misfits the settled estimate of at
   least ``MIN_IMAGES_TO_JUDGE`` images by more than ``CONSENSUS_MIN_SIGMAS`` (judged with that estimate's
   uncertainty, ``misfit.py``) is refused; each start-up
   runs the batch consensus on its images. Each image refused is named in ``excluded`` with its reason.
2. Until start-up every image waits. Start-up happens at the first image where the images with >= 3
   fiducials contain a complete configuration tree (:func:`complete_tree`: every kept placement of
   mirror l has >= 3 kept placements of mirror l+1 under it, the root >= 3 placements of mirror 1;
   Sect. 4.2, Fig. 3). The analytical solution is solved on that tree, every image whose placements
   it determines goes into one graph, Levenberg-Marquardt refines it (as the batch does) and a fresh
   iSAM2 gets that whole graph at the refined values.
3. Afterwards an image whose placements all have values only adds its factors (one ``ISAM2.update``
   with the new factors and values, nothing re-added): its last-mirror placement goes into a new block
   of its own, and every ``MERGE_FANOUT`` blocks of one size under one parent are merged into one (their
   factors replaced in the same update). New placements and points get values from the image's PnP and
   the current estimate, each then moved to its optimum alone (``values.py``); a point's
   observations wait until two images in the graph see it.

Settling: a start-up counts as settled only when iSAM2's own step at the LM solution is small; until
then the LM estimate is reported and the start-up re-run with later images (``startup.py``).

This module holds the screening of images and when to restart; the calibrator holds an
:class:`~mirror_fg.solver.incremental.graph.IncrementalGraph` (``graph.py``: graph, iSAM2
updates; state in ``state.py``, new values in ``values.py``), started by
``startup.py``. An image off the tree raises :class:`LeavesTheTree` before anything changes:
the public calibrator (``calibrator.py``) then hands every image to ``views.py``.
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import gtsam
import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.core.geometry import nested_transform
from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.factors.robust import check_kernel
from mirror_fg.io.dataset import validate_image
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.start.analytic import AnalyticSolution
from mirror_fg.solver.calibrate import as_dataset
from mirror_fg.solver.result.calibration import Calibration, Exclusion
from mirror_fg.solver.screen.consensus import BEHIND, CONSENSUS_MIN_SIGMAS, board_side, check_image, misfit_sigmas, screen
from mirror_fg.solver.incremental.graph import IncrementalGraph
from mirror_fg.solver.incremental.misfit import misfit_sigmas_with_uncertainty
from mirror_fg.solver.incremental.startup import DIVERGENCE_SIGMAS, FINAL_LM_ITERATIONS, STARTUP_LM_ITERATIONS, start_graph
from mirror_fg.solver.incremental.state import GraphState, RelinearizeThresholds
from mirror_fg.solver.incremental.values import MIN_PNP_FIDUCIALS
from mirror_fg.solver.start.initial import initial_estimate
from mirror_fg.solver.incremental.view_factors import vector_covariance, vector_jacobian
from mirror_fg.solver.start.placement_tree import complete_tree, tree_shortfall
from mirror_fg.solver.timing import timed

if TYPE_CHECKING:
    from mirror_fg.solver.information.suggest import Reach, Suggestions

__all__ = ["TreeIncrementalCalibrator", "LeavesTheTree", "complete_tree"]

#: An image is judged against the estimate (refused when it misfits it by more than
#: ``consensus.CONSENSUS_MIN_SIGMAS``) only once this many images are in the graph: the estimate of a
#: first, minimal tree is too rough to judge by (and could itself hold an image no majority refused yet).
MIN_IMAGES_TO_JUDGE = 8
#: Unsettled: re-run the start-up on every image for this many tries, then on every 2nd, 4th, ... image.
UNSETTLED_EVERY_IMAGE = 8
#: ... but at least every this many images.
UNSETTLED_MAX_INTERVAL = 32


class LeavesTheTree(Exception):
    """An image off the paper's tree (``mirror_configs`` shorter than ``num_mirrors``, or ``reflections``):
    the tree backend cannot take it; nothing changed. Carries the image's id."""


class TreeIncrementalCalibrator:
    """Camera-to-base calibration that takes images one at a time (iSAM2 on the batch factors).

    ``dataset`` gives the camera, fiducials, number of mirrors and pixel sigma; its images are not
    calibrated. ``points``: the reconstruction point names images may use; ``None`` takes the names in
    ``dataset.images`` when it has images (any other non-fiducial name is then refused as unknown) and
    accepts any non-fiducial name when it has none. ``robust``: ``None``, ``"huber"`` or ``"cauchy"``
    kernel as in ``calibrate``. ``thresholds``: iSAM2 relinearisation thresholds. ``seed``: for the
    analytical solution's P3P hypotheses.

    ``add_image(image)`` returns ``None`` until the analytical solution exists (:attr:`status` says what
    it waits for, :attr:`startup_error` why the latest start-up failed), then a cheap
    ``Calibration`` after every image; ``calibration(full=True)`` adds mirror and point covariances and
    residuals over every image in the graph; ``marginal_covariance()`` gives covariances on demand.
    """

    def __init__(self, dataset: Dataset, *, points: Iterable[str] | None = None, robust: str | None = None,
                 thresholds: RelinearizeThresholds | None = None, seed: int = 0) -> None:
        dataset = as_dataset(dataset, "IncrementalCalibrator()")
        # Our own Dataset holds the images in the graph: normalisation cache, residuals, messages.
        self._ds = replace(dataset, images=[], point_sigma=dict(dataset.point_sigma),
                           fiducials={name: np.array(p, dtype=float) for name, p in dataset.fiducials.items()})
        if points is not None:
            self._known_points: set[str] | None = set(points)
        elif dataset.images:
            self._known_points = set(dataset.reconstruction_point_names)
        else:
            self._known_points = None
        check_kernel(robust)
        self._seed = seed
        self._ids: set[str] = set()
        #: Images or fiducials refused by the consensus (``consensus.py``), each with its reason.
        self.excluded: list[Exclusion] = []
        self._sides: dict[str, float] = {}  # side of the board each accepted image sees
        #: The images refused as inconsistent with the estimate (``calibrate_incremental`` asks whether
        #: they are consistent among themselves: a camera or board that moved).
        self.misfits: list[Image] = []
        self._accepted: list[Image] = []  # every accepted image, in order
        # Start-up / restart bookkeeping.
        self._analytic: AnalyticSolution | None = None
        self._settled = False
        self._unsettled_tries = 0
        self._accepted_at_restart = 0
        self._failed_tree: frozenset | None = None  # placements of the last failed analytical solution
        #: Why the latest start-up attempt failed (``None`` after a successful one); :attr:`status`
        #: says it in one line.
        self.startup_error: Exception | None = None
        self.restarts = 0
        self._lm_iterations: list[int] = []  # LM iterations of each start-up
        self.timings: dict[str, float] = defaultdict(float)
        self._graph = IncrementalGraph(self._ds, robust, thresholds or RelinearizeThresholds(), self.timings, seed)

    @property
    def dataset(self) -> Dataset:
        """The camera, fiducials and noise of the calibration, with the images in the graph."""
        return self._ds

    @property
    def state(self) -> GraphState:
        """The graph's state: graph, estimate, images in and waiting for it."""
        return self._graph.state

    @property
    def _g(self) -> GraphState:
        """The graph's state: graph, estimate, images in and waiting for it."""
        return self._graph.state

    def _reset_graph(self) -> None:
        """Empty graph and estimate (before a start-up); every accepted image waits."""
        self._graph.reset(self._accepted)

    # --- public -------------------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        """Whether the analytical solution has been formed and there is an estimate."""
        return self._analytic is not None

    @property
    def settled(self) -> bool:
        """Whether iSAM2 runs on its own (the start-up's Levenberg-Marquardt solution was a clean minimum)."""
        return self._settled

    @property
    def num_images(self) -> int:
        """Images whose factors are in the graph."""
        return len(self._ds.images)

    @property
    def waiting_images(self) -> list[str]:
        """Ids of accepted images not in the graph: before start-up, or their placements still unknown."""
        return [im.id for im in self._g.waiting]

    @property
    def analytic(self) -> AnalyticSolution | None:
        """The analytical solution of the latest start-up (``None`` before start-up)."""
        return self._analytic

    @property
    def status(self) -> str:
        """One line on where the calibrator stands; before start-up, why it is waiting (what the
        configuration tree still lacks, ``placement_tree.tree_shortfall``, or why the start-up failed):
        ``"waiting: mirror 2 has 2 placement(s) under (1, 0), needs 3"``."""
        if self.started:
            state = "settled (iSAM2)" if self._settled else "unsettled (Levenberg-Marquardt estimate, retrying)"
            return (f"{state}: {self.num_images} image(s) in the graph, {len(self.waiting_images)} waiting, "
                    f"{len(self.excluded)} left out")
        usable = [im for im in self._accepted if self._num_fiducials(im) >= MIN_PNP_FIDUCIALS]
        shortfall = tree_shortfall(usable, self._ds.num_mirrors)
        if shortfall is None and self.startup_error is not None:
            return f"waiting: the start-up failed: {self.startup_error}"
        if shortfall == "no image yet":
            return (f"waiting: no image with >= {MIN_PNP_FIDUCIALS} fiducials yet" if self._accepted
                    else "waiting: no image yet")
        return f"waiting: {shortfall or 'the start-up is due'}"

    def __repr__(self) -> str:
        """A few words: images given, in the graph, left out, and :attr:`status`."""
        return (f"TreeIncrementalCalibrator({self._ds.source!r}: {len(self._ids)} image(s) given, {self.num_images} in "
                f"the graph, {len(self.excluded)} left out; {self.status})")

    def add_image(self, image: Image | Mapping[str, Any]) -> Calibration | None:
        """Take one image's observations (a ``mirror_fg.Image`` or its dataset@1 dict).

        Returns ``None`` while the analytical solution cannot be formed (:attr:`status` says why), else the
        current ``Calibration`` (the cheap one, see :meth:`calibration`). Raises ``DatasetError`` on bad input
        (unknown point name, non-finite value, wrong ``mirror_configs`` length, an id already given) before
        anything changes. Trouble solving never raises here: the calibrator keeps its estimate, unsettled,
        retries with later images and keeps the reason in ``startup_error``.
        """
        checked = validate_image(image, self._ds, known_points=self._known_points)
        if checked.id in self._ids:
            raise DatasetError(f"{self._ds.source}: image {checked.id!r}: duplicate image id (already given)")
        # Accepted: nothing below is input validation.
        if len(checked.mirror_configs) != self._ds.num_mirrors:  # off the tree: the view model from here on
            raise LeavesTheTree(checked.id)
        self._ids.add(checked.id)
        screened = self._screen(checked)
        if screened is None:  # refused as inconsistent: named in ``excluded``, the estimate untouched
            return self.calibration() if self.started else None
        checked = screened
        self._accepted.append(checked)
        self._g.waiting.append(checked)
        if not self._settled:
            if self._restart_due():
                self._restart()
            if not self.started:
                return None
        else:
            self._process_waiting()
        return self.calibration()

    def suggest_next(self, count: int = 3, reach: Reach | None = None) -> Suggestions:
        """The mirror placements to try next for the images so far, best first (``mirror-fg plan --next``;
        :func:`mirror_fg.solver.information.suggest.suggest_next` at the current estimate). Raises SolveError before
        the analytical solution exists."""
        from mirror_fg.solver.information.suggest import suggest_next

        self._require_started()
        return suggest_next(self._ds, self.calibration(), count=count, reach=reach)

    def marginal_covariance(self, unknown: tuple[int, int] | str | None = None) -> np.ndarray:
        """Marginal covariance from iSAM2's Bayes tree, on demand (at the linearisation point).

        ``None``: ``T_cam_base``, 6x6 in docs/formats.md's convention ``[dtheta (rad), dt (m)]`` with ``R_true =
        Exp(dtheta) R_est``, ``t_true = t_est + dt``. ``(l, m)``: the mirror vector of that configuration,
        3x3, m^2, camera frame. A point name: that reconstruction point, 3x3, m^2, base frame. An
        eliminated placement (not an iSAM2 unknown) gets the whole graph's marginal at the estimate, a
        pass over every measurement.
        """
        self._require_started()
        if unknown is None:
            return covariance_from_pose3(self._g.R, self._g.pose_cov)
        if isinstance(unknown, str):
            key = self._g.layout.point_keys.get(unknown)
        else:
            config = tuple(unknown)  # a list ``[l, m]`` works too
            key = self._g.layout.mirror_keys.get(config) if len(config) == 2 else None
        if key is None:
            raise KeyError(f"{unknown!r} has no value in the graph yet")
        if self._settled and isinstance(unknown, str):
            return self._g.require_isam().marginalCovariance(key)
        if self._settled and config in self._g.kept:  # the plane's covariance as its mirror vector's
            return vector_covariance(self._g.mirrors[config], self._g.require_isam().marginalCovariance(key))
        # Unsettled, iSAM2 may not hold the reported (LM) estimate; an eliminated placement is not in
        # iSAM2: marginals of the whole graph at the estimate.
        _, _, (_, mirrors, points) = self._graph.explicit_covariances()
        return points[unknown] if isinstance(unknown, str) else mirrors[config]

    def calibration(self, full: bool = False) -> Calibration:
        """The current estimate as a ``Calibration`` (same shape as the batch one).

        ``full=False`` (what ``add_image`` returns, about a millisecond): pose and its covariance from
        iSAM2; mirror vectors and points without covariances (an eliminated placement as its block gave
        it at the update that made or last merged the block); no residuals (empty, so ``to_dict()``
        reports 0) and NaN ``initial_error``/``final_error`` (each would cost a pass over every factor).
        ``full=True`` (about a second for 300 images): first every factor is relinearised at the current
        estimate until the pose moves less than 1e-3 of its standard deviation (an unsettled calibrator
        first re-runs the start-up on every image with the batch's LM budget); then covariances of every
        unknown by ``gtsam.Marginals`` on the whole graph, the residual of every measurement in the graph,
        ``final_error`` of the whole graph and ``initial_error`` of the latest start-up graph at its
        analytical solution.

        Both: ``iterations`` counts iSAM2 updates so far; ``converged`` is whether the calibrator is
        settled (and, with ``full=True``, the relinearisation converged). Raises ``SolveError`` before
        start-up.
        """
        self._require_started()
        if not full:
            return self._graph.calibration(self._analytic, self._settled, self.excluded)
        stage_times: dict[str, float] = {}
        with timed(stage_times, "full"):
            if not self._settled:
                # Every image, and the batch's iteration budget, for the Levenberg-Marquardt solution.
                self._restart(lm_iterations=FINAL_LM_ITERATIONS)
            if self._settled:
                try:
                    self._graph.polish()
                except SolveError:  # relinearised, the system turned indeterminant: fall back to LM
                    self._settled = False
                    self._restart(lm_iterations=FINAL_LM_ITERATIONS)
            # Unsettled, the estimate is the start-up's Levenberg-Marquardt solution: no Gauss-Newton step.
            calibration = self._graph.calibration(self._analytic, self._settled, self.excluded, full=True)
        calibration.timings.update(stage_times)
        return calibration

    # --- start-up and restarts (Sects. 4-5) ------------------------------------------------------------

    def _restart_due(self) -> bool:
        """Unsettled: retry the start-up on every image at first, then less and less often."""
        if not self.started:
            return True
        tries = self._unsettled_tries - UNSETTLED_EVERY_IMAGE
        interval = 1 if tries < 0 else min(2 ** (tries // 4 + 1), UNSETTLED_MAX_INTERVAL)
        return len(self._accepted) - self._accepted_at_restart >= interval

    def _restart(self, lm_iterations: int = STARTUP_LM_ITERATIONS) -> bool:
        """Analytical solution on the complete tree of every image so far, LM, then a fresh iSAM2.

        Returns whether there is a new estimate. On failure (no complete tree yet, degenerate geometry)
        the calibrator keeps what it had, unsettled, and the reason in ``startup_error``.
        """
        saved = self._g  # a start-up builds a new GraphState: the saved one is left as it was
        with timed(self.timings, "startup"):
            try:
                self._start(lm_iterations)
                self.startup_error = None
                return True
            except (SolveError, DatasetError) as error:
                self._graph.state = saved
                self.startup_error = error
                self._settled = False
                return False

    def _start(self, lm_iterations: int) -> None:
        Nv = self._ds.num_mirrors
        tree = complete_tree([im for im in self._accepted if self._num_fiducials(im) >= MIN_PNP_FIDUCIALS], Nv)
        if not tree:
            raise SolveError(
                f"{self._ds.source}: no complete tree of placements yet (each placement needs >= 3 child "
                "placements seen with >= 3 fiducials)"
            )
        placements = frozenset(im.mirror_configs for im in tree)
        if placements == self._failed_tree:
            # More views of the placements that failed will not make the analytical solution work.
            raise self.startup_error or SolveError(f"{self._ds.source}: the analytical solution failed")
        # Fiducials only: points are triangulated below from every image the start-up admits.
        fiducial_only = Dataset(
            num_mirrors=Nv,
            camera=self._ds.camera,
            pixel_sigma=self._ds.pixel_sigma,
            fiducials=self._ds.fiducials,
            images=[
                Image(im.id, im.mirror_configs, {n: z for n, z in im.observations.items() if n in self._ds.fiducials})
                for im in tree
            ],
            source=self._ds.source,
        )
        # The batch consensus on the start-up images: an image whose board side or mirror placement
        # disagrees with the majority is refused before it can poison the estimate.
        fiducial_only, excluded, pnp = screen(fiducial_only, seed=self._seed)
        refused = {e.image for e in excluded if e.point is None}
        if refused:
            self.excluded.extend(e for e in excluded if e.point is None)
            self._accepted = [im for im in self._accepted if im.id not in refused]
            for image_id in refused:
                self._sides.pop(image_id, None)
            self._reset_graph()
            tree = complete_tree([im for im in self._accepted if self._num_fiducials(im) >= MIN_PNP_FIDUCIALS], Nv)
            if not tree:
                raise SolveError(f"{self._ds.source}: no complete tree of placements left after refusing "
                                 f"{', '.join(sorted(refused))}")
            kept = {im.id for im in tree}
            fiducial_only.images = [im for im in fiducial_only.images if im.id in kept]
            placements = frozenset(im.mirror_configs for im in tree)
        try:
            analytic = initial_estimate(fiducial_only, seed=self._seed, pnp=pnp)
        except (SolveError, DatasetError):
            self._failed_tree = placements
            raise
        was_started = self.started
        self._reset_graph()
        start = start_graph(self._graph, analytic, lm_iterations)
        self._settled = start.settled
        self._unsettled_tries = 0 if self._settled else self._unsettled_tries + 1
        self._analytic = analytic
        self._accepted_at_restart = len(self._accepted)
        self.restarts += int(was_started)
        self._lm_iterations.append(start.lm_iterations)

    # --- adding images ------------------------------------------------------------------------------

    def _screen(self, image: Image) -> Image | None:
        """The batch consensus on one image (``consensus.py``), against the images and estimate so far:
        its PnP fit (gross fiducials dropped, a wrong corner order refused), the side of the board it
        sees against the majority so far, and, once settled, its misfit with the estimate (the parent of
        its last mirror from the estimate, that mirror's placement fitted where new). Returns the image to
        use, or None when it is refused; everything left out goes to ``excluded``."""
        kept, candidates, excluded = check_image(self._ds, image)
        self.excluded.extend(excluded)
        if kept is None or not candidates:
            return kept
        side = board_side(self._ds, candidates[0])
        behind = False  # not a reason on its own (consensus.BEHIND): named when the image misfits too
        if side is not None:
            majority = sum(self._sides.values())
            behind = len(self._sides) >= 3 and abs(majority) == len(self._sides) and side != np.sign(majority)
            self._sides[image.id] = side
        if self._settled and self.num_images >= MIN_IMAGES_TO_JUDGE:
            configs = kept.mirror_configs
            above = [self._g.mirrors.get((level + 1, m)) for level, m in enumerate(configs[:-1])]
            known = [v for v in above if v is not None]
            if len(known) == len(above):
                A_parent, b_parent = nested_transform(self._g.R, self._g.t, known)  # eqs. (6)-(8)
                last = self._g.mirrors.get((len(configs), configs[-1]))
                sigmas = misfit_sigmas(self._ds, kept, candidates, A_parent, b_parent, last)
                if sigmas > CONSENSUS_MIN_SIGMAS:  # judged again with the estimate's uncertainty (never larger)
                    sigmas = self._misfit_with_uncertainty(kept, candidates, configs, known, last)
                if sigmas > CONSENSUS_MIN_SIGMAS:
                    reason = f"inconsistent with the estimate so far ({sigmas:.3g} sigma RMS)"
                    self.excluded.append(Exclusion(image.id, f"{BEHIND}; {reason}" if behind else reason, None, sigmas))
                    self.misfits.append(kept)
                    self._sides.pop(image.id, None)
                    return None
        return kept

    def _misfit_with_uncertainty(self, image: Image, candidates, configs: tuple[int, ...], parents: list[np.ndarray],
                                 last: np.ndarray | None) -> float:
        """:func:`~mirror_fg.solver.incremental.misfit.misfit_sigmas_with_uncertainty` of ``image`` at the
        estimate, with the joint marginal of the pose and its parent placements from iSAM2."""
        layout = self._g.layout
        keys = [layout.pose_key, *(layout.mirror_keys[(level + 1, m)] for level, m in enumerate(configs[:-1]))]
        try:
            covariance = self._g.require_isam().jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
        except RuntimeError:  # an indeterminant system: judged at the estimate's value alone
            covariance = np.zeros((6 + 3 * len(parents), 6 + 3 * len(parents)))
        else:  # the parents' planes as their mirror vectors (v = d n), at the estimate
            J = np.eye(len(covariance))
            for k, v in enumerate(parents):
                J[6 + 3 * k:9 + 3 * k, 6 + 3 * k:9 + 3 * k] = vector_jacobian(v)
            covariance = J @ covariance @ J.T
        pose = gtsam.Pose3(gtsam.Rot3(self._g.R), np.asarray(self._g.t, float))
        return misfit_sigmas_with_uncertainty(self._ds, image, candidates, pose, parents, last, covariance)

    def _process_waiting(self) -> None:
        values = gtsam.Values()
        factors = gtsam.NonlinearFactorGraph()
        self._graph.collect(factors, values)
        if factors.size() == 0 and values.size() == 0:
            return
        before = (self._g.R, self._g.t, self._g.pose_cov)
        self._graph.refine_new(factors, values)
        try:
            self._graph.update(factors, values)
            diverged = self._graph.pose_step_sigmas(*before) > DIVERGENCE_SIGMAS
        except SolveError:
            diverged = True
        if diverged:
            self._settled = False
            self._restart()

    # --- helpers ------------------------------------------------------------------------------------

    def _num_fiducials(self, image: Image) -> int:
        return sum(1 for n in image.observations if n in self._ds.fiducials)

    def _require_started(self) -> None:
        if not self.started:
            raise SolveError(f"{self._ds.source}: no estimate yet: {self.status}")


