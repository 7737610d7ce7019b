"""The cost of calibrating 1,000 images of an arm (4 mirror placements, a 6 x 5 chessboard: 30 corners an
image) against 1,000 images of the paper's tree (3 fiducials an image), each timed by stage: the arm's
screen (one PnP per image, ``robot_solve.lowest_pnp_minima``), its solve (start, LM, covariances) and the
whole calibrate(). The stages are run in turn ``--repeats`` times, each one's least time kept, as the
process's CPU time (``time.process_time``: what the ratio is taken from, as it does not count the time
other processes hold the cores; a loaded machine still slows it a little) and as wall-clock time.
Run: PYTHONPATH=. python scripts/robot_cost.py [--images 1000] [--repeats 3]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

from mirror_fg.io.dataset import load_dataset
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.simulate.tree import simulate_base_case
from mirror_fg.solver.batch.robot_solve import RobotPipelineProblem, solve_robot
from mirror_fg.solver.options import SolveOptions


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        dataset, truth = simulate_arm("arm6", False, placements=4, arm_poses=args.images // 4, seed=5, spread_rad=0.3)
        path = os.path.join(folder, "arm.json")
        write_arm_simulation(path, dataset, truth)
        arm = load_dataset(path)
        tree, _ = simulate_base_case(num_images=args.images, seed=1)
        cpu, wall = {}, {}
        stages = (("arm: screen", lambda: RobotPipelineProblem(None, SolveOptions()).screen(arm)),
                  ("arm: solve", lambda: solve_robot(arm)), ("arm: calibrate", lambda: calibrate(arm)),
                  ("tree: calibrate", lambda: calibrate(tree)))
        for _ in range(args.repeats):  # the stages in turn, so that a change of load touches them alike
            for name, call in stages:
                start, start_wall = time.process_time(), time.perf_counter()
                call()
                cpu[name] = min(cpu.get(name, float("inf")), time.process_time() - start)
                wall[name] = min(wall.get(name, float("inf")), time.perf_counter() - start_wall)
        for name, _ in stages:
            print(f"{name:16s} {cpu[name]:7.2f} s CPU {wall[name]:7.2f} s wall")
        print(f"arm / tree: x{cpu['arm: calibrate'] / cpu['tree: calibrate']:.2f} CPU "
              f"(x{wall['arm: calibrate'] / wall['tree: calibrate']:.2f} wall) "
              f"({len(arm.images)} arm images of 30 corners, {len(tree.images)} tree images of 3 fiducials)")


if __name__ == "__main__":
    main()
