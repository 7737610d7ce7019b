"""The cost of calibrating 1,000 images of an arm (3 mirror placements, a 6 x 5 chessboard: 30 corners an
image) against 1,000 images of the paper's tree (3 fiducials an image), each timed by stage: the screen
(consensus.screen: one PnP per image), the arm's solve (start, LM, covariances) and the whole calibrate().
Each stage is timed twice: the process's CPU time (``time.process_time``: what the ratio is taken from, as it
does not count the time other processes hold the cores; a loaded machine still slows it a little) and the
wall-clock time.
Run: PYTHONPATH=. python scripts/robot_cost.py [--images 1000]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

from mirror_fg.io.dataset import load_dataset
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.consensus import screen
from mirror_fg.solver.robot_solve import solve_robot
from mirror_fg.tools.simulate import simulate_base_case


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=1000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        dataset, truth = simulate_arm("arm6", False, placements=4, arm_poses=args.images // 4, seed=5, spread_rad=0.3)
        path = os.path.join(folder, "arm.json")
        write_arm_simulation(path, dataset, truth)
        arm = load_dataset(path)
        tree, _ = simulate_base_case(num_images=args.images, seed=1)
        cpu, wall = {}, {}
        for name, call in (("arm: screen", lambda: screen(arm)), ("arm: solve", lambda: solve_robot(arm)),
                           ("arm: calibrate", lambda: calibrate(arm)), ("tree: calibrate", lambda: calibrate(tree))):
            start, start_wall = time.process_time(), time.perf_counter()
            call()
            cpu[name], wall[name] = time.process_time() - start, time.perf_counter() - start_wall
            print(f"{name:16s} {cpu[name]:7.2f} s CPU {wall[name]:7.2f} s wall")
        print(f"arm / tree: x{cpu['arm: calibrate'] / cpu['tree: calibrate']:.1f} CPU "
              f"(x{wall['arm: calibrate'] / wall['tree: calibrate']:.1f} wall) "
              f"({len(arm.images)} arm images of 30 corners, {len(tree.images)} tree images of 3 fiducials)")


if __name__ == "__main__":
    main()
