"""plan --next --joint-candidates against random arm poses (docs/formats.md, "Robot arms"): from a few
images (3 placements x 3 arm poses), arm poses are added one at a time through the mirror where it stands
(the last placement), either the best-ranked of a pool of reachable candidates (robot/plan.py) or a
random visible one; how many images each needs to bring the camera mount's position 3-sigma (norm) to the
bound random poses reach after --random-images images. Information at the solution of the first images
(the bounds of a solve with the images added, noise-free: tests/test_robot_plan.py).
Run: PYTHONPATH=. python scripts/robot_plan_next_study.py [--robot panda --eye-in-hand] [--seeds 5]
"""
from __future__ import annotations

import argparse
import os
import tempfile

import numpy as np

from mirror_fg.io.dataset import load_dataset
from mirror_fg.robot.plan import candidate_jacobian, mount_bounds
from mirror_fg.robot.simulate import NOMINAL, simulate_arm, write_arm_simulation
from mirror_fg.solver.batch.robot_solve import solve_robot


def run(robot: str, eye_in_hand: bool, seed: int, pool: int, random_images: int, folder: str) -> tuple[int, int]:
    dataset, truth = simulate_arm(robot, eye_in_hand, placements=3, arm_poses=3, pixel_sigma=0.5, seed=seed)
    path = os.path.join(folder, f"study{seed}.json")
    write_arm_simulation(path, dataset, truth)
    data = load_dataset(path)
    solution = solve_robot(data)
    placement = data.images[-1].reflections[-1]
    assert data.robot is not None
    names = data.robot.joints
    rng = np.random.default_rng(1000 + seed)
    jacobians = []
    for _ in range(pool):
        joints = dict(zip(names, np.array(NOMINAL[robot]) + rng.uniform(-0.3, 0.3, len(names))))
        J = candidate_jacobian(solution, data, joints, placement)
        if J is not None:
            jacobians.append(J.T @ J)
    role = "camera"

    def bound(information):
        return float(np.linalg.norm(mount_bounds(solution, information, role)[1]))

    information = solution.information.copy()
    for k in rng.permutation(len(jacobians))[:random_images]:
        information = information + jacobians[k]
    target = bound(information)
    information, left, greedy = solution.information.copy(), list(range(len(jacobians))), 0
    while bound(information) > target and left:
        best = min(left, key=lambda k: bound(information + jacobians[k]))
        information = information + jacobians[best]
        left.remove(best)
        greedy += 1
    return greedy, random_images


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="panda", choices=["arm6", "panda"])
    parser.add_argument("--eye-in-hand", action="store_true")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--pool", type=int, default=150)
    parser.add_argument("--random-images", type=int, default=15)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        counts = [run(args.robot, args.eye_in_hand, s, args.pool, args.random_images, folder) for s in range(args.seeds)]
    greedy = np.array([g for g, _ in counts])
    print(f"{args.robot} {'eye-in-hand' if args.eye_in_hand else 'eye-to-hand'}: to the camera mount's 3-sigma that "
          f"{args.random_images} random arm poses reach, plan --next needs {greedy.tolist()} images "
          f"(mean {greedy.mean():.1f}, {100 * (1 - greedy.mean() / args.random_images):.0f} % fewer)")


if __name__ == "__main__":
    main()
