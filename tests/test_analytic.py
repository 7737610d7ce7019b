"""Analytical solution (Sects. 4-5): exact on noise-free trees, refusals on degenerate schedules."""
import numpy as np
import pytest

from mirror_fg import (
    DatasetError,
    SolveError,
    calibrate,
    initial_estimate,
    solve_analytic,
)
from mirror_fg.solver.start.analytic import (
    Hypothesis as _Hypothesis,
    _subtree_solution,
    subtree_dataset,
    triangulate_point,
)
from mirror_fg.solver.start.pnp import pnp_candidates
from mirror_fg.data import Dataset, Image
from mirror_fg.core.geometry import apply_transform, nested_transform, project, so3_exp
from mirror_fg.simulate.tree import simulate_base_case, simulate_tree
from mirror_fg.core.transform import rotation_angle


@pytest.mark.parametrize("num_mirrors", [1, 2, 3])
@pytest.mark.parametrize("num_fiducials", [3, 4])
def test_noise_free_minimal_tree_is_exact(num_mirrors, num_fiducials):
    dataset, truth = simulate_tree(num_mirrors, num_fiducials=num_fiducials, num_points=2, pixel_sigma=0.0, seed=3)
    assert len(dataset.images) == 3**num_mirrors
    solution = solve_analytic(dataset)
    assert rotation_angle(solution.R_cam_base, truth.R_cam_base) < 1e-6
    assert np.linalg.norm(solution.t_cam_base - truth.t_cam_base) < 1e-6
    for config, v in truth.mirror_vectors.items():
        assert np.linalg.norm(solution.mirror_vectors[config] - v) < 1e-6
    for name, p in truth.points.items():
        assert np.linalg.norm(solution.points[name] - p) < 1e-6
    # The MLE started there stays there.
    calibration = calibrate(dataset)
    assert rotation_angle(calibration.R_cam_base, truth.R_cam_base) < 1e-6
    assert np.linalg.norm(calibration.t_cam_base - truth.t_cam_base) < 1e-6
    assert calibration.iterations <= 2


@pytest.mark.parametrize("seed", range(4))
def test_pnp_candidates_contain_truth_for_odd_and_even_mirror_counts(seed):
    rng = np.random.default_rng(seed)
    base_points = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0.0]])
    for num_mirrors in (1, 2):
        R = so3_exp(rng.normal(size=3) * 0.3)
        vectors = [np.array([0.05, 0.0, 0.5 * (-1) ** (num_mirrors - l)]) for l in range(1, num_mirrors + 1)]
        A, b = nested_transform(R, np.array([0.0, 0.05, -0.1]), vectors)
        z = project(apply_transform(A, b, base_points))
        candidates = pnp_candidates(base_points, z, num_mirrors)
        assert 1 <= len(candidates) <= 4
        assert min(np.linalg.norm(Ac - A) + np.linalg.norm(bc - b) for Ac, bc in candidates) < 1e-8
        assert all(np.isclose(np.linalg.det(Ac), (-1) ** num_mirrors) for Ac, _ in candidates)


def test_triangulation_eq20_recovers_point():
    rng = np.random.default_rng(1)
    point = np.array([0.1, -0.05, 0.02])
    transforms, rays = [], []
    for _ in range(4):
        A = so3_exp(rng.normal(size=3) * 0.2)
        b = np.array([0.0, 0.0, 2.0]) + 0.1 * rng.normal(size=3)
        transforms.append((A, b))
        rays.append(project(A @ point + b))
    np.testing.assert_allclose(triangulate_point(transforms, rays), point, atol=1e-10)


def _drop_images(dataset, keep):
    return Dataset(dataset.num_mirrors, dataset.camera, dataset.pixel_sigma, dataset.fiducials,
                   [im for im in dataset.images if keep(im)], "test.json")


def test_placement_with_two_children_is_refused_with_its_name():
    dataset, _ = simulate_tree(2, pixel_sigma=0.0, seed=1)
    # remove mirror 2's third placement under mirror 1 placement 1
    victim = [im for im in dataset.images if im.mirror_configs[0] == 1][-1]
    reduced = _drop_images(dataset, lambda im: im is not victim)
    with pytest.raises(DatasetError, match=r"test.json: under placement \(1, 1\).*mirror 2 needs at least three placements, you gave two"):
        solve_analytic(reduced)


def test_root_with_two_placements_of_mirror_one_is_refused():
    dataset, _ = simulate_tree(1, pixel_sigma=0.0, seed=1)
    reduced = _drop_images(dataset, lambda im: im.mirror_configs[0] != 2)
    with pytest.raises(DatasetError, match="mirror 1 needs at least three placements, you gave two"):
        solve_analytic(reduced)


@pytest.mark.parametrize("num_mirrors", [2, 3])
def test_a_subtree_dataset_is_explained_by_its_node(num_mirrors):
    """A node's (A_{l-1}, b_{l-1}) and its subtree's mirror vectors, as the subtree dataset's unknowns,
    reproduce every observation of the images under it (odd l - 1: fiducials mirrored in y)."""
    dataset, truth = simulate_tree(num_mirrors, pixel_sigma=0.0, seed=4)
    for level in range(2, num_mirrors + 1):
        prefix = dataset.images[-1].mirror_configs[: level - 1]
        images = [im for im in dataset.images if im.mirror_configs[: level - 1] == prefix]
        A, b = nested_transform(truth.R_cam_base, truth.t_cam_base,
                                [truth.mirror_vectors[(l + 1, m)] for l, m in enumerate(prefix)])
        below = {key: [v] for key, v in truth.mirror_vectors.items()
                 if key[0] >= level and any(im.mirror_configs[key[0] - 1] == key[1] for im in images)}
        sub = subtree_dataset(dataset, images, level)
        solution = _subtree_solution(_Hypothesis(A, b, below, {}), level)
        assert sub.num_mirrors == num_mirrors - level + 1 and len(sub.images) == len(images)
        assert np.linalg.det(solution.R_cam_base) == pytest.approx(1.0)
        for image in sub.images:
            A_sub, b_sub = nested_transform(solution.R_cam_base, solution.t_cam_base,
                                            [solution.mirror_vectors[(l + 1, m)] for l, m in enumerate(image.mirror_configs)])
            observed = sub.normalized(image)
            for name, point in sub.fiducials.items():
                np.testing.assert_allclose(project(A_sub @ point + b_sub), observed[name], atol=1e-9)


def test_initial_estimate_rejects_a_subtrees_p3p_twin():
    """2 px at 0.25 m: under one placement of mirror 1, the bare closed form prefers a P3P twin that most
    of its images agree on, and LM from it stops in another minimum; refined on their own images, the
    hypotheses rank right, and calibrate() reaches the MLE started from the truth."""
    dataset, truth = simulate_base_case(num_images=60, pixel_sigma=2.0, mirror_distance=0.25, seed=50)
    optimum = calibrate(dataset, initial=truth, compute_covariance=False)
    from_closed_form = calibrate(dataset, initial=solve_analytic(dataset), compute_covariance=False)
    assert rotation_angle(from_closed_form.R_cam_base, optimum.R_cam_base) > 1e-3, "no twin here: pick another seed"
    assert from_closed_form.final_error > optimum.final_error  # a worse minimum, not another optimum
    estimate = initial_estimate(dataset)
    calibration = calibrate(dataset, compute_covariance=False)
    assert np.array_equal(calibration.analytic.t_cam_base, estimate.t_cam_base)
    assert rotation_angle(calibration.R_cam_base, optimum.R_cam_base) < 1e-6
    assert np.linalg.norm(calibration.t_cam_base - optimum.t_cam_base) < 1e-6
    assert calibration.cost_plausible


def test_coplanar_mirror_normals_are_refused_naming_placements():
    dataset, truth = simulate_tree(1, pixel_sigma=0.0, seed=2)
    # Rebuild the three placements with normals in one plane (all rotated about the camera x axis).
    images = []
    for m, angle in enumerate([-0.2, 0.0, 0.25]):
        v = so3_exp(np.array([angle, 0.0, 0.0])) @ np.array([0.0, 0.0, 0.5])
        A, b = nested_transform(truth.R_cam_base, truth.t_cam_base, [v])
        z = {n: project(A @ p + b) for n, p in dataset.fiducials.items()}
        images.append(Image(f"im{m}", (m,), z))
    coplanar = Dataset(1, None, 1e-3, dataset.fiducials, images, "flat.json")
    with pytest.raises(SolveError, match=r"flat.json.*\(1, 0\), \(1, 1\), \(1, 2\) are nearly coplanar"):
        solve_analytic(coplanar)


def test_pnp_failure_names_the_image():
    dataset, _ = simulate_tree(1, pixel_sigma=0.0, seed=1)
    broken = dataset.images[1]
    # every fiducial behind the camera: no admissible pose
    normalized = {n: np.array([5.0, -7.0]) * (i + 1) * (-1) ** i for i, n in enumerate(broken.observations)}
    images = [im if im is not broken else Image(im.id, im.mirror_configs, normalized) for im in dataset.images]
    bad = Dataset(1, None, 1e-3, dataset.fiducials, images, "bad.json")
    with pytest.raises(SolveError, match=f"bad.json: image '{broken.id}': PnP"):
        solve_analytic(bad)


def test_point_seen_once_is_refused():
    dataset, _ = simulate_tree(1, num_points=1, pixel_sigma=0.0, seed=1)
    for im in dataset.images[1:]:
        im.observations.pop("P0", None)
    with pytest.raises(DatasetError, match="point 'P0' is seen only in image"):
        solve_analytic(dataset)


def test_placement_seen_only_without_three_fiducials_is_refused():
    dataset, _ = simulate_tree(1, pixel_sigma=0.0, seed=1)
    extra = Image("lonely", (7,), {"F0": np.array([0.01, 0.02]), "F1": np.array([0.03, 0.02])})
    bad = Dataset(1, None, 1e-3, dataset.fiducials, dataset.images + [extra], "few.json")
    with pytest.raises(DatasetError, match="few.json: mirror 1 placement 7 is only seen in images with fewer than 3"):
        solve_analytic(bad)


def test_one_mirror_with_many_p3p_images_is_not_enumerated():
    """Nv = 1, 3 fiducials, 70 images: the root's candidate combinations (2^70 or more) overflow int64;
    they must go to the sampled search, not be enumerated (which never ends)."""
    import signal

    dataset, truth = simulate_base_case(num_images=70, num_mirrors=1, pixel_sigma=0.5, seed=2)

    def too_slow(signum, frame):
        raise TimeoutError("solve_analytic enumerated the P3P combinations")

    previous = signal.signal(signal.SIGALRM, too_slow)
    signal.alarm(60)
    try:
        solution = initial_estimate(dataset)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert rotation_angle(solution.R_cam_base, truth.R_cam_base) < np.radians(5.0)
    calibration = calibrate(dataset, compute_covariance=False)
    optimum = calibrate(dataset, initial=truth, compute_covariance=False)
    assert np.linalg.norm(calibration.t_cam_base - optimum.t_cam_base) < 1e-6


def test_smallest_eigenvectors_match_eigh():
    """The closed-form smallest eigenvectors of the mirror peeling agree with eigh to rounding (up to sign)."""
    from mirror_fg.solver.start.peeling import smallest_eigenvectors

    rng = np.random.default_rng(3)
    normals = rng.normal(size=(200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    householder = np.eye(3) - 2.0 * np.einsum("ka,kb->kab", normals, normals)
    for noise in (0.0, 1e-6, 1e-2, 0.5):
        S = 4.0 * householder + noise * rng.normal(size=householder.shape)
        S = 0.5 * (S + S.transpose(0, 2, 1))
        expected = np.linalg.eigh(S)[1][:, :, 0]
        got = smallest_eigenvectors(S)
        off = np.minimum(np.linalg.norm(got - expected, axis=1), np.linalg.norm(got + expected, axis=1))
        assert off.max() < 1e-12
