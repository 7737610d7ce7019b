"""A camera mount's 3-sigma through one hand-held mirror against a direct-view hand-eye calibration with the
same number of images, on simulated arms (docs/formats.md, "Robot arms: joint states and mounts").

Both are the MLE's covariance (solver/robot_solve.py) at the simulated truth, averaged over seeds; the
direct view sees the board 0.9 m ahead (about the mirror's light path), the mirror scenes 3 or 4 placements.
Run: PYTHONPATH=. python scripts/robot_mirror_vs_direct.py [--images 24] [--seeds 5]
"""
from __future__ import annotations

import argparse
import os
import tempfile

import numpy as np

from mirror_fg.io.dataset import load_dataset
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation
from mirror_fg.solver.robot_solve import calibrate_robot
from mirror_fg.solver.robot_views import RobotEstimate


def sigma3(robot: str, eye_in_hand: bool, placements: int, images: int, seed: int, folder: str) -> np.ndarray:
    """[rotation 3-sigma (deg) x3, position 3-sigma (mm) x3] of the camera's mount, at the truth."""
    direct = placements == 0
    dataset, truth = simulate_arm(robot, eye_in_hand, placements=max(placements, 1),
                                  arm_poses=images if direct else images // placements, pixel_sigma=0.5,
                                  seed=seed, direct=direct)
    path = os.path.join(folder, f"{robot}_{placements}_{seed}.json")
    write_arm_simulation(path, dataset, truth)
    start = RobotEstimate({role: pose for role, (_, pose) in truth.mounts.items()}, dict(truth.mirror_vectors))
    entry = calibrate_robot(load_dataset(path), initial=start).robot["mounts"]["camera"]["sigma3"]
    return np.array(entry["rotation_deg"] + entry["position_mm"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=24)
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        for robot, eye_in_hand in (("arm6", False), ("panda", True)):
            setup = f"{robot} {'eye-in-hand' if eye_in_hand else 'eye-to-hand'}"
            rows = {}
            for placements in (0, 3, 4):
                values = np.mean([sigma3(robot, eye_in_hand, placements, args.images, s, folder)
                                  for s in range(args.seeds)], axis=0)
                rows[placements] = values
                name = "direct view" if placements == 0 else f"mirror, {placements} placements"
                print(f"{setup:22s} {name:22s} {args.images} images: camera mount 3-sigma rotation "
                      f"{np.round(values[:3], 3).tolist()} deg, position {np.round(values[3:], 2).tolist()} mm "
                      f"(largest {values[:3].max():.3f} deg, {values[3:].max():.2f} mm)")
            for placements in (3, 4):
                ratio = rows[placements] / rows[0]
                print(f"{setup:22s} mirror/direct at {placements} placements: rotation x{ratio[:3].max():.2f}, "
                      f"position x{ratio[3:].max():.2f} (largest axis ratio)")


if __name__ == "__main__":
    main()
