"""``mirror-fg simulate --robot arm6|panda [--arm-poses N] [--eye-in-hand] [--cameras N]``: a simulated robot arm seen
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
    cameras = getattr(args, "cameras", None) or 1
    dataset, truth = simulate_arm(args.robot, args.eye_in_hand, placements, args.arm_poses, args.sigma, seed=args.seed,
                                  cameras=cameras)
    truth_file, urdf = write_arm_simulation(path, dataset, truth, plan)
    setup = "eye-in-hand" if args.eye_in_hand else "eye-to-hand"
    if cameras > 1:
        setup += f", {cameras} cameras on {'the tool' if args.eye_in_hand else 'the base'}"
    out.info(f"wrote {path} ({len(dataset['images'])} images of {args.robot}, {setup}, {placements} mirror placements), "
             f"{truth_file} and {urdf}")
    return EXIT_OK


def add_robot_plan_arguments(pln: argparse.ArgumentParser) -> None:
    """``--robot``, ``--eye-in-hand``, ``--arm-poses``, ``--joint-candidates`` on ``plan``."""
    pln.add_argument("--robot", choices=ARMS,
                     help="the Cramer-Rao bounds of a robot-arm set-up: --placements mirror placements x --arm-poses "
                     "arm poses (the camera on the base, the target on the tool; --eye-in-hand the other way)")
    pln.add_argument("--arm-poses", type=int, default=8, metavar="N", help="with --robot: arm poses per placement")
    pln.add_argument("--eye-in-hand", action="store_true", help="with --robot: the camera on the tool")
    pln.add_argument("--joint-candidates", type=str, metavar="CSV",
                     help="with --next DATA of a robot arm: reachable joint configurations (a header of joint names, "
                     "one row each), ranked by the camera mount's predicted 3-sigma with the mirror where it stands")


def plan_robot(args, out: _Printer) -> int:
    """``plan --robot ...`` (the bounds of a set-up) or ``plan --next DATA --joint-candidates CSV``."""
    import json

    import numpy as np

    from mirror_fg.robot.plan import arm_bounds, load_joint_candidates, rank_joint_candidates

    if args.joint_candidates is not None:
        if args.next_data is None:
            raise DatasetError("plan: --joint-candidates goes with --next DATA (the arm's data so far)")
        from mirror_fg.io.dataset import load_dataset

        dataset = load_dataset(args.next_data)
        if dataset.robot is None:
            raise DatasetError(f"{args.next_data}: --joint-candidates needs data of a robot arm (robot, mounts, joints)")
        if dataset.robot.cameras is not None:
            raise DatasetError(f"{args.next_data}: --joint-candidates ranks arm poses for one camera; these data have "
                               f"{len(dataset.robot.cameras)} (cameras)")
        candidates = load_joint_candidates(args.joint_candidates, dataset.robot.joints)
        ranked, now = rank_joint_candidates(dataset, candidates)
        l, m = now["placement"]
        out.info(f"the {now['mount']} mount now: 3-sigma position {np.round(now['position_mm'], 2).tolist()} mm, "
                 f"rotation {np.round(now['rotation_deg'], 3).tolist()} deg; next arm pose with the mirror at "
                 f"mirror {l} placement {m} ({len(ranked)} of {len(candidates)} candidates would see the target):")
        for k, c in enumerate(ranked[:args.count], start=1):
            out.info(f"{k}. row {c.row}: position {np.round(c.position_mm, 2).tolist()} mm, rotation "
                     f"{np.round(c.rotation_deg, 3).tolist()} deg  ({', '.join(f'{n}={v:.4g}' for n, v in c.joints.items())})")
        if args.json is not None:
            rows = [{"row": c.row, "joints": c.joints, "position_mm": c.position_mm.tolist(),
                     "rotation_deg": c.rotation_deg.tolist()} for c in ranked]
            args.json.write_text(json.dumps({"mount": now["mount"], "candidates": rows}, indent=1))
        return EXIT_OK
    if args.arm_poses < 3:
        raise DatasetError(f"--arm-poses: 3 or more arm poses per placement, got {args.arm_poses}")
    cameras = getattr(args, "cameras", None) or 1
    bounds = arm_bounds(args.robot, args.eye_in_hand, args.placements, args.arm_poses, args.sigma or 1.0,
                        draws=args.draws, seed=args.seed, cameras=cameras)
    setup = "eye-in-hand" if args.eye_in_hand else "eye-to-hand"
    out.info(f"{args.robot} {setup}, {args.placements} mirror placements x {args.arm_poses} arm poses, "
             f"{args.sigma or 1.0} px (Cramer-Rao, {args.draws} draws):")
    for role, b in bounds.items():
        role = role.replace("camera:", "camera ")  # several cameras: "camera cam0"
        out.info(f"  {role} mount 3-sigma: rotation {np.round(b['rotation_deg'], 3).tolist()} deg, position "
                 f"{np.round(b['position_mm'], 2).tolist()} mm")
    if args.json is not None:
        args.json.write_text(json.dumps(bounds, indent=1))
    return EXIT_OK
