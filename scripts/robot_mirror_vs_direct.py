"""A camera mount's 3-sigma through one hand-held mirror against a direct-view hand-eye calibration with the
same number of images, on simulated arms (docs/formats.md, "Robot arms: joint states and mounts"), for
several mirror set-ups.

All figures are the MLE's covariance (solver/batch/robot_solve.py) at the simulated truth, averaged over seeds,
0.5 px, the 6 x 5 chessboard of ``simulate --robot``. The direct views: the board at each of several
distances ahead of the camera (0.35 m fills about a third of the image; closer, the arm poses' spread
takes it out of view); "best" is the one with the smallest largest 3-sigma. The mirror set-ups (the board
where ``simulate --robot`` puts it: eye-to-hand on the tool 0.3 m in front of the camera and 0.15 m to its
side, eye-in-hand on the base beside the wrist camera):

* poor: the mirror 0.45-0.6 m ahead, its normal 6-14 deg from the camera's axis (``simulate``'s default):
  the placements' planes nearly parallel;
* bench: the mirror 0.5 m ahead, tilted 20-30 deg, each placement turned a further quarter turn about the
  camera's axis (30-60 deg between placements' normals), as a user holds it at arm's length;
* bench, 1 m: the same with the mirror 1 m ahead;
* close: the mirror 0.3-0.35 m ahead, tilted 20-30 deg (eye-to-hand, the board on the tool then a few
  centimetres in front of the glass);
* near: the board beside the camera (eye-to-hand on the tool 0.15 m aside and 5 cm ahead; eye-in-hand where
  ``simulate --robot`` puts it), the mirror 0.2-0.25 m ahead tilted 10-20 deg, or 0.3-0.35 m tilted 20-30 deg.

Every mirror set-up keeps only arm poses where the board's plate does not stand in the camera's line of
sight to the mirror (``simulate_arm``'s ``check_occlusion``); a set-up where no arm pose is left is printed
as blocked.

Each mirror row is also compared with a direct view at the distance of the board's image in the mirror
(camera to the reflected board's centre, the mean over the images): what the mirror's model costs
beyond the longer light path. The last figure, "planes known", is the mount's 3-sigma from the same images
were the placements' planes given; the line after it names the turn of the camera mount whose variance the
unknown planes inflate most (its axis in the camera's frame) and the share of that turn's information they
take (1 - planes-known variance / variance).
``--chosen`` adds, for the near set-ups at 4 placements, the arm poses chosen rather than drawn
(:func:`chosen_camera_mount`), for the mirror and the best direct view alike.
Run: PYTHONPATH=. python scripts/robot_mirror_vs_direct.py [--images 24] [--seeds 5] [--chosen]
"""
from __future__ import annotations

import argparse
import os
import tempfile

import numpy as np

from mirror_fg.core.transform import covariance_from_pose3
from mirror_fg.factors.robot import compose
from mirror_fg.io.dataset import load_dataset
from mirror_fg.robot import arm_urdf
from mirror_fg.robot.kinematics import load_kinematics
from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation
from mirror_fg.solver.batch.robot_solve import solve_robot
from mirror_fg.solver.model.robot_views import RobotEstimate

#: Board distances (metres) a user might hold the board at in front of the camera for a direct view.
DIRECT_DISTANCES = (0.35, 0.45, 0.6, 0.9)
#: Eye-to-hand, the board on the tool beside the camera (camera frame at the nominal pose, metres).
BESIDE = (0.15, 0.0, 0.05)
#: name: (mirror distance range (m), tilt range (deg), the eye-to-hand board's position or None: where
#: ``simulate_arm`` puts it) -- module docstring.
SETUPS = {
    "poor: mirror 0.45-0.6 m, tilt 6-14 deg": ((0.45, 0.6), (6.0, 14.0), None),
    "bench: mirror 0.5 m, tilt 20-30 deg": ((0.5, 0.5), (20.0, 30.0), None),
    "bench: mirror 1 m, tilt 20-30 deg": ((1.0, 1.0), (20.0, 30.0), None),
    "close: mirror 0.3-0.35 m, tilt 20-30 deg": ((0.3, 0.35), (20.0, 30.0), None),
    "near: mirror 0.2-0.25 m, tilt 10-20 deg": ((0.2, 0.25), (10.0, 20.0), BESIDE),
    "near: mirror 0.3-0.35 m, tilt 20-30 deg": ((0.3, 0.35), (20.0, 30.0), BESIDE),
}


def _sigma3(covariance: np.ndarray, R: np.ndarray) -> np.ndarray:
    s = 3.0 * np.sqrt(np.diag(covariance_from_pose3(R, covariance)))
    return np.concatenate([np.degrees(s[:3]), 1000.0 * s[3:]])


def _board_distance(dataset: dict, truth) -> float:
    """Mean distance (m) from the camera to the board's centre as the camera sees it (through the mirror)."""
    kin = load_kinematics(arm_urdf(truth.robot))
    (link_c, mount_c), (link_t, mount_t) = truth.mounts["camera"], truth.mounts["target"]
    distances = []
    for image in dataset["images"]:
        F = kin.placements(image["joints"], list({link_c, link_t}))
        C = compose((F[link_c][0][:3, :3], F[link_c][0][:3, 3]), mount_c)
        x = compose((F[link_t][0][:3, :3], F[link_t][0][:3, 3]), mount_t)[1]  # the board's centre, {B}
        for k in image.get("mirror_configs", []):
            v = truth.mirror_vectors[(1, k)]
            x = x - 2.0 * v * ((v @ x) / (v @ v) - 1.0)  # eq. (3)
        distances.append(float(np.linalg.norm(x - C[1])))
    return float(np.mean(distances))


def camera_mount(robot: str, eye_in_hand: bool, placements: int, images: int, seed: int, folder: str,
                 distance: float = 0.9, setup: tuple | None = None, mirror_size: tuple[float, float] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, float, tuple[np.ndarray, float]]:
    """The camera mount's 3-sigma ``[rotation (deg) x3, position (mm) x3]`` at the truth, the same with the
    planes known, the board's distance as seen and the mount's turn the planes take most of (its axis in
    the camera's frame, the share of its information they take); ``placements`` 0: the direct view at
    ``distance``. ``mirror_size``: the glass's width and height (metres; None: no edges). RuntimeError where
    no arm pose sees the board."""
    direct = placements == 0
    mirror: dict = {} if setup is None else {"mirror_distance": setup[0], "mirror_tilt_deg": setup[1],
                                             "check_occlusion": True, "mirror_size": mirror_size}
    if setup is not None and setup[2] is not None and not eye_in_hand:
        mirror["board_position"] = setup[2]
    dataset, truth = simulate_arm(robot, eye_in_hand, placements=max(placements, 1),
                                  arm_poses=images if direct else images // placements, pixel_sigma=0.5,
                                  seed=seed, direct=direct, direct_distance=distance, **mirror)
    path = os.path.join(folder, f"{robot}_{placements}_{seed}.json")
    write_arm_simulation(path, dataset, truth)
    start = RobotEstimate({role: pose for role, (_, pose) in truth.mounts.items()}, dict(truth.mirror_vectors))
    solution = solve_robot(load_dataset(path), initial=start)
    problem, information, columns = solution.problem, solution.information, solution.columns
    R = solution.estimate.mounts["camera"][0]
    c = columns[problem.mount_keys["camera"]]
    marginal = _sigma3(np.linalg.inv(information)[c, c], R)
    keep = np.array([i for key, cols in columns.items() if key not in problem.mirror_keys.values()
                     for i in range(cols.start, cols.stop)])  # every unknown but the planes
    at = {i: k for k, i in enumerate(keep)}
    mount = [at[i] for i in range(c.start, c.stop)]
    known_cov = np.linalg.inv(information[np.ix_(keep, keep)])[np.ix_(mount, mount)]
    known_planes = _sigma3(known_cov, R)
    # the turn (Pose3 tangent: the camera's frame) of largest variance ratio, planes unknown / known
    L = np.linalg.cholesky(known_cov[:3, :3])
    ratios, axes = np.linalg.eigh(np.linalg.solve(L, np.linalg.solve(L, np.linalg.inv(information)[c, c][:3, :3]).T))
    axis = np.linalg.solve(L.T, axes[:, -1])
    taken = (axis / np.linalg.norm(axis), 1.0 - 1.0 / ratios[-1]) if not direct else (np.zeros(3), 0.0)
    return marginal, known_planes, _board_distance(dataset, truth) if not direct else distance, taken


def chosen_camera_mount(robot: str, eye_in_hand: bool, placements: int, images: int, seed: int, folder: str,
                        reference: np.ndarray, distance: float = 0.35, setup: tuple | None = None,
                        pool: int = 5, mirror_size: tuple[float, float] | None = None) -> np.ndarray:
    """The camera mount's 3-sigma (as :func:`camera_mount`'s, at the truth) from ``images`` arm poses chosen
    among ``pool`` times as many visible ones: two (direct: four) per placement drawn, then one at a time
    the one that most lowers the larger of the largest rotation and position 3-sigma over ``reference``'s
    (what ``plan --next`` does with the data's estimate, here at the truth: a bound on what it can reach)."""
    import gtsam

    from mirror_fg.solver.model.robot_views import RobotProblem

    direct = placements == 0
    mirror: dict = {} if setup is None else {"mirror_distance": setup[0], "mirror_tilt_deg": setup[1],
                                             "check_occlusion": True, "mirror_size": mirror_size}
    if setup is not None and setup[2] is not None and not eye_in_hand:
        mirror["board_position"] = setup[2]
    per = images if direct else images // placements
    dataset, truth = simulate_arm(robot, eye_in_hand, placements=max(placements, 1), arm_poses=pool * per,
                                  pixel_sigma=0.5, seed=seed, direct=direct, direct_distance=distance, **mirror)
    path = os.path.join(folder, f"{robot}_{placements}_{seed}_pool.json")
    write_arm_simulation(path, dataset, truth)
    problem = RobotProblem(load_dataset(path))
    values = problem.values(RobotEstimate({role: pose for role, (_, pose) in truth.mounts.items()},
                                          dict(truth.mirror_vectors)))
    graph = gtsam.NonlinearFactorGraph()
    for factor in problem.factors:  # one factor per image: the rows of each image together, in order
        graph.add(factor.factor())
    ordering, columns, start = gtsam.Ordering(), {}, 0
    for key in problem.keys:
        ordering.push_back(key)
        columns[key] = slice(start, start + (6 if key in problem.mount_keys.values() else 3))
        start += columns[key].stop - columns[key].start
    A, _ = graph.linearize(values).jacobian(ordering)
    rows = np.cumsum([0] + [2 * len(im.observations) for im in problem.dataset.images])
    blocks = [A[rows[i]:rows[i + 1]].T @ A[rows[i]:rows[i + 1]] for i in range(len(rows) - 1)]
    c, R = columns[problem.mount_keys["camera"]], truth.mounts["camera"][1][0]

    def sigma3(information: np.ndarray) -> np.ndarray:
        return _sigma3(np.linalg.inv(information)[c, c], R)

    def score(information: np.ndarray) -> float:
        try:
            s3 = sigma3(information)
        except np.linalg.LinAlgError:
            return float("inf")
        return float(max(s3[:3].max() / reference[:3].max(), s3[3:].max() / reference[3:].max()))

    group = [im.reflections[0] if im.reflections else 0 for im in problem.dataset.images]
    chosen = [i for g in sorted(set(group)) for i in [k for k in range(len(group)) if group[k] == g][:4 if direct else 2]]
    information = np.sum([blocks[i] for i in chosen], axis=0)
    while len(chosen) < images:
        best = min((i for i in range(len(blocks)) if i not in chosen), key=lambda i: score(information + blocks[i]))
        chosen.append(best)
        information = information + blocks[best]
    return sigma3(information)


def _line(setup: str, name: str, images: int, values: np.ndarray) -> str:
    return (f"{setup:22s} {name:46s} {images} images: camera mount 3-sigma rotation "
            f"{np.round(values[:3], 3).tolist()} deg, position {np.round(values[3:], 2).tolist()} mm "
            f"(largest {values[:3].max():.3f} deg, {values[3:].max():.2f} mm)")


def _ratio(a: np.ndarray, b: np.ndarray) -> str:
    return f"rotation x{a[:3].max() / b[:3].max():.2f}, position x{a[3:].max() / b[3:].max():.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=24)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--chosen", action="store_true",
                        help="also the arm poses chosen by their predicted bound (chosen_camera_mount), near set-ups")
    parser.add_argument("--mirror-size", type=float, nargs=2, metavar=("WIDTH", "HEIGHT"),
                        help="a glass of this size (metres): arm poses whose board is not seen within it are left out")
    parser.add_argument("--only", default="", help="only the set-ups whose name contains this text")
    parser.add_argument("--arm", choices=("arm6", "panda"), help="only this arm (arm6 eye-to-hand, panda eye-in-hand)")
    args = parser.parse_args()
    size = tuple(args.mirror_size) if args.mirror_size else None
    seeds = range(args.seeds)
    with tempfile.TemporaryDirectory() as folder:
        for robot, eye_in_hand in (("arm6", False), ("panda", True)):
            if args.arm and robot != args.arm:
                continue
            arm = f"{robot} {'eye-in-hand' if eye_in_hand else 'eye-to-hand'}"
            direct: dict[float, np.ndarray] = {}

            def direct_at(distance: float) -> np.ndarray:
                distance = round(distance, 2)
                if distance not in direct:
                    direct[distance] = np.mean([camera_mount(robot, eye_in_hand, 0, args.images, s, folder, distance)[0]
                                                for s in seeds], axis=0)
                    print(_line(arm, f"direct view, board {distance:.2f} m", args.images, direct[distance]))
                return direct[distance]

            for distance in DIRECT_DISTANCES:
                direct_at(distance)
            best = min(DIRECT_DISTANCES, key=lambda d: direct[d][:3].max() / direct[0.9][:3].max()
                       + direct[d][3:].max() / direct[0.9][3:].max())
            for name, setup in SETUPS.items():
                if args.only not in name:
                    continue
                for placements in (3, 4):
                    try:
                        runs = [camera_mount(robot, eye_in_hand, placements, args.images, s, folder, setup=setup,
                                             mirror_size=size) for s in seeds]
                    except RuntimeError:
                        print(f"{arm:22s} {name}, {placements} placements: blocked (no arm pose sees the board "
                              "through the mirror past the board itself, inside the image)")
                        continue
                    mirror = np.mean([r[0] for r in runs], axis=0)
                    known = np.mean([r[1] for r in runs], axis=0)
                    seen = float(np.mean([r[2] for r in runs]))
                    axis = np.mean([r[3][0] * np.sign(r[3][0][np.argmax(np.abs(r[3][0]))]) for r in runs], axis=0)
                    print(_line(arm, f"{name}, {placements} placements", args.images, mirror))
                    same_path = direct_at(0.05 * round(float(seen) / 0.05))
                    print(f"{arm:22s}   board seen {float(seen):.2f} m away; / best direct view ({best:.2f} m): "
                          f"{_ratio(mirror, direct[best])}; / direct view at {0.05 * round(float(seen) / 0.05):.2f} m: "
                          f"{_ratio(mirror, same_path)}; planes known: {known[:3].max():.3f} deg, "
                          f"{known[3:].max():.2f} mm")
                    if args.chosen and name.startswith("near") and placements == 4:
                        picked = np.mean([chosen_camera_mount(robot, eye_in_hand, placements, args.images, s, folder,
                                                              direct[best], setup=setup, mirror_size=size)
                                          for s in seeds], axis=0)
                        picked_direct = np.mean([chosen_camera_mount(robot, eye_in_hand, 0, args.images, s, folder,
                                                                     direct[best], best) for s in seeds], axis=0)
                        print(_line(arm, f"{name}, arm poses chosen", args.images, picked))
                        print(_line(arm, f"direct view {best:.2f} m, arm poses chosen", args.images, picked_direct))
                        print(f"{arm:22s}   chosen arm poses: / best direct view: {_ratio(picked, direct[best])}; "
                              f"/ its arm poses chosen too: {_ratio(picked, picked_direct)}")
                    print(f"{arm:22s}   the planes take {100 * np.mean([r[3][1] for r in runs]):.0f} % of the "
                          f"information on the mount's turn about {np.round(axis / np.linalg.norm(axis), 2).tolist()} "
                          f"(camera frame)")


if __name__ == "__main__":
    main()
