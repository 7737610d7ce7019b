"""The consensus guards: they neither refuse valid data (coplanar fiducials seen from either side,
a small planar target whose PnP has a twin, a rough start of the intrinsics) nor let one garbage image of
the paper's three-fiducial set-up sink the batch or the incremental solve."""
from dataclasses import replace

import numpy as np
import pytest
from conftest import pose_difference
from test_intrinsics import reference_pixels, seen_points

from mirror_fg import calibrate
from mirror_fg.core.geometry import apply_transform
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.screen.consensus import screen
from mirror_fg.solver.incremental.calibrator import calibrate_incremental
from mirror_fg.simulate.tree import measure, simulate_base_case, visible

# Ten coplanar fiducials in the simulator's 20 cm triangle (its plane z = 0): corners, edge midpoints,
# centroid and three inner points (the layout).
TRIANGLE = [(0.0, 0.0), (0.2, 0.0), (0.0, 0.2), (0.1, 0.0), (0.0, 0.1), (0.1, 0.1), (0.2 / 3, 0.2 / 3),
            (0.04, 0.03), (0.12, 0.04), (0.03, 0.11)]
CENTROID = np.array([0.2 / 3, 0.2 / 3, 0.0])
#: A plane for them that mirror 1's placement 2 sees from the other side than placements 0 and 1 in the
#: 60-image scene of seed 0, every view at least 20 deg off edge-on (found by a search over normals).
TILTED_NORMAL = (-0.909, 0.036, 0.416)


def _board(normal=(0.0, 0.0, 1.0)) -> dict[str, np.ndarray]:
    """The ten points turned about the triangle's centroid so that their plane's normal is ``normal``."""
    a, b = np.array([0.0, 0.0, 1.0]), np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    v, c = np.cross(a, b), float(a @ b)
    V = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    R = np.eye(3) + V + V @ V / (1.0 + c)
    return {f"B{i}": CENTROID + R @ (np.array([x, y, 0.0]) - CENTROID) for i, (x, y) in enumerate(TRIANGLE)}


def _board_scene(board: dict[str, np.ndarray], num_images: int, seed: int, pixel_sigma: float = 1.0):
    """The paper's two-mirror scene (its mirrors and T_cam_base) seen on ``board``; images where a board
    point would not be visible are dropped."""
    layout, truth = simulate_base_case(num_images=num_images, pixel_sigma=pixel_sigma, seed=seed)
    rng = np.random.default_rng(seed + 100)
    points = apply_transform(truth.R_cam_base, truth.t_cam_base, np.array(list(board.values())))
    images = [Image(im.id, im.mirror_configs, measure(truth, layout.camera, board, im.mirror_configs, pixel_sigma, rng))
              for im in layout.images if visible(layout.camera, points, truth.vectors(im.mirror_configs))]
    return replace(layout, fiducials=board, images=images, source="<board scene>"), truth


def _sigmas_from(calibration, R, t) -> np.ndarray:
    return pose_difference(R, t, calibration.R_cam_base, calibration.t_cam_base) / np.sqrt(np.diag(calibration.covariance))


# --------------------------------------------------------------------------------------------------
# Valid data the guards refused


def test_board_seen_from_the_other_side_by_one_mirror_group_is_kept():
    """A board whose plane one placement of mirror 1 sees from the other side than the other two (every
    view >= 20 deg off edge-on). Today: the whole group 'seen from behind' left out, then exit 2 (and
    iSAM2 never starts)."""
    board = _board(TILTED_NORMAL)
    dataset, truth = _board_scene(board, num_images=60, seed=0)
    plane_normal = np.cross(board["B1"] - CENTROID, board["B2"] - CENTROID)
    sides = set()
    for image in dataset.images:  # the truth: one placement of mirror 1 sees the board's other side
        A, b = truth.transform(image.mirror_configs)
        sides.add((image.mirror_configs[0], float(np.sign((A @ plane_normal) @ (A @ CENTROID + b)))))
    assert len(sides) == 3 and {side for _, side in sides} == {-1.0, 1.0}, sides
    _, excluded, _ = screen(dataset)
    assert excluded == []
    calibration = calibrate(dataset)
    assert calibration.excluded == [] and calibration.converged
    assert np.all(np.abs(_sigmas_from(calibration, truth.R_cam_base, truth.t_cam_base)) < 4.0)
    incremental = calibrate_incremental(dataset)  # today: the group refused image by image, no estimate ever
    assert incremental.excluded == [] and incremental.converged


def test_small_distant_board_keeps_every_valid_image():
    """Ten coplanar fiducials 2 m away through the mirrors: PnP's twin pose fits about as well as the
    true one, and judging an image by the wrong twin left valid images out ('inconsistent with the other
    placements of mirror 2', 1 of 60 here; 3 of 200 at seed 1 of the issue's scene)."""
    dataset, truth = _board_scene(_board(), num_images=60, seed=6)
    assert len(dataset.images) == 60
    _, excluded, _ = screen(dataset)
    assert excluded == []


def test_rough_start_of_the_intrinsics_keeps_every_valid_image():
    """camera.estimate started at fx = fy = 760 without distortion for a true 810 / 790, k1 = -0.2 (the
    issue's rough start), the ten coplanar fiducials, 60 images: nothing left out (today 2 valid images)."""
    truth_intrinsics = {"fx": 810.0, "fy": 790.0, "cx": 512.0, "cy": 384.0, "k1": -0.2}
    _, truth = simulate_base_case(num_images=60, pixel_sigma=0.0, seed=0)
    board = _board()
    base = np.array(list(board.values()))
    rng = np.random.default_rng(1000)
    images = []
    for i in range(60):
        configs = [i * 3 // 60, i]
        pixels = reference_pixels(seen_points(truth.R_cam_base, truth.t_cam_base, truth.vectors(configs), base),
                                  truth_intrinsics) + rng.normal(scale=1.0, size=(len(board), 2))
        images.append({"id": f"img{i:03d}", "mirror_configs": configs,
                       "observations": {n: pixels[j].tolist() for j, n in enumerate(board)}})
    data = {"format": "mirror-fg/dataset@1", "num_mirrors": 2, "pixel_sigma": 1.0,
            "camera": {"model": "pinhole", "width": 1024, "height": 768, "fx": 760.0, "fy": 760.0, "cx": 512.0,
                       "cy": 384.0, "dist": [0, 0, 0, 0, 0], "estimate": ["fx", "fy", "cx", "cy", "k1"]},
            "fiducials": {n: p.tolist() for n, p in board.items()}, "images": images}
    calibration = calibrate(dataset_from_dict(data), compute_covariance=False)
    # (at 2 m the focal lengths are weakly determined by 60 images: whether LM converges is not this test's)
    assert calibration.excluded == []


# --------------------------------------------------------------------------------------------------
# One garbage image of the paper's set-up (3 fiducials: no per-image PnP check)


def _with_garbage(dataset: Dataset, index: int, seed: int) -> Dataset:
    rng = np.random.default_rng(seed)
    images = list(dataset.images)
    bad = images[index]
    images[index] = Image(bad.id, bad.mirror_configs,
                          {name: rng.uniform([0.0, 0.0], [1024.0, 768.0]) for name in bad.observations})
    return replace(dataset, images=images)


@pytest.mark.parametrize("index", [10, 55])  # before the incremental start-up, and after it
def test_one_garbage_image_is_left_out_by_batch_and_incremental_alike(index):
    """Random pixels for one image of 60 (paper's scene, 1 px). Today: batch does not converge (LM
    stalled, the analytical solution 0.6 m off), iSAM2 stalls or meets an indeterminant system."""
    clean, _ = simulate_base_case(num_images=60, pixel_sigma=1.0, seed=0)
    bad = _with_garbage(clean, index, seed=0)
    bad_id = clean.images[index].id
    reference = calibrate(replace(clean, images=[im for im in clean.images if im.id != bad_id]))
    assert reference.excluded == []
    batch = calibrate(bad)
    incremental = calibrate_incremental(bad)
    for calibration in (batch, incremental):
        assert calibration.converged
        assert [(e.image, e.point) for e in calibration.excluded] == [(bad_id, None)]
        assert np.all(np.abs(_sigmas_from(reference, calibration.R_cam_base, calibration.t_cam_base)) < 0.1)
    assert batch.excluded[0].reason.startswith("inconsistent with the other placements of mirror 2")


@pytest.mark.parametrize("incremental", [False, True])
def test_cli_exits_0_naming_the_garbage_image(tmp_path, incremental):
    """The command line: exit 0 with the image in result@1's ``excluded`` (its misfit, its fiducials behind
    the camera, must not make the result file invalid)."""
    import json

    from mirror_fg.cli import main
    from mirror_fg.simulate.tree import write_simulation

    clean, truth = simulate_base_case(num_images=60, pixel_sigma=1.0, seed=0)
    path = tmp_path / "garbage.json"
    write_simulation(path, _with_garbage(clean, 10, seed=0), truth)
    out = tmp_path / "result.json"
    assert main(["calibrate", str(path), "-o", str(out), "--no-ros", "-q", *(["--incremental"] if incremental else [])]) == 0
    excluded = json.loads(out.read_text())["excluded"]
    assert [(e["image"], e["point"]) for e in excluded] == [(clean.images[10].id, None)]


# --------------------------------------------------------------------------------------------------
# The screening's mirror fit (speed: one Levenberg-Marquardt of every image and hypothesis at once)


def test_fit_mirrors_reaches_each_mirrors_least_squares_optimum():
    """``fit_mirrors`` on 40 mirrors at once against scipy's least_squares on each alone (same starts,
    eq. 3 written here from docs/formats.md), with noise so that the optimum is not the truth."""
    from scipy.optimize import least_squares

    from mirror_fg.solver.screen.placement_consensus import fit_mirrors

    rng = np.random.default_rng(3)
    sigma = np.array([1.0 / 800, 1.0 / 790])
    count, per_mirror = 40, 6
    normals = np.array([0.0, 0.0, 1.0]) + rng.normal(scale=0.3, size=(count, 3)) * [1, 1, 0]
    truth = 0.5 * normals / np.linalg.norm(normals, axis=1)[:, None]
    before = np.concatenate([rng.uniform([-0.2, -0.1, -0.6], [0.2, 0.3, -0.2], size=(per_mirror, 3)) for _ in range(count)])
    index = np.repeat(np.arange(count), per_mirror)

    def reflect(x, v):  # the plane v.x = v.v
        return x - 2.0 * (((x * v).sum(axis=-1) - (v * v).sum(axis=-1)) / (v * v).sum(axis=-1))[..., None] * v

    seen = reflect(before, truth[index])
    observed = seen[:, :2] / seen[:, 2:] + rng.normal(size=(len(index), 2)) * sigma
    starts = truth + rng.normal(scale=0.02, size=truth.shape)
    fitted, squared = fit_mirrors(before, index, observed, sigma, starts)
    costs = np.bincount(index, weights=squared, minlength=count)
    for k in range(count):
        rows = index == k

        def residual(v, rows=rows):
            x = reflect(before[rows], v)
            return ((x[:, :2] / x[:, 2:] - observed[rows]) / sigma).ravel()

        reference = least_squares(residual, starts[k], method="lm", xtol=1e-14, ftol=1e-14)
        assert costs[k] <= 2.0 * reference.cost * (1 + 1e-3) + 1e-9
        assert np.linalg.norm(fitted[k] - reference.x) < 1e-3 * np.linalg.norm(reference.x)


def test_screening_is_a_small_share_of_a_small_solve(takahashi_dir):
    """The five real photographs: the screening (board sides, the node's least median of squares) takes at
    most 40 % of the solve's wall time here (goal 25 %, measured 21-23 % under load; main: 75 %, with the
    per-image PnP, which is now a stage of its own that the initial estimate reuses)."""
    from conftest import load_script

    result = load_script("benchmark_screening").measure(takahashi_dir / "dataset.json", repeats=5)
    assert result["fraction"] < 0.4, result


def test_pnp_refines_one_start_per_basin_to_opencvs_optimum(takahashi_dir):
    """PnP of each real photograph (70 corners) against OpenCV's own SQPnP refined by its LM: the same pose."""
    import cv2

    from mirror_fg import load_dataset
    from mirror_fg.core.geometry import FLIP_Y
    from mirror_fg.solver.start.pnp import pnp_candidates

    dataset = load_dataset(takahashi_dir / "dataset.json")
    for image in dataset.images:
        names = [n for n in image.observations if n in dataset.fiducials]
        points = np.array([dataset.fiducials[n] for n in names])
        normalized = dataset.normalized(image)
        observed = np.array([normalized[n] for n in names])
        [(A, b)] = pnp_candidates(points, observed, dataset.num_mirrors)
        flipped = observed * [1.0, -1.0]  # one mirror: PnP of the y-flipped image (eq. 11)
        _, rvec, tvec = cv2.solvePnP(points, flipped, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
        rvec, tvec = cv2.solvePnPRefineLM(points, flipped, np.eye(3), None, rvec, tvec,
                                          criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15))
        R = cv2.Rodrigues(rvec)[0]
        assert np.allclose(A, FLIP_Y @ R, atol=1e-6) and np.allclose(b, FLIP_Y @ tvec.ravel(), atol=1e-6 * np.linalg.norm(b))


def test_fit_last_mirror_is_scipys_least_squares_result():
    """``consensus.fit_last_mirror`` (what the placement check of ``consistency.py`` fits) against scipy's
    least_squares on one image of the ten-point board scene, its parent the truth: vector, errors, Jacobian."""
    from scipy.optimize import least_squares

    from mirror_fg.core.geometry import nested_transform
    from mirror_fg.solver.screen.consensus import fit_last_mirror

    dataset, truth = _board_scene(_board(), num_images=12, seed=1)
    image = dataset.images[4]
    A_parent, b_parent = nested_transform(truth.R_cam_base, truth.t_cam_base, truth.vectors(image.mirror_configs[:-1]))
    names = list(dataset.fiducials)
    before = np.array([dataset.fiducials[n] for n in names]) @ A_parent.T + b_parent
    normalized = dataset.normalized(image)
    observed = np.array([normalized[n] for n in names])

    def residual(v):  # eq. (3) written here: reflection about the plane v.x = v.v, then projection
        x = before - 2.0 * ((before @ v - v @ v) / (v @ v))[:, None] * v
        return ((x[:, :2] / x[:, 2:] - observed) / dataset.normalized_sigma).ravel()

    start = truth.mirror_vectors[(2, image.mirror_configs[-1])] * 1.02
    reference = least_squares(residual, start, method="lm", xtol=1e-14, ftol=1e-14)
    fit = fit_last_mirror(dataset, image, A_parent, b_parent, start)
    assert np.allclose(fit.x, reference.x, atol=1e-6)
    assert np.allclose(fit.fun, residual(fit.x), atol=1e-9)
    numeric = np.column_stack([(residual(fit.x + h) - residual(fit.x - h)) / 2e-7 for h in np.eye(3) * 1e-7])
    assert np.allclose(fit.jac, numeric, rtol=1e-4, atol=1e-2)
