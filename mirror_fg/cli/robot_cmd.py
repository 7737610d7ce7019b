"""``mirror-fg simulate --robot arm6|panda [--arm-poses N] [--eye-in-hand]``: a simulated robot arm seen
through hand-held mirrors (docs/formats.md, "Robot arms: joint states and mounts"); its arguments and runner,
registered by ``parser.py`` and ``commands.cmd_simulate``."""
from __future__ import annotations

import argparse

from mirror_fg.cli.printing import EXIT_OK, _Printer
from mirror_fg.core.errors import DatasetError

__all__ = ["add_robot_arguments", "simulate_robot"]

ARMS = ("arm6", "panda")


def add_robot_arguments(sim: argparse.ArgumentParser) -> None:
    """``--robot``, ``--arm-poses``, ``--eye-in-hand`` on ``simulate``."""
    sim.add_argument("--robot", choices=ARMS,
                     help="a robot arm (arm6: UR5-like, panda: Panda-like, URDF written beside the data) whose camera "
                     "or target is calibrated through --placements N hand-held mirror placements (default 3)")
    sim.add_argument("--arm-poses", type=int, default=8, metavar="N",
                     help="with --robot: arm poses per mirror placement (default 8)")
    sim.add_argument("--eye-in-hand", action="store_true",
                     help="with --robot: the camera on the tool, the target on the base (default: the camera on the "
                     "base, the target on the tool)")


def simulate_robot(args, out: _Printer) -> int:
    """Write the arm's dataset, its truth and its URDF."""
    from mirror_fg.robot.simulate import arm_outputs, simulate_arm, write_arm_simulation

    placements = 3 if args.placements is None else args.placements
    try:
        placements = int(placements)
    except ValueError:
        raise DatasetError(f"--placements: with --robot one number of mirror placements, got {placements!r}") from None
    if placements < 3:
        raise DatasetError(f"--placements: a robot arm needs 3 or more mirror placements, got {placements}")
    if args.arm_poses < 3:
        raise DatasetError(f"--arm-poses: 3 or more arm poses per placement, got {args.arm_poses}")
    path = str(args.output)
    plan = arm_outputs(path, args.robot)  # checked before the work
    dataset, truth = simulate_arm(args.robot, args.eye_in_hand, placements, args.arm_poses, args.sigma, seed=args.seed)
    truth_file, urdf = write_arm_simulation(path, dataset, truth, plan)
    setup = "eye-in-hand" if args.eye_in_hand else "eye-to-hand"
    out.info(f"wrote {path} ({len(dataset['images'])} images of {args.robot}, {setup}, {placements} mirror placements), "
             f"{truth_file} and {urdf}")
    return EXIT_OK
