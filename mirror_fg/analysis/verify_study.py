"""The detection power of ``verify`` (docs/formats.md, "Has it moved?") on simulated data.

Each trial: a stored calibration from ``stored_images`` simulated images (one hand-held mirror, four
fiducials, the paper's camera and noise), then ``new_images`` new placements simulated with the camera
where it was (no move) and with the camera moved by ``move_sigmas`` times the combined sigma of each of
its six components (``[dtheta, dt]``, the uncertainty convention: ``R_moved = Exp(dtheta) R``,
``t_moved = t + dt``; each component's sign drawn at random). The combined covariance is the one the test
uses, ``S + N^-1`` at the truth (the new placements without noise). Units: radians and metres inside.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from mirror_fg.core.geometry import so3_exp
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.analysis.verify import MOVED, verify
from mirror_fg.simulate.tree import GroundTruth, measure, simulate_base_case

__all__ = ["PowerCounts", "PowerFigures", "power_study", "moved_data"]


@dataclass(frozen=True)
class PowerCounts:
    """How often each case was called ``moved``, out of ``trials``; ``verdicts_*`` counts every verdict."""

    trials: int
    alpha: float
    move_sigmas: float
    false_alarms: int
    detections: int
    verdicts_still: dict[str, int]
    verdicts_moved: dict[str, int]

    @property
    def false_alarm_rate(self) -> float:
        return self.false_alarms / self.trials

    @property
    def detection_rate(self) -> float:
        return self.detections / self.trials


@dataclass(frozen=True)
class PowerFigures(PowerCounts):
    """:class:`PowerCounts` of the camera's study."""

    #: The mean ``d2`` without a move: ``dof`` (6) where the test is calibrated.
    mean_d2_still: float


def moved_data(new: Dataset, truth: GroundTruth, move: np.ndarray, pixel_sigma: float,
               rng: np.random.Generator | None) -> Dataset:
    """``new``'s images measured again with the camera moved by ``move = [dtheta, dt]`` (the mirrors kept
    in the camera's frame), with ``pixel_sigma`` noise (none when ``rng`` is None)."""
    moved = replace(truth, R_cam_base=so3_exp(move[:3]) @ truth.R_cam_base, t_cam_base=truth.t_cam_base + move[3:])
    assert new.camera is not None
    images = [Image(im.id, im.mirror_configs,
                    measure(moved, new.camera, new.fiducials, im.mirror_configs, pixel_sigma if rng else 0.0, rng))
              for im in new.images]
    return replace(new, images=images)


def power_study(trials: int = 200, seed: int = 0, alpha: float = 0.01, move_sigmas: float = 3.0,
                stored_images: int = 20, new_images: int = 3, pixel_sigma: float = 1.0,
                estimate: tuple[str, ...] = ()) -> PowerFigures:
    """The study of the module docstring; every trial has its own scene, stored data and noise.
    ``estimate``: intrinsics the stored calibration estimates (``camera.estimate``; verify then holds them
    under their stored covariance, correlated with the pose's)."""
    rng = np.random.default_rng(seed)
    false_alarms = detections = 0
    still: dict[str, int] = {}
    moved_counts: dict[str, int] = {}
    d2_still: list[float] = []
    for trial in range(trials):
        scene_seed = int(rng.integers(0, 2**31 - 1))
        stored_data, _ = simulate_base_case(num_images=stored_images, num_mirrors=1, num_fiducials=4,
                                            pixel_sigma=pixel_sigma, seed=scene_seed)
        if estimate:
            assert stored_data.camera is not None
            stored_data = replace(stored_data, camera=replace(stored_data.camera, estimate=estimate))
        with warnings.catch_warnings():  # a weak intrinsic is part of the study (its bounds say so), not news
            warnings.simplefilter("ignore")
            stored = calibrate(stored_data)
        new, truth = simulate_base_case(num_images=new_images, num_mirrors=1, num_fiducials=4, pixel_sigma=pixel_sigma,
                                        mirror1_placements=1, seed=scene_seed + 1)
        exact = verify(stored, moved_data(new, truth, np.zeros(6), pixel_sigma, None), alpha=alpha)
        combined = exact.cameras["camera"].covariance
        assert combined is not None, "three placements determine the pose"
        move = move_sigmas * np.sqrt(np.diag(combined)) * rng.choice([-1.0, 1.0], size=6)
        unmoved = verify(stored, new, alpha=alpha).cameras["camera"]  # new: the camera where it was
        answer = unmoved.verdict
        d2_still.append(unmoved.mahalanobis2)
        still[answer] = still.get(answer, 0) + 1
        false_alarms += answer == MOVED
        answer = verify(stored, moved_data(new, truth, move, pixel_sigma, rng), alpha=alpha).cameras["camera"].verdict
        moved_counts[answer] = moved_counts.get(answer, 0) + 1
        detections += answer == MOVED
    return PowerFigures(trials, alpha, move_sigmas, false_alarms, detections, still, moved_counts,
                        float(np.mean(d2_still)))
