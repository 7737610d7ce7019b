"""A camera mount's 3-sigma through one hand-held mirror against a direct-view hand-eye calibration with the
same number of images, on simulated arms (docs/formats.md, "Robot arms: joint states and mounts").

Both are the MLE's covariance (solver/batch/robot_solve.py) at the simulated truth, averaged over seeds. The
direct view is as good as a user could make it: the board at each of several distances ahead of the camera
(0.35 m fills about a third of the image; closer, the arm poses' spread takes it out of view), the best one
kept (the smallest largest 3-sigma); the mirror scenes are those of ``simulate --robot`` (eye-to-hand: the
board on the tool 0.3 m in front of the camera, the mirror 0.45-0.6 m ahead, tilted 6-14 degrees) at 3 or
4 placements.
Run: PYTHONPATH=. python scripts/robot_mirror_vs_direct.py [--images 24] [--seeds 5]
"""
from __future__ import annotations

import argparse
import os
import tempfile

import numpy as np

from mirror_fg.io.dataset import load_dataset
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation
from mirror_fg.solver.batch.robot_solve import calibrate_robot
from mirror_fg.solver.model.robot_views import RobotEstimate

#: Board distances (metres) a user might hold the board at in front of the camera for a direct view.
DIRECT_DISTANCES = (0.35, 0.45, 0.6, 0.9)


def sigma3(robot: str, eye_in_hand: bool, placements: int, images: int, seed: int, folder: str,
           distance: float = 0.9) -> np.ndarray:
    """[rotation 3-sigma (deg) x3, position 3-sigma (mm) x3] of the camera's mount, at the truth."""
    direct = placements == 0
    dataset, truth = simulate_arm(robot, eye_in_hand, placements=max(placements, 1),
                                  arm_poses=images if direct else images // placements, pixel_sigma=0.5,
                                  seed=seed, direct=direct, direct_distance=distance)
    path = os.path.join(folder, f"{robot}_{placements}_{seed}_{distance}.json")
    write_arm_simulation(path, dataset, truth)
    start = RobotEstimate({role: pose for role, (_, pose) in truth.mounts.items()}, dict(truth.mirror_vectors))
    entry = calibrate_robot(load_dataset(path), initial=start).robot["mounts"]["camera"]["sigma3"]
    return np.array(entry["rotation_deg"] + entry["position_mm"])


def _line(setup: str, name: str, images: int, values: np.ndarray) -> str:
    return (f"{setup:22s} {name:28s} {images} images: camera mount 3-sigma rotation "
            f"{np.round(values[:3], 3).tolist()} deg, position {np.round(values[3:], 2).tolist()} mm "
            f"(largest {values[:3].max():.3f} deg, {values[3:].max():.2f} mm)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=24)
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        for robot, eye_in_hand in (("arm6", False), ("panda", True)):
            setup = f"{robot} {'eye-in-hand' if eye_in_hand else 'eye-to-hand'}"
            direct = {}
            for distance in DIRECT_DISTANCES:
                direct[distance] = np.mean([sigma3(robot, eye_in_hand, 0, args.images, s, folder, distance)
                                            for s in range(args.seeds)], axis=0)
                print(_line(setup, f"direct view, board {distance:.2f} m", args.images, direct[distance]))
            best = min(direct, key=lambda d: (direct[d][3:].max() / direct[0.9][3:].max()
                                              + direct[d][:3].max() / direct[0.9][:3].max()))
            rows = {0: direct[best]}
            for placements in (3, 4):
                rows[placements] = np.mean([sigma3(robot, eye_in_hand, placements, args.images, s, folder)
                                            for s in range(args.seeds)], axis=0)
                print(_line(setup, f"mirror, {placements} placements", args.images, rows[placements]))
            for placements in (3, 4):
                for name, base in ((f"the best direct view ({best:.2f} m)", direct[best]),
                                   ("the direct view at 0.9 m", direct[0.9])):
                    ratio = rows[placements] / base
                    print(f"{setup:22s} mirror at {placements} placements / {name}: rotation x{ratio[:3].max():.2f}, "
                          f"position x{ratio[3:].max():.2f} (largest axis ratio)")


if __name__ == "__main__":
    main()
