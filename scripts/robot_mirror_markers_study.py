"""Markers fixed on the mirror, seen directly by the camera in the same photographs: how close they bring the
camera mount's 3-sigma through one hand-held mirror to a direct-view hand-eye calibration with the same
number of images (docs/setups/arm.md, the table's set-ups; ``robot_mirror_vs_direct.py`` for the baseline).

Cramér-Rao bound at the simulated truth, 0.5 px for the board's corners and the markers alike. The mirror's
own frame {P}: z along the plane's normal toward the camera,
z = 0 on the glass, x along the camera's x axis laid onto the plane; its origin the mean of the points where
the camera's rays to the board's image meet the plane (the middle of the glass the board is seen in). Each
placement's unknowns: its plane in {B} (3, the key the reflections use) and the mirror's in-plane pose (a turn
about its normal and two in-plane translations: 3). A marker ``m`` ({P}) lies at ``X = o + R_P m`` in {B}
and is seen directly: ``pi(C^-1 X)``, C the camera's pose by forward kinematics and its mount.

Layouts (metres, {P}; the glass 0.25 x 0.18 m):

* ``tag6``: one 6 cm square tag's 4 corners on the glass, in a corner of it;
* ``dots``: 4 dots on the frame at the glass's corners (2 mm proud of the glass);
* ``tag10``: one 10 cm tag on a tab of the frame below the glass (5 mm proud);
* ``4tags6``: four 6 cm tags on the frame beside the glass's left and right edges (5 mm proud);
* ``big``: four 6 cm tags centred at the corners of a 0.4 x 0.3 m rectangle (a larger mirror's frame: the
  board's image spreads over +-0.1-0.28 m of the plane in these set-ups, more than the 0.25 x 0.18 m glass).

The row ``none, planes known``: no markers, the placements' planes given (eye-to-hand, the most any marker
could give).
``--marker-sigma`` sets the markers' pixel sigma apart from the board's (what-if: how well they would have to
be measured). Each set-up also prints the placements' plane tilt sigma (the larger of the normal's two
tangent directions, degrees, mean over placements) from the board's reflections alone (the camera mount
unknown) and from ``4tags6``'s markers alone (the camera and the mount known): the markers pin each plane
only if theirs is well below the reflections'.

A marker is used in an image where it is inside the image (20 px margin), at least 0.1 m ahead of the
camera, and the board's plate (3 cm beyond its corners) does not stand in the camera's line of sight to it;
a tag only with all 4 corners. ``--once``: the markers counted once per placement (their detection errors
shared by a placement's photographs of a still camera and mirror rather than drawn afresh in each: the
conservative figure eye-to-hand). Derivatives of the marker pixels: central differences over GTSAM's
retractions (Pose3 mount, OrientedPlane3 plane), independent of the library's factors.
What it finds (24 images, 5 seeds): eye-to-hand, no layout at 0.5 px brings the camera mount within 2x of the
best direct view in rotation; the best, four 6 cm tags with the mirror 0.3-0.35 m away tilted 20-30 deg at 3
placements, is 2.7x in rotation and 1.9x in position (3.8x and 2.7x without markers); the others 3.1-4.0x in
rotation. Each placement's tilt from its markers alone (0.08-0.2 deg sigma with four tags, 6-8 photographs) is
far looser than what the board's reflections already give (0.02-0.03 deg): a tilt turns the reflected board
by twice its angle, but moves a directly seen marker only through the foreshortening of a small, nearly
face-on patch. Markers measured to 0.1 px (the board still at 0.5 px; 3 seeds) would give 1.7x and 1.2x
at that best set-up, 2.0-3.0x in rotation at the others (0.02 px: 1.5-2.2x); counted once per placement (``--once``) they give 3.2-4.0x. Eye-in-hand the markers are a
directly seen target in {B} as well, and help more: 1.0-1.2x in rotation, 1.1-1.9x in position (1.2-2.0x,
1.4-3.8x without).
Run: PYTHONPATH=. python scripts/robot_mirror_markers_study.py [--images 24] [--seeds 5] [--once]
[--marker-sigma PX]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile

import gtsam
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from robot_mirror_vs_direct import BESIDE, DIRECT_DISTANCES, _line, _ratio, _sigma3  # noqa: E402

from mirror_fg.factors.views import plane_of  # noqa: E402
from mirror_fg.io.dataset import load_dataset  # noqa: E402
from mirror_fg.robot.simulate import CAMERA, simulate_arm, write_arm_simulation  # noqa: E402
from mirror_fg.solver.model.robot_views import RobotEstimate, RobotProblem  # noqa: E402

#: The glass's half sizes (m).
GLASS = (0.125, 0.09)


def _tag(centre, side, z=0.0) -> np.ndarray:
    h = side / 2.0
    return np.array([[centre[0] + a * h, centre[1] + b * h, z] for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])


#: name: groups of markers ({P}, metres), each group seen whole or not at all (a tag's 4 corners)
LAYOUTS = {
    "tag6": [_tag((-GLASS[0] + 0.035, -GLASS[1] + 0.035), 0.06)],
    "dots": [np.array([[a * GLASS[0], b * GLASS[1], 0.002]]) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))],
    "tag10": [_tag((0.0, -GLASS[1] - 0.065), 0.10, 0.005)],
    "4tags6": [_tag((a * (GLASS[0] + 0.035), b * (GLASS[1] - 0.03), 0.005), 0.06)
               for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))],
    "big": [_tag((a * 0.2, b * 0.15, 0.005), 0.06) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))],
}
#: Set-ups of docs/setups/arm.md's table: (mirror distance (m), tilt (deg), eye-to-hand board or None).
SETUPS = {
    "bench: mirror 0.5 m, tilt 20-30 deg": ((0.5, 0.5), (20.0, 30.0), None),
    "close: mirror 0.3-0.35 m, tilt 20-30 deg": ((0.3, 0.35), (20.0, 30.0), None),
    "near: mirror 0.2-0.25 m, tilt 10-20 deg": ((0.2, 0.25), (10.0, 20.0), BESIDE),
    "near: mirror 0.3-0.35 m, tilt 20-30 deg": ((0.3, 0.35), (20.0, 30.0), BESIDE),
}


def mirror_frame(n: np.ndarray, d: float, sign: float, reference: np.ndarray, nuisance: np.ndarray):
    """The mirror's pose ``(R_B_P, o)`` in {B} from its plane ``n . x = d`` and in-plane pose ``nuisance =
    [turn, s1, s2]`` (``sign`` n the side of the camera; ``reference`` the direction x is laid from)."""
    z = sign * n
    e1 = reference - (reference @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(z, e1)
    c, s = np.cos(nuisance[0]), np.sin(nuisance[0])
    R = np.column_stack([c * e1 + s * e2, -s * e1 + c * e2, z])
    return R, d * n + nuisance[1] * e1 + nuisance[2] * e2


def _seen_directly(C, X: np.ndarray, board) -> np.ndarray:
    """Per marker (K, 3 in {B}): inside the image, ahead of the camera, not behind the board's plate."""
    R, t = C
    x = (X - t) @ R
    ok = x[:, 2] > 0.1
    pix = (CAMERA.K @ (x.T / x[:, 2]))[:2].T
    ok &= np.all((pix >= 20) & (pix <= [CAMERA.width - 20, CAMERA.height - 20]), axis=1)
    R_t, t_t, low, high = board
    c_t = R_t.T @ (t - t_t)
    for k in range(len(X)):
        m_t = R_t.T @ (X[k] - t_t)
        dz = m_t[2] - c_t[2]
        if abs(dz) > 1e-12 and 0.0 < -c_t[2] / dz < 1.0:
            p = c_t[:2] + (-c_t[2] / dz) * (m_t[:2] - c_t[:2])
            ok[k] &= not (np.all(p >= low) and np.all(p <= high))
    return ok


def marker_information(problem: RobotProblem, truth, layout: str, once: bool = False,
                       pixel_sigma: float = 0.5) -> tuple[np.ndarray, int, dict, np.ndarray]:
    """The information of the mirror markers over ``problem``'s columns then 3 nuisance columns per placement
    (``problem.placements`` order), the number of marker sightings and each placement's glass spread
    (the board's image on the glass, metres about the origin)."""
    groups = LAYOUTS[layout]
    markers = np.vstack(groups)
    group_of = np.concatenate([np.full(len(g), k) for k, g in enumerate(groups)])
    mounts = {r: pose for r, (_, pose) in truth.mounts.items()}
    information, columns = problem.information(problem.graph(), problem.values(RobotEstimate(mounts, dict(truth.mirror_vectors))))
    size = information.shape[0]
    baseline = information.copy()
    total = np.zeros((size + 3 * len(problem.placements),) * 2)
    total[:size, :size] = information
    role = problem.camera
    link_c, link_t = problem.links[role], problem.links["target"]
    M_c, M_t = mounts["camera"], mounts["target"]
    frames, spreads = {}, {}
    board_points = np.array(list(problem.dataset.fiducials.values()))
    low, high = board_points[:, :2].min(axis=0) - 0.03, board_points[:, :2].max(axis=0) + 0.03
    per_image = []
    for index, image in enumerate(problem.dataset.images):
        F_c, F_t = problem.recorded[index][link_c][0], problem.recorded[index][link_t][0]
        C = (F_c[:3, :3] @ M_c[0], F_c[:3, :3] @ M_c[1] + F_c[:3, 3])
        D = (F_t[:3, :3] @ M_t[0], F_t[:3, :3] @ M_t[1] + F_t[:3, 3])
        per_image.append((image.reflections[0], C, (D[0], D[1], low, high), F_c))
    for p in problem.placements:  # the mirror's frame: where the board is seen on the glass
        v = truth.mirror_vectors[p]
        n, d = v / np.linalg.norm(v), float(np.linalg.norm(v))
        hits, sides, xs = [], [], []
        for (q, C, (R_t, t_t, _, _), _) in per_image:
            if q != p:
                continue
            x = R_t @ board_points.T + t_t[:, None]
            virtual = x - 2.0 * np.outer(v, (v @ x) / (v @ v) - 1.0)  # eq. (3)
            ray = virtual - C[1][:, None]
            hits.append((C[1][:, None] + ray * ((d - n @ C[1]) / (n @ ray))).T)
            sides.append(np.sign(d - n @ C[1]))
            xs.append(C[0][:, 0])
        hits = np.vstack(hits)
        sign = -float(np.sign(np.mean(sides)))  # toward the camera
        reference = np.mean(xs, axis=0)
        o = hits.mean(axis=0)
        R0, o0 = mirror_frame(n, d, sign, reference, np.zeros(3))
        nuisance = np.array([0.0, *(R0[:, :2].T @ (o - o0))])
        frames[p] = (sign, reference, nuisance)
        spreads[p] = np.abs((hits - o) @ R0[:, :2]).max(axis=0)
    sightings = 0
    seen_placements: set = set()
    alone = np.zeros((len(problem.placements), 6, 6))  # each placement's plane and in-plane pose, markers alone
    for (p, C, board, F_c) in per_image:
        if once and p in seen_placements:
            continue
        sign, reference, nuisance = frames[p]
        plane = plane_of(truth.mirror_vectors[p])
        M = gtsam.Pose3(gtsam.Rot3(M_c[0]), M_c[1])

        def predict(a, xi, w):
            mount = M.retract(a)
            Cm = (F_c[:3, :3] @ mount.rotation().matrix(), F_c[:3, :3] @ mount.translation() + F_c[:3, 3])
            pl = plane.retract(xi)
            R, o = mirror_frame(np.asarray(pl.normal().point3()), float(pl.distance()), sign, reference, nuisance + w)
            x = (o + markers @ R.T - Cm[1]) @ Cm[0]
            return (x[:, :2] / x[:, 2:]).reshape(-1)

        R, o = mirror_frame(truth.mirror_vectors[p] / np.linalg.norm(truth.mirror_vectors[p]),
                            float(np.linalg.norm(truth.mirror_vectors[p])), sign, reference, nuisance)
        seen = _seen_directly(C, o + markers @ R.T, board)
        for k in range(len(groups)):  # a tag's corners all or none
            seen[group_of == k] = seen[group_of == k].all()
        if not seen.any():
            continue
        seen_placements.add(p)
        rows = np.repeat(seen, 2)
        J = np.zeros((2 * len(markers), 12))
        h = 1e-6
        for k in range(12):
            e = np.zeros(12)
            e[k] = h
            J[:, k] = (predict(e[:6], e[6:9], e[9:]) - predict(-e[:6], -e[6:9], -e[9:])) / (2 * h)
        J = J[rows] / (pixel_sigma / CAMERA.fx)
        sightings += int(seen.sum())
        cols = list(range(columns[problem.mount_keys["camera"]].start, columns[problem.mount_keys["camera"]].stop)) \
            if "camera" in problem.mount_keys else []
        c = columns[problem.mirror_keys[p]]
        k = problem.placements.index(p)
        idx = np.array(cols + list(range(c.start, c.stop)) + list(range(size + 3 * k, size + 3 * k + 3)))
        Jk = J if cols else J[:, 6:]
        total[np.ix_(idx, idx)] += Jk.T @ Jk
        alone[k] += J[:, 6:].T @ J[:, 6:]
    tilts = []
    for k, p in enumerate(problem.placements):
        c = columns[problem.mirror_keys[p]]
        reflections = np.degrees(np.sqrt(np.diag(np.linalg.inv(baseline)[c, c])[:2]).max())
        eigenvalues = np.linalg.eigvalsh(alone[k])
        markers_alone = np.inf  # too few marker sightings at this placement to pose the mirror
        if eigenvalues[0] > 1e-9 * eigenvalues[-1]:
            markers_alone = np.degrees(np.sqrt(np.diag(np.linalg.inv(alone[k]))[:2]).max())
        tilts.append((reflections, markers_alone))
    return total, sightings, spreads, baseline, np.array(tilts)


def study(robot: str, eye_in_hand: bool, placements: int, images: int, seed: int, folder: str, setup,
          layouts=tuple(LAYOUTS), once: bool = False, marker_sigma: float = 0.5) -> dict:
    """``{"none"|layout: 3-sigma [deg x3, mm x3]}`` of the camera mount, and ``"sightings"``, ``"spread"``."""
    mirror = {"mirror_distance": setup[0], "mirror_tilt_deg": setup[1], "check_occlusion": True}
    if setup[2] is not None and not eye_in_hand:
        mirror["board_position"] = setup[2]
    dataset, truth = simulate_arm(robot, eye_in_hand, placements=placements, arm_poses=images // placements,
                                  pixel_sigma=0.5, seed=seed, **mirror)
    path = os.path.join(folder, f"{robot}_{placements}_{seed}.json")
    write_arm_simulation(path, dataset, truth)
    problem = RobotProblem(load_dataset(path))
    R = truth.mounts["camera"][1][0]
    out: dict = {"sightings": {}}
    for layout in layouts:
        information, count, spreads, baseline, tilts = marker_information(problem, truth, layout, once, marker_sigma)
        if layout == "4tags6":
            posed = tilts[np.isfinite(tilts[:, 1])]
            out["tilts"] = np.mean(posed, axis=0) if len(posed) else np.array([tilts[:, 0].mean(), np.inf])
        size = baseline.shape[0]
        columns = problem.information(problem.graph(), problem.values(RobotEstimate(
            {r: pose for r, (_, pose) in truth.mounts.items()}, dict(truth.mirror_vectors))))[1]
        c = columns[problem.mount_keys["camera"]]
        if "none" not in out:
            out["none"] = _sigma3(np.linalg.inv(baseline)[c, c], R)
            planes = {i for k in problem.mirror_keys.values() for i in range(columns[k].start, columns[k].stop)}
            rest = np.array([i for i in range(size) if i not in planes])
            at = [int(np.flatnonzero(rest == i)[0]) for i in range(c.start, c.stop)]
            out["known"] = _sigma3(np.linalg.inv(baseline[np.ix_(rest, rest)])[np.ix_(at, at)], R)
            out["spread"] = np.max(list(spreads.values()), axis=0)
        # a placement whose markers do not pose its mirror leaves some in-plane directions free: a prior of
        # 1e3 (rad, m) sigma on them holds those without informing anything else
        vague = information + np.diag([0.0] * size + [1e-6] * (information.shape[0] - size))
        out[layout] = _sigma3(np.linalg.inv(vague)[c, c], R)
        out.setdefault("placements_seen", {})[layout] = int(np.sum(np.diag(information)[size::3] > 0.0))
        out["sightings"][layout] = count
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=24)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--once", action="store_true", help="markers counted once per placement")
    parser.add_argument("--marker-sigma", type=float, default=0.5, help="the markers' pixel sigma")
    args = parser.parse_args()
    from robot_mirror_vs_direct import camera_mount

    seeds = range(args.seeds)
    with tempfile.TemporaryDirectory() as folder:
        for robot, eye_in_hand in (("arm6", False), ("panda", True)):
            arm = f"{robot} {'eye-in-hand' if eye_in_hand else 'eye-to-hand'}"
            direct = {d: np.mean([camera_mount(robot, eye_in_hand, 0, args.images, s, folder, d)[0] for s in seeds], axis=0)
                      for d in DIRECT_DISTANCES}
            best = min(DIRECT_DISTANCES, key=lambda d: direct[d][:3].max() / direct[0.9][:3].max()
                       + direct[d][3:].max() / direct[0.9][3:].max())
            print(_line(arm, f"best direct view, board {best:.2f} m", args.images, direct[best]))
            for name, setup in SETUPS.items():
                if eye_in_hand and setup[2] is not None and name.startswith("near: mirror 0.3"):
                    continue  # eye-in-hand the board is beside the camera in every set-up
                for placements in (3, 4):
                    try:
                        runs = [study(robot, eye_in_hand, placements, args.images, s, folder, setup, once=args.once,
                                      marker_sigma=args.marker_sigma)
                                for s in seeds]
                    except RuntimeError:
                        print(f"{arm:22s} {name}, {placements} placements: blocked")
                        continue
                    spread = np.max([r["spread"] for r in runs], axis=0)
                    for layout in ("none", *LAYOUTS, "known"):
                        values = np.mean([r[layout] for r in runs], axis=0)
                        seen = "" if layout in ("none", "known") else \
                            (f" ({np.mean([r['sightings'][layout] for r in runs]):.0f} marker sightings, "
                             f"{np.mean([r['placements_seen'][layout] for r in runs]):.1f} placements)")
                        label = "none, planes known" if layout == "known" else layout
                        print(f"{arm:22s} {name}, {placements} pl., markers {label:6s}: / best direct "
                              f"({best:.2f} m): {_ratio(values, direct[best])}; {values[:3].max():.3f} deg, "
                              f"{values[3:].max():.2f} mm{seen}")
                    tilt = np.mean([r["tilts"] for r in runs], axis=0)
                    print(f"{arm:22s}   the board's image on the glass within +-{np.round(spread, 3).tolist()} m; "
                          f"plane tilt sigma from the reflections {tilt[0]:.3f} deg, from 4tags6's markers alone "
                          f"{tilt[1]:.3f} deg")


if __name__ == "__main__":
    main()
