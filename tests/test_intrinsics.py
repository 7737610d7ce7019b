"""Intrinsics estimated through the mirrors: pixel factors, the joint MLE, its covariance,
the observability refusal, and the real photographs of shared/data/takahashi2012."""
import copy
import json
import warnings

import cv2
import gtsam
import numpy as np
import pytest
from conftest import pose_difference
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.factors.intrinsics import INTRINSIC_NAMES, IntrinsicsModel, intrinsics_key, intrinsics_prior_factor
from mirror_fg.io.dataset import dataset_from_dict, load_dataset
from mirror_fg.solver.calibrate import calibrate
from mirror_fg.solver.model.graph import GraphLayout, measurements_of
from reference.intrinsics_factors import intrinsics_factors
from reference.graph import initial_values
from mirror_fg.solver.batch.intrinsics import WeakIntrinsicsWarning
from mirror_fg.simulate.tree import simulate_base_case

# The simulated camera: fx != fy, principal point off-centre, barrel distortion (k1, k2).
TRUE_INTRINSICS = {"fx": 830.0, "fy": 790.0, "cx": 531.0, "cy": 371.0, "k1": -0.12, "k2": 0.05}
ROUGH_START = {"fx": 700.0, "fy": 700.0, "cx": 480.0, "cy": 400.0}
ESTIMATE = ["fx", "fy", "cx", "cy", "k1", "k2"]
# Ten coplanar fiducials inside the simulator's 20 cm triangle (its corners are kept 20 px inside the
# image, so every point inside is visible too).
BOARD = {f"B{i}": [x, y, 0.0] for i, (x, y) in enumerate(
    [(0.0, 0.0), (0.2, 0.0), (0.0, 0.2), (0.1, 0.0), (0.0, 0.1), (0.1, 0.1), (0.05, 0.05), (0.15, 0.02),
     (0.02, 0.15), (0.05, 0.12)])}
SIGMA_PX = 0.5


def reference_pixels(camera_points, intrinsics):
    """Pixels of camera-frame points (N, 3) through cv2.projectPoints (OpenCV's own lens model)."""
    K = np.array([[intrinsics["fx"], 0, intrinsics["cx"]], [0, intrinsics["fy"], intrinsics["cy"]], [0, 0, 1.0]])
    dist = np.array([intrinsics.get(n, 0.0) for n in ("k1", "k2", "p1", "p2", "k3")])
    pixels, _ = cv2.projectPoints(camera_points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    return pixels.reshape(-1, 2)


def seen_points(R, t, vectors, base_points):
    """Camera-frame points (N, 3) of base points through the mirrors ``vectors`` (mirror 1 first), written
    here from docs/formats.md (eqs. 2, 3): independent of mirror_fg's model."""
    x = base_points @ R.T + t
    for v in vectors:
        x = x - 2.0 * ((x @ v - v @ v) / (v @ v))[:, None] * v  # reflection about the plane v.x = v.v
    return x


def simulate_pixels(num_images=30, seed=0, fiducials=BOARD, sigma=SIGMA_PX, start=ROUGH_START, estimate=ESTIMATE,
                    prior_sigma=None, noise_seed=None):
    """A dataset@1 dict of a two-mirror scene seen by the distorted camera, and its truth. Mirrors at
    0.2 m tilted up to 45 deg: the board (20 cm) at about 0.8 m fills more of the image than at the
    base case's 2 m, so the focal lengths are determined to ~1 % (3-sigma ~23 px)."""
    _, truth = simulate_base_case(num_images=num_images, num_mirrors=2, pixel_sigma=0.0, seed=seed,
                                  mirror_distance=0.2, tilt_deg=45.0)
    rng = np.random.default_rng(seed + 1000 if noise_seed is None else noise_seed)
    names = list(fiducials)
    base = np.array([fiducials[n] for n in names])
    images = []
    for i in range(num_images):
        configs = [i * 3 // num_images, i]
        pixels = reference_pixels(seen_points(truth.R_cam_base, truth.t_cam_base, truth.vectors(configs), base),
                                  TRUE_INTRINSICS)
        pixels = pixels + rng.normal(scale=sigma, size=pixels.shape)
        images.append({"id": f"img{i:03d}", "mirror_configs": configs,
                       "observations": {n: pixels[j].tolist() for j, n in enumerate(names)}})
    camera = {"model": "pinhole", "width": 1024, "height": 768, **start, "dist": [0, 0, 0, 0, 0], "estimate": estimate}
    if prior_sigma:
        camera["prior_sigma"] = prior_sigma
    data = {"format": "mirror-fg/dataset@1", "num_mirrors": 2, "camera": camera, "pixel_sigma": sigma,
            "fiducials": fiducials, "images": images}
    return data, truth


def reference_mle(data, start_R, start_t, start_vectors, start_intrinsics):
    """The MLE by scipy's least_squares over pose, mirror vectors and the six intrinsics."""
    configs = sorted({(l + 1, m) for image in data["images"] for l, m in enumerate(image["mirror_configs"])})
    index = {c: i for i, c in enumerate(configs)}
    names = list(data["fiducials"])
    base = np.array([data["fiducials"][n] for n in names])
    observed = np.concatenate([[image["observations"][n] for n in names] for image in data["images"]])

    def unpack(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix()
        vectors = p[6 : 6 + 3 * len(configs)].reshape(-1, 3)
        return R, p[3:6], vectors, dict(zip(ESTIMATE, p[6 + 3 * len(configs) :]))

    def residual(p):
        R, t, vectors, intrinsics = unpack(p)
        seen = [seen_points(R, t, [vectors[index[(l + 1, m)]] for l, m in enumerate(image["mirror_configs"])], base)
                for image in data["images"]]
        return (reference_pixels(np.concatenate(seen), intrinsics) - observed).ravel() / data["pixel_sigma"]

    p0 = np.concatenate([Rotation.from_matrix(start_R).as_rotvec(), start_t,
                         np.concatenate([start_vectors[c] for c in configs]), [start_intrinsics[n] for n in ESTIMATE]])
    solution = least_squares(residual, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, x_scale="jac")
    R, t, vectors, intrinsics = unpack(solution.x)
    return R, t, intrinsics


def joint_covariance(calibration):
    """Covariance (6 + k) of ``[dtheta, dt, intrinsics]``."""
    k = len(calibration.camera.estimated)
    C = np.zeros((6 + k, 6 + k))
    C[:6, :6] = calibration.covariance
    C[6:, 6:] = calibration.camera.covariance
    C[6:, :6] = calibration.camera.pose_cross_covariance
    C[:6, 6:] = calibration.camera.pose_cross_covariance.T
    return C


def joint_error(calibration, R, t, intrinsics):
    """``[dtheta, dt, intrinsics]`` from the estimate to (R, t, intrinsics), docs/formats.md's convention."""
    camera = calibration.camera.camera
    dist = dict(zip(("k1", "k2", "p1", "p2", "k3"), camera.dist))
    values = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy, **dist}
    pose = pose_difference(calibration.R_cam_base, calibration.t_cam_base, R, t)
    return np.r_[pose, [intrinsics[n] - values[n] for n in calibration.camera.estimated]]


@pytest.fixture(scope="module")
def simulated():
    data, truth = simulate_pixels()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WeakIntrinsicsWarning)
        calibration = calibrate(dataset_from_dict(copy.deepcopy(data)))
    return data, truth, calibration


# --- factors --------------------------------------------------------------------------------------


def test_pixel_factor_jacobians_match_numerical_ones():
    fiducials = dict(list(BOARD.items())[:6])
    data, truth = simulate_pixels(num_images=6, fiducials={**fiducials}, sigma=0.3)
    data["fiducials"] = {k: v for k, v in list(data["fiducials"].items())[:4]}  # the other two: landmarks
    data["camera"].update({"estimate": ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]})
    dataset = dataset_from_dict(data)
    layout = GraphLayout.for_dataset(dataset)
    measurements = measurements_of(dataset)
    by_id = {image.id: image for image in dataset.images}
    pixels = np.array([by_id[m.image_id].observations[m.point] for m in measurements])
    theta = np.array([830.0, 790.0, 531.0, 371.0, -0.12, 0.05, 0.003, -0.002, 0.01])
    model = IntrinsicsModel(theta, INTRINSIC_NAMES)
    points = {name: np.array(BOARD[name]) + 0.002 for name in layout.point_keys}
    truth.points = points
    values = initial_values(layout, truth)
    values.insert(intrinsics_key(), theta)
    factors = intrinsics_factors(dataset, layout, measurements, pixels, model, 0.3)
    assert len(factors) < len(measurements)  # stacked
    for factor in factors:
        A = factor.linearize(values).jacobian()[0] * 0.3  # unwhiten
        column = 0
        for key in factor.keys():
            dim = values.atPose3(key).localCoordinates(values.atPose3(key)).size if key == layout.pose_key else (
                len(values.atVector(key)) if key == intrinsics_key() else 3)
            for j in range(dim):
                eps = 1e-6 if key != intrinsics_key() or j >= 4 else 1e-3
                delta = gtsam.VectorValues()
                for other in factor.keys():
                    size = 6 if other == layout.pose_key else (9 if other == intrinsics_key() else 3)
                    step = np.zeros(size)
                    if other == key:
                        step[j] = eps
                    delta.insert(other, step)
                plus = factor.unwhitenedError(values.retract(delta))
                delta_minus = gtsam.VectorValues()
                for other in factor.keys():
                    delta_minus.insert(other, -delta.at(other))
                minus = factor.unwhitenedError(values.retract(delta_minus))
                numerical = (plus - minus) / (2 * eps)
                scale = max(1.0, np.max(np.abs(numerical)))
                assert np.max(np.abs(A[:, column + j] - numerical)) < 1e-5 * scale, (key, j)
            column += dim


def test_prior_factor_error_and_jacobian():
    model = IntrinsicsModel(np.array([800.0, 800.0, 512.0, 384.0, 0, 0, 0, 0, 0]), ["fx", "cy", "k1"])
    factor = intrinsics_prior_factor(model, {"cy": 2.0, "k2": 1.0})  # k2 not estimated: no prior on it
    values = gtsam.Values()
    values.insert(intrinsics_key(), np.array([805.0, 380.0, -0.1]))
    assert np.allclose(factor.unwhitenedError(values), [380.0 - 384.0])
    assert np.allclose(factor.linearize(values).jacobian()[0] * 2.0, [[0.0, 1.0, 0.0]])
    assert intrinsics_prior_factor(model, {"k2": 1.0}) is None


# --- the joint MLE on simulated pixels ---------------------------------------------------------------


def test_mle_equals_independent_mle_from_truth(simulated):
    data, truth, calibration = simulated
    assert calibration.converged and calibration.residual_units == "px"
    R, t, intrinsics = reference_mle(data, truth.R_cam_base, truth.t_cam_base, truth.mirror_vectors, TRUE_INTRINSICS)
    sigma = np.sqrt(np.diag(joint_covariance(calibration)))
    off = joint_error(calibration, R, t, intrinsics) / sigma
    assert np.max(np.abs(off)) < 0.05, off


def test_truth_within_three_sigma(simulated):
    data, truth, calibration = simulated
    error = joint_error(calibration, truth.R_cam_base, truth.t_cam_base, TRUE_INTRINSICS)
    C = joint_covariance(calibration)
    assert np.all(np.abs(error) < 3.0 * np.sqrt(np.diag(C))), error / np.sqrt(np.diag(C))
    # The rough start was far outside: the estimate really moved.
    assert abs(calibration.camera.camera.fx - ROUGH_START["fx"]) > 5 * np.sqrt(calibration.camera.covariance[0, 0])
    assert calibration.camera.estimated == tuple(ESTIMATE)
    rms = np.sqrt(np.mean(np.sum(calibration.residuals**2, axis=1)))
    assert 0.8 * np.sqrt(2) * SIGMA_PX < rms < 1.2 * np.sqrt(2) * SIGMA_PX  # pixels, about sqrt(2) sigma


def test_intrinsics_absent_start_from_the_photographs(simulated):
    data, _, calibration = simulated
    bare = copy.deepcopy(data)
    for name in ("fx", "fy", "cx", "cy"):
        del bare["camera"][name]
    dataset = dataset_from_dict(bare)
    assert dataset.camera.fx != ROUGH_START["fx"]  # started from the images
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WeakIntrinsicsWarning)
        from_nothing = calibrate(dataset)
    sigma = np.sqrt(np.diag(joint_covariance(calibration)))
    camera = calibration.camera.camera
    off = joint_error(from_nothing, calibration.R_cam_base, calibration.t_cam_base,
                      {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy, "k1": camera.dist[0],
                       "k2": camera.dist[1]})
    assert np.max(np.abs(off / sigma)) < 1e-3


def test_too_rough_a_start_is_replaced_by_one_from_the_photographs(caplog):
    # 24 images: with fx and fy 30 % low and no distortion the analytical solution puts some mirror
    # vectors near zero and the joint solve from there does not converge; the start from the photographs
    # then takes over. (At 16 % low, the rough start above, the joint solve on the planes of the one
    # measurement model now converges from the given values to the same optimum; the mirror vectors of
    # the tree's own factors did not.)
    data, truth = simulate_pixels(num_images=24, noise_seed=0, start={**ROUGH_START, "fx": 581.0, "fy": 553.0})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WeakIntrinsicsWarning)
        with caplog.at_level("INFO", logger="mirror_fg"):
            calibration = calibrate(dataset_from_dict(data))
    assert "starting them from the photographs" in caplog.text
    assert calibration.converged
    error = joint_error(calibration, truth.R_cam_base, truth.t_cam_base, TRUE_INTRINSICS)
    assert np.all(np.abs(error) < 3.0 * np.sqrt(np.diag(joint_covariance(calibration))))


def test_estimating_a_subset_leaves_the_rest_untouched(simulated):
    data, truth, _ = simulated
    subset = copy.deepcopy(data)
    subset["camera"].update({**{k: TRUE_INTRINSICS[k] for k in ("fy", "cx", "cy")}, "fx": 815.0, "estimate": ["fx"],
                             "dist": [TRUE_INTRINSICS["k1"], TRUE_INTRINSICS["k2"], 0.0, 0.0, 0.0]})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WeakIntrinsicsWarning)
        calibration = calibrate(dataset_from_dict(subset))
    camera = calibration.camera.camera
    assert (camera.fy, camera.cx, camera.cy) == (TRUE_INTRINSICS["fy"], TRUE_INTRINSICS["cx"], TRUE_INTRINSICS["cy"])
    assert camera.dist == (TRUE_INTRINSICS["k1"], TRUE_INTRINSICS["k2"], 0.0, 0.0, 0.0)
    assert calibration.camera.estimated == ("fx",) and calibration.camera.covariance.shape == (1, 1)
    assert abs(camera.fx - TRUE_INTRINSICS["fx"]) < 3.0 * np.sqrt(calibration.camera.covariance[0, 0])


def test_prior_sigma_pulls_toward_the_given_value(simulated):
    data, _, calibration = simulated
    free_fx = calibration.camera.camera.fx
    given = TRUE_INTRINSICS["fx"] + 20.0
    pulled = copy.deepcopy(data)
    pulled["camera"].update({"fx": given, "prior_sigma": {"fx": 0.01}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WeakIntrinsicsWarning)
        tight = calibrate(dataset_from_dict(pulled))
        pulled["camera"]["prior_sigma"] = {"fx": float(np.sqrt(calibration.camera.covariance[0, 0]))}
        equal = calibrate(dataset_from_dict(pulled))
    assert abs(tight.camera.camera.fx - given) < 0.05 and np.sqrt(tight.camera.covariance[0, 0]) < 0.011
    # A prior as informative as the photographs: about half way (information-weighted mean).
    assert free_fx < equal.camera.camera.fx < given
    assert abs(equal.camera.camera.fx - 0.5 * (free_fx + given)) < 0.15 * (given - free_fx)


def test_three_fiducials_per_image_refused():
    triangle = {"F0": [0.0, 0.0, 0.0], "F1": [0.2, 0.0, 0.0], "F2": [0.0, 0.2, 0.0]}
    data, _ = simulate_pixels(num_images=12, fiducials=triangle, estimate=["fx", "fy", "cx", "cy"])
    with pytest.raises(SolveError, match="do not determine fx, fy, cx, cy: 0 image.*more points per image"):
        calibrate(dataset_from_dict(data))
    # Absent intrinsics cannot even be started from three points per image.
    for name in ("fx", "fy", "cx", "cy"):
        del data["camera"][name]
    with pytest.raises(DatasetError, match="4 or more fiducials"):
        dataset_from_dict(data)


def test_unobservable_by_fisher_information_refused():
    # Nine photographs of the board and every term of the lens: k2 and k3 would move the image corner
    # by hundreds of pixels at 3 sigma (the criterion: above 10 % of the image diagonal).
    data, _ = simulate_pixels(num_images=9, estimate=list(INTRINSIC_NAMES))
    with pytest.raises(SolveError, match=r"do not determine k2 \(3-sigma .* px at the image corner\), k3 .*"
                                         "more mirror placements, or estimate fewer intrinsics"):
        calibrate(dataset_from_dict(data))
    data["camera"]["estimate"] = ESTIMATE  # the same photographs determine six of them
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WeakIntrinsicsWarning)
        assert calibrate(dataset_from_dict(data)).converged


def test_refusals_at_load():
    data, _ = simulate_pixels(num_images=4)
    bad = copy.deepcopy(data)
    del bad["camera"]["fx"]
    bad["camera"]["estimate"] = ["fy"]
    with pytest.raises(DatasetError, match="missing 'fx'"):
        dataset_from_dict(bad)
    bad = copy.deepcopy(data)
    del bad["camera"]["fx"]
    bad["camera"]["prior_sigma"] = {"fx": 1.0}
    with pytest.raises(DatasetError, match="prior_sigma fx: a prior needs a given value"):
        dataset_from_dict(bad)
    bad = copy.deepcopy(data)
    del bad["camera"]["cx"]
    bad["fiducials"] = {**bad["fiducials"], "B9": [0.05, 0.12, 0.05]}  # off the board's plane
    with pytest.raises(DatasetError, match="coplanar"):
        dataset_from_dict(bad)
    fisheye = copy.deepcopy(data)
    fisheye["camera"].update({"model": "fisheye", "dist": [0, 0, 0, 0], "estimate": ["fx"]})
    with pytest.raises(DatasetError, match="pinhole model only"):
        calibrate(dataset_from_dict(fisheye))


def test_weak_intrinsics_warn():
    data, _ = simulate_pixels(num_images=9)
    with pytest.warns(WeakIntrinsicsWarning, match=r"weakly determined intrinsics: .*k2.*more tilt"):
        calibrate(dataset_from_dict(data))


def test_per_measurement_sigma_whitens_each_row():
    """point_sigma reaches the pixel factors: each measurement is whitened by its own sigma."""
    data, truth = simulate_pixels(num_images=8)
    dataset = dataset_from_dict(data)
    layout = GraphLayout.for_dataset(dataset)
    measurements = measurements_of(dataset)
    by_id = {image.id: image for image in dataset.images}
    pixels = np.array([by_id[m.image_id].observations[m.point] for m in measurements])
    theta = np.array([830.0, 790.0, 531.0, 371.0, -0.12, 0.05, 0, 0, 0])
    model = IntrinsicsModel(theta, ESTIMATE)
    values = initial_values(layout, truth)
    values.insert(intrinsics_key(), theta[:6] + np.array([4.0, -3.0, 2.0, 1.0, 0.01, 0.0]))
    sigmas = np.where(np.array([m.point == "B1" for m in measurements]), 2.0, 0.5)
    graph = gtsam.NonlinearFactorGraph()
    for factor in intrinsics_factors(dataset, layout, measurements, pixels, model, sigmas):
        graph.add(factor)
    unit = gtsam.NonlinearFactorGraph()
    for factor in intrinsics_factors(dataset, layout, measurements, pixels, model, 1.0):
        unit.add(factor)
    errors = np.concatenate([unit.at(i).unwhitenedError(values) for i in range(unit.size())]).reshape(-1, 2)
    order = np.concatenate([np.array(group) for group in _groups_of(dataset, layout, measurements)])
    expected = 0.5 * np.sum((errors / sigmas[order][:, None]) ** 2)
    assert np.isclose(graph.error(values), expected, rtol=1e-12)
    assert not np.isclose(graph.error(values), 0.5 * np.sum((errors / 0.5) ** 2), rtol=1e-3)


def _groups_of(dataset, layout, measurements):
    """The measurement indices of each stacked pixel factor, in factor order (as intrinsics_factors groups)."""
    from reference.model import measurement_arrays
    from reference.stacking import MAX_POINTS_PER_FACTOR, auto_images_per_factor, group_measurements

    _, _, landmark_rows, _, _ = measurement_arrays(dataset, layout, measurements)
    per_image = auto_images_per_factor(measurements, landmark_rows.tolist(), MAX_POINTS_PER_FACTOR)
    return group_measurements(measurements, landmark_rows.tolist(), per_image, MAX_POINTS_PER_FACTOR)


# --- Monte Carlo -----------------------------------------------------------------------------------------


@pytest.mark.slow
def test_nees_of_pose_and_intrinsics_in_its_band():
    runs, nees = 40, []
    for run in range(runs):
        data, truth = simulate_pixels(num_images=24, seed=0, noise_seed=run)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", WeakIntrinsicsWarning)
            calibration = calibrate(dataset_from_dict(data))
        error = joint_error(calibration, truth.R_cam_base, truth.t_cam_base, TRUE_INTRINSICS)
        nees.append(float(error @ np.linalg.solve(joint_covariance(calibration), error)))
    dim = 6 + len(ESTIMATE)
    low, high = chi2.ppf([0.025, 0.975], runs * dim) / runs
    assert low < np.mean(nees) < high, (np.mean(nees), low, high)


# --- the real photographs ----------------------------------------------------------------------------------


def _takahashi(takahashi_dir, absent=False):
    """The five real photographs with fx, fy, cx, cy, k1, k2 estimated (from the authors' values, or
    with fx, fy, cx, cy absent); the WeakIntrinsicsWarning it gives is checked once, here."""
    data = json.loads((takahashi_dir / "dataset.json").read_text())
    data["camera"]["estimate"] = ESTIMATE
    if absent:
        for name in ("fx", "fy", "cx", "cy"):
            del data["camera"][name]
    with pytest.warns(WeakIntrinsicsWarning, match=r"cx \(3-sigma 6\d px at the image corner\)"):  # 5 photographs
        return calibrate(dataset_from_dict(data, source="takahashi2012"))


def test_real_photographs_with_intrinsics(takahashi_dir):
    fixed = calibrate(load_dataset(takahashi_dir / "dataset.json"))
    joint = _takahashi(takahashi_dir)
    k1 = joint.camera.camera.dist[0]
    sigma3 = joint.camera.sigma3
    # Independent joint MLE: k1 = -0.24 +/- 0.03 (1 sigma), mean reprojection 0.64 -> 0.30 px,
    # T_cam_base moves by ~14 mm.
    assert abs(k1 - (-0.24)) < 0.01 and 0.08 < sigma3["k1"] < 0.10
    assert abs(np.mean(joint.residual_norms) - 0.30) < 0.005 and abs(np.mean(fixed.residual_norms) - 0.64) < 0.005
    moved_mm = 1000 * np.linalg.norm(joint.t_cam_base - fixed.t_cam_base)
    assert 12.0 < moved_mm < 16.0
    # The pose's covariance now includes the intrinsics' uncertainty: wider than with them fixed.
    assert np.all(joint.sigma3_position_mm > fixed.sigma3_position_mm)


def test_real_photographs_from_nothing_but_the_images(takahashi_dir):
    given = _takahashi(takahashi_dir)
    absent = _takahashi(takahashi_dir, absent=True)
    assert absent.converged
    for name, s3 in given.camera.sigma3.items():
        a = getattr(absent.camera.camera, name, None)
        g = getattr(given.camera.camera, name, None)
        if a is None:
            a, g = absent.camera.camera.dist[ESTIMATE.index(name) - 4], given.camera.camera.dist[ESTIMATE.index(name) - 4]
        assert abs(a - g) < 1e-3 * s3, name  # the same optimum
    assert np.linalg.norm(absent.t_cam_base - given.t_cam_base) < 1e-6


# --- Cramér-Rao bounds, plan, camera_info ------------------------------------------------------------


def test_cramer_rao_bound_with_intrinsics_matches_the_mle_covariance(simulated):
    from mirror_fg.solver.information.crb import intrinsics_cramer_rao_bound

    data, truth, calibration = simulated
    at_truth = copy.deepcopy(data)
    at_truth["camera"].update({k: TRUE_INTRINSICS[k] for k in ("fx", "fy", "cx", "cy")})
    at_truth["camera"]["dist"] = [TRUE_INTRINSICS["k1"], TRUE_INTRINSICS["k2"], 0.0, 0.0, 0.0]
    bound = intrinsics_cramer_rao_bound(dataset_from_dict(at_truth), truth, ESTIMATE)
    # The bound at the truth and the MLE's covariance at its estimate: the same to first order.
    ratio = np.sqrt(np.diag(bound.covariance) / np.diag(calibration.camera.covariance))
    assert np.all(np.abs(ratio - 1) < 0.15), ratio
    ratio = np.sqrt(np.diag(bound.pose_covariance) / np.diag(calibration.covariance))
    assert np.all(np.abs(ratio - 1) < 0.15), ratio


def test_plan_bounds_the_intrinsics():
    from mirror_fg.analysis.plan import PlanSetup, format_plan, plan

    result = plan(PlanSetup(num_images=30, fiducials=BOARD, estimate=("fx", "k1")), draws=1)
    assert set(result.intrinsics_sigma3) == {"fx", "k1"} and result.intrinsics_sigma3["fx"] > 0
    # Estimating intrinsics costs pose accuracy; the fixed-intrinsics bound is the old one.
    assert np.all(result.sigma3_position_mm >= result.sigma3_position_mm_fixed_intrinsics)
    fixed = plan(PlanSetup(num_images=30, fiducials=BOARD), draws=1)
    assert np.allclose(fixed.sigma3_position_mm, result.sigma3_position_mm_fixed_intrinsics)
    assert fixed.intrinsics_sigma3 is None
    text = format_plan(result)
    assert "intrinsics (3-sigma): fx" in text and "include the intrinsics' uncertainty" in text
    # focal_px scales the pixel bounds, not the distortion's
    doubled = plan(PlanSetup(num_images=30, fiducials=BOARD, estimate=("fx", "k1"), focal_px=1600.0, pixel_sigma=2.0),
                   draws=1)
    assert np.isclose(doubled.intrinsics_sigma3["fx"], 2 * result.intrinsics_sigma3["fx"], rtol=1e-6)
    assert np.isclose(doubled.intrinsics_sigma3["k1"], result.intrinsics_sigma3["k1"], rtol=1e-6)


def test_camera_info_yaml_of_the_estimated_camera(simulated):
    import yaml

    from mirror_fg.io.ros import camera_info_text

    _, _, calibration = simulated
    camera = calibration.camera.camera
    info = yaml.safe_load(camera_info_text(camera, "front_camera", calibration.camera.sigma3))
    K = np.array(info["camera_matrix"]["data"]).reshape(3, 3)
    assert np.array_equal(K, camera.K) and info["distortion_model"] == "plumb_bob"
    assert info["distortion_coefficients"]["data"] == list(camera.dist)
    assert np.array_equal(np.array(info["projection_matrix"]["data"]).reshape(3, 4)[:, :3], camera.K)
    assert (info["image_width"], info["image_height"], info["camera_name"]) == (1024, 768, "front_camera")


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
def test_robust_kernel_inside_stacked_factors_equals_per_measurement_robust_factors(kernel):
    from functools import partial

    from reference.intrinsics_factors import _group_error, _Group
    from reference.model import measurement_arrays
    from reference.reflection import noise_model

    data, truth = simulate_pixels(num_images=9, sigma=0.3)
    data["images"][4]["observations"]["B3"][0] += 15.0  # an outlier far in the kernel's tail
    dataset = dataset_from_dict(data)
    layout = GraphLayout.for_dataset(dataset)
    measurements = measurements_of(dataset)
    by_id = {image.id: image for image in dataset.images}
    pixels = np.array([by_id[m.image_id].observations[m.point] for m in measurements])
    theta = np.array([TRUE_INTRINSICS[n] for n in ESTIMATE] + [0.0, 0.0, 0.0])
    model = IntrinsicsModel(theta, ESTIMATE)
    values = initial_values(layout, truth)
    values.insert(intrinsics_key(), theta[:6] + np.array([3.0, -2.0, 1.0, 1.0, 0.01, 0.0]))
    stacked, single = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
    for factor in intrinsics_factors(dataset, layout, measurements, pixels, model, 0.3, robust=kernel):
        stacked.add(factor)
    point_keys, mirror_rows, landmark_rows, base_points, _ = measurement_arrays(dataset, layout, measurements)
    for i in range(len(measurements)):
        group = _Group(point_keys, mirror_rows[[i]], landmark_rows[[i]], base_points[[i]], pixels[[i]], np.array([0.3]))
        single.add(gtsam.CustomFactor(noise_model(np.array([0.3, 0.3]), kernel), [layout.pose_key, intrinsics_key(),
                                      *group.keys], partial(_group_error, model, group)))
    assert len(stacked.keys()) == len(single.keys()) and stacked.size() < single.size()
    assert np.isclose(stacked.error(values), single.error(values), rtol=1e-10)
    ordering = gtsam.Ordering()
    for key in sorted(single.keys()):
        ordering.push_back(key)
    H_stacked, g_stacked = stacked.linearize(values).hessian(ordering)
    H_single, g_single = single.linearize(values).hessian(ordering)
    assert np.allclose(H_stacked, H_single, rtol=1e-9, atol=1e-9 * np.abs(H_single).max())
    assert np.allclose(g_stacked, g_single, rtol=1e-9, atol=1e-9 * np.abs(g_single).max())


def test_without_covariance():
    data, _ = simulate_pixels(num_images=9)
    with warnings.catch_warnings():
        warnings.simplefilter("error", WeakIntrinsicsWarning)  # no covariance: no weakness judged
        calibration = calibrate(dataset_from_dict(data), compute_covariance=False)
    assert calibration.covariance is None and calibration.camera.covariance is None
    assert calibration.camera.pose_cross_covariance is None and calibration.camera.sigma3 is None
    assert calibration.converged and calibration.residual_units == "px"
