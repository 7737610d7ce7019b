"""The detection power of ``verify`` on an arm's mounts (docs/formats.md, "Has it moved?"), simulated
(``mirror_fg.robot.simulate``).

Each trial: a stored calibration of a simulated arm (``stored_poses`` arm poses at each of three
placements), then new images (``new_placements`` new placements, ``new_poses`` arm poses each) rendered
again with mount ``role`` where it was (no move) and moved by ``move_sigmas`` times the combined sigma of
each of its six components (``[dtheta, dt]``, the uncertainty convention about and along the link's axes:
``R_moved = Exp(dtheta) R``, ``t_moved = t + dt``; each sign drawn at random). The combined covariance is
the test's own, ``S + N^-1``, from the new images rendered without noise. The images are rendered here
from the truth (eq. 3 and the pinhole, not the solver's factors). Units: radians and metres.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mirror_fg.core.geometry import so3_exp
from mirror_fg.factors.robot import compose, inverse
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.data import Dataset
from mirror_fg.robot import arm_urdf
from mirror_fg.robot.kinematics import load_kinematics
from mirror_fg.robot.simulate import CAMERA, ArmTruth, simulate_arm
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.analysis.verify import MOVED, verify
from mirror_fg.analysis.verify_study import PowerCounts

__all__ = ["ArmPowerFigures", "arm_power_study", "render_arm", "arm_trial"]


@dataclass(frozen=True)
class ArmPowerFigures(PowerCounts):
    """:class:`~mirror_fg.analysis.verify_study.PowerCounts` of an arm's mount; ``d2_still`` every unmoved
    ``d2``, ``dof`` each one's degrees of freedom."""

    d2_still: tuple[float, ...]
    dof: tuple[int, ...]


def render_arm(data: dict, truth: ArmTruth, role: str, move: np.ndarray, pixel_sigma: float,
               rng: np.random.Generator | None, source: str) -> Dataset:
    """``data``'s images (a dataset@1 dictionary of ``simulate_arm``, its URDF the shipped arm) measured
    again at their joint states with mount ``role`` moved by ``move = [dtheta, dt]`` (link axes), noise of
    ``pixel_sigma`` (none where ``rng`` is None): ``x_cam = C^-1 (M D p + 2 v)`` (eq. 3), pinhole."""
    kin = load_kinematics(arm_urdf(truth.robot))
    mounts = dict(truth.mounts)
    link, (R, t) = mounts[role]
    mounts[role] = (link, (so3_exp(move[:3]) @ R, t + move[3:]))
    names = list(data["fiducials"])
    p = np.array([data["fiducials"][n] for n in names], float).T
    images = []
    for image in data["images"]:
        q = {j: x + truth.joint_offsets.get(j, 0.0) for j, x in image["joints"].items()}
        F = kin.placements(q, list({lk for lk, _ in mounts.values()}))
        poses = {r: compose((F[lk][0][:3, :3], F[lk][0][:3, 3]), m) for r, (lk, m) in mounts.items()}
        x = poses["target"][0] @ p + poses["target"][1][:, None]
        for placement in image["mirror_configs"]:
            v = truth.mirror_vectors[(1, placement)]
            x = x - 2.0 * np.outer(v, (v @ x) / (v @ v) - 1.0)  # eq. (3)
        R_c, t_c = inverse(poses["camera"])
        x_cam = R_c @ x + t_c[:, None]
        pix = (CAMERA.K @ (x_cam / x_cam[2]))[:2].T
        if rng is not None:
            pix = pix + rng.normal(0.0, pixel_sigma, pix.shape)
        images.append({**image, "observations": {n: [float(u), float(w)] for n, (u, w) in zip(names, pix)}})
    urdf = {**data["robot"], "urdf": arm_urdf(truth.robot)}
    return dataset_from_dict({**data, "robot": urdf, "images": images}, source)


def arm_trial(seed: int, role: str = "camera", move_sigmas: float = 3.0, alpha: float = 0.01, stored_poses: int = 6,
              new_placements: int = 3, new_poses: int = 4, pixel_sigma: float = 0.5, offsets_deg: dict | None = None):
    """One trial: ``(verification unmoved, verification moved, move)`` (module docstring)."""
    rng = np.random.default_rng(seed)
    stored_dict, truth = simulate_arm("arm6", placements=3, arm_poses=stored_poses, pixel_sigma=pixel_sigma,
                                      joint_offsets_deg=offsets_deg, seed=seed)
    stored = calibrate(render_arm(stored_dict, truth, role, np.zeros(6), pixel_sigma, rng, "stored"))
    new_dict, new_truth = simulate_arm("arm6", placements=new_placements, arm_poses=new_poses, pixel_sigma=pixel_sigma,
                                       joint_offsets_deg=offsets_deg, seed=seed + 1)
    exact = verify(stored, render_arm(new_dict, new_truth, role, np.zeros(6), 0.0, None, "exact"), alpha=alpha)
    combined = exact.cameras[role].covariance
    assert combined is not None, "the new images determine the mount"
    move = move_sigmas * np.sqrt(np.diag(combined)) * rng.choice([-1.0, 1.0], size=6)
    still = verify(stored, render_arm(new_dict, new_truth, role, np.zeros(6), pixel_sigma, rng, "new"), alpha=alpha)
    moved = verify(stored, render_arm(new_dict, new_truth, role, move, pixel_sigma, rng, "moved"), alpha=alpha)
    return still, moved, move


def arm_power_study(trials: int = 200, seed: int = 0, role: str = "camera", **options) -> ArmPowerFigures:
    """:func:`arm_trial` ``trials`` times, each with its own scene, stored data and noise."""
    rng = np.random.default_rng(seed)
    alpha = options.get("alpha", 0.01)
    still_counts: dict[str, int] = {}
    moved_counts: dict[str, int] = {}
    d2, dofs = [], []
    for _ in range(trials):
        still, moved, _ = arm_trial(int(rng.integers(0, 2**31 - 2)), role, **options)
        entry = still.cameras[role]
        still_counts[entry.verdict] = still_counts.get(entry.verdict, 0) + 1
        d2.append(entry.mahalanobis2)
        dofs.append(entry.dof)
        verdict = moved.cameras[role].verdict
        moved_counts[verdict] = moved_counts.get(verdict, 0) + 1
    return ArmPowerFigures(trials, alpha, options.get("move_sigmas", 3.0), still_counts.get(MOVED, 0),
                           moved_counts.get(MOVED, 0), still_counts, moved_counts, tuple(d2), tuple(dofs))
