"""The independent reference of the general view model (views_reference.py) against itself: noise-free
data give the truth, the complex-step Jacobian equals central differences, the covariance matches a
Monte Carlo, the gauge is held, and the generated views are physically plausible."""
from types import SimpleNamespace

import numpy as np
import pytest

import views_reference as vr

CASE_NAMES = list(vr.CASES)


@pytest.mark.parametrize("name", CASE_NAMES)
def test_noise_free_mle_from_a_perturbed_start_is_the_truth(name):
    dataset, truth = vr.CASES[name](None)  # no noise
    ref = vr.reference_mle(dataset, truth, perturbation=0.01, seed=3)  # 0.6 deg, 1 mm off the truth
    assert ref.cost < 1e-16
    for c, (R, t) in truth.T_cam_base.items():
        assert np.abs(vr.pose_error(R, t, *ref.poses[c])).max() < 1e-9, c
    for p, v in truth.mirrors.items():
        assert np.abs(ref.mirrors[p] - v).max() < 1e-9, p
    for n, x in truth.points.items():
        assert np.abs(ref.points[n] - x).max() < 1e-9, n


@pytest.mark.parametrize("name", CASE_NAMES)
def test_noisy_mle_does_not_depend_on_the_start(name):
    """One optimum near the truth: started 0.6 deg / 1 mm away, the noisy MLE is the one from the truth."""
    dataset, truth = vr.CASES[name](0)
    from_truth = vr.reference_mle(dataset, truth)
    from_elsewhere = vr.reference_mle(dataset, truth, perturbation=0.01, seed=5)
    assert abs(from_elsewhere.cost - from_truth.cost) < 1e-9 * from_truth.cost
    for p, v in from_truth.mirrors.items():
        z = (from_elsewhere.mirrors[p] - v) / np.sqrt(np.diag(from_truth.mirror_cov[p]))
        assert np.abs(z).max() < 1e-4, p
    for c, (R, t) in from_truth.poses.items():
        var = np.diag(from_truth.pose_cov[c])
        e = vr.pose_error(R, t, *from_elsewhere.poses[c])
        assert np.all(np.abs(e[var > 0]) < 1e-4 * np.sqrt(var[var > 0])) and np.all(e[var == 0] == 0), c


@pytest.mark.parametrize("name", CASE_NAMES)
def test_complex_step_jacobian_equals_central_differences(name):
    dataset, truth = vr.CASES[name](0)
    problem = vr.read_problem(dataset)
    model = vr.Model(problem, *vr.start_state(problem, truth))
    x = np.random.default_rng(1).normal(0, 1e-3, model.size)  # away from the linearisation point
    J = model.jacobian(x)
    h = 1e-6
    numeric = np.array([(model.residuals(x + h * e) - model.residuals(x - h * e)) / (2 * h)
                        for e in np.eye(model.size)]).T
    assert J.shape == (model.residuals(x).size, model.size)
    assert np.abs(J - numeric).max() < 1e-5 * max(1.0, np.abs(J).max())
    assert np.linalg.matrix_rank(J) == model.size  # every unknown observable, the gauge fixed


def test_reported_covariances_are_blocks_of_the_inverse_fisher_information():
    """With fiducials every pose, mirror vector and point parameter is docs/formats.md's perturbation itself
    (R = Exp(dtheta) R0, t = t0 + dt, v = v0 + dv), so each reported block is the block of (J^T J)^-1."""
    dataset, truth = vr.mixed_two_handheld(None)
    ref = vr.reference_mle(dataset, truth)
    problem = vr.read_problem(dataset)
    model = vr.Model(problem, *vr.start_state(problem, truth))
    J = model.jacobian(np.zeros(model.size))
    cov_x = np.linalg.inv(J.T @ J)
    s = model.slices[("pose", vr.SINGLE)]
    np.testing.assert_allclose(ref.pose_cov[vr.SINGLE], cov_x[s, s], rtol=1e-6)
    s = model.slices[("mirror", (2, 1))]
    np.testing.assert_allclose(ref.mirror_cov[(2, 1)], cov_x[s, s], rtol=1e-6)
    np.testing.assert_allclose(ref.joint_pose_cov, ref.pose_cov[vr.SINGLE], rtol=0, atol=0)


@pytest.mark.slow
def test_covariance_matches_monte_carlo_rig_two_cameras():
    """200 noisy trials of case (e): the sample covariance of the MLE errors (docs/formats.md's convention, truth
    as reference) against the reference covariance at the truth."""
    dataset, truth = vr.rig_two_cameras(None)
    predicted = vr.reference_mle(dataset, truth)
    errors = []
    for seed in range(200):
        noisy, _ = vr.rig_two_cameras(seed)
        ref = vr.reference_mle(noisy, truth, passes=1)
        e = [vr.pose_error(*truth.T_cam_base[c], *ref.poses[c]) for c in ref.poses]
        e += [ref.mirrors[p] - truth.mirrors[p] for p in ref.mirrors]
        errors.append(np.concatenate(e))
    errors = np.array(errors)
    labels = list(predicted.blocks)
    assert [k for k, _ in labels][:2] == ["pose", "pose"]
    P = predicted.covariance
    nees = np.einsum("ij,jk,ik->i", errors, np.linalg.inv(P), errors)
    assert 0.8 < nees.mean() / P.shape[0] < 1.25, nees.mean() / P.shape[0]
    ratio = np.diag(np.cov(errors.T, bias=True)) / np.diag(P)
    pose = ratio[:12]
    assert 0.75 < pose.min() and pose.max() < 1.33, pose  # 200 samples: a variance ratio's sigma is 0.1
    assert 0.8 < np.median(ratio) < 1.25, np.median(ratio)


def test_gauge_without_fiducials_scale_by_mirror_is_held():
    dataset, truth = vr.kaleidoscope_three_mirrors_one_point(0)
    assert dataset["fiducials"] == {} and "mirror" in dataset["scale"]
    ref = vr.reference_mle(dataset, truth, perturbation=0.01)
    d = dataset["scale"]["distance"]
    v = ref.mirrors[(1, 0)]
    assert abs(np.linalg.norm(v) - d) < 1e-12
    R, t = ref.poses[vr.SINGLE]
    assert np.array_equal(R, np.eye(3)) and np.array_equal(t, np.zeros(3))
    assert np.array_equal(ref.pose_cov[vr.SINGLE], np.zeros((6, 6)))
    cov = ref.mirror_cov[(1, 0)]
    u = v / d
    eig = np.linalg.eigvalsh(cov)
    assert u @ cov @ u < 1e-12 * eig.max() and eig[1] > 1e-6 * eig.max()  # rank 2, null along v
    for p in [(2, 0), (3, 0)]:
        assert np.linalg.eigvalsh(ref.mirror_cov[p])[0] > 0  # the other mirrors are free in 3D


def test_gauge_without_fiducials_scale_by_points_is_held():
    dataset, truth = vr.kaleidoscope_three_mirrors_one_point(0, scale_by_points=True)
    assert dataset["scale"]["points"] == ["P0", "P1"]
    ref = vr.reference_mle(dataset, truth, perturbation=0.01)
    assert abs(np.linalg.norm(ref.points["P1"] - ref.points["P0"]) - dataset["scale"]["distance"]) < 1e-12
    # the P0-P1 distance is exact, so its variance is zero to first order
    u = vr.unit(ref.points["P1"] - ref.points["P0"])
    G = np.r_[-u, u]
    b0, b1 = ref.blocks[("point", "P0")], ref.blocks[("point", "P1")]
    idx = np.r_[np.arange(b0.start, b0.stop), np.arange(b1.start, b1.stop)]
    assert G @ ref.covariance[np.ix_(idx, idx)] @ G < 1e-12 * np.trace(ref.point_cov["P0"])


def _chain_checks(dataset, truth):
    """Per observation, with the reference's camera-frame model at the truth: pixel (noise free), and the
    plausibility flags (in front, before each reflection on the camera's side)."""
    problem = vr.read_problem(dataset)
    model = vr.Model(problem, *vr.start_state(problem, truth))
    x0 = np.zeros(model.size)
    poses = {c: model.pose(x0, c) for c in problem.cameras}
    for (cam, refl, names, obs), image in zip(problem.images, dataset["images"]):
        R, t = poses[cam]
        X = np.array([problem.fiducials[n] if n in problem.fiducials else truth.points[n] for n in names])
        p = X @ R.T + t
        for pl in refl:
            n, d = model.plane_in(x0, pl, cam, poses)
            n, d = np.real(n), float(np.real(d))
            before = p @ n - d
            assert np.all(np.sign(before) == np.sign(-d)), (image["id"], pl)  # camera centre side
            p = p - 2 * np.outer(before, n)
        assert np.all(p[:, 2] > 0.1), image["id"]
        K = problem.cameras[cam]
        yield image, np.c_[K["fx"] * p[:, 0] / p[:, 2] + K["cx"], K["fy"] * p[:, 1] / p[:, 2] + K["cy"]], obs, K


@pytest.mark.parametrize("name", CASE_NAMES)
def test_generated_views_are_plausible(name):
    noisy, truth = vr.CASES[name](0)
    clean, _ = vr.CASES[name](None)
    assert [im["id"] for im in noisy["images"]] == [im["id"] for im in clean["images"]]
    sigma = noisy["pixel_sigma"]
    for (image, pix, obs, K), noisy_image in zip(_chain_checks(clean, truth), noisy["images"]):
        np.testing.assert_allclose(obs, pix, atol=1e-9)  # the generator's base-frame model agrees
        noisy_obs = np.array(list(noisy_image["observations"].values()))
        assert np.all((noisy_obs >= 0) & (noisy_obs <= [K["width"], K["height"]])), image["id"]
        assert 0 < np.abs(noisy_obs - obs).max() < 6 * sigma
        for l, m in image["reflections"]:
            assert 1 <= l <= noisy["num_mirrors"]
        refl = image["reflections"]
        assert all(a[0] != b[0] for a, b in zip(refl, refl[1:])), image["id"]
        assert len(image["observations"]) >= (1 if not noisy["fiducials"] else 12), image["id"]


def _views(dataset, camera=None):
    return [tuple(map(tuple, im["reflections"])) for im in dataset["images"]
            if camera is None or im.get("camera") == camera]


def test_scene_designs():
    a, _ = vr.kaleidoscope_two_mirrors(0)
    assert set(_views(a)) == {(), ((1, 0),), ((2, 0),), ((1, 0), (2, 0)), ((2, 0), (1, 0))}
    assert min(len(im["observations"]) for im in a["images"]) >= 20 and "camera" in a
    b, _ = vr.mixed_two_handheld(0)
    alone = [v[0] for v in _views(b) if len(v) == 1]
    assert () not in _views(b)
    assert len({p for p in alone if p[0] == 1}) >= 3 and len({p for p in alone if p[0] == 2}) >= 3
    assert any(v[0][0] == 1 for v in _views(b) if len(v) == 2) and any(v[0][0] == 2 for v in _views(b) if len(v) == 2)
    c, _ = vr.mixed_one_mirror_gives_pose(0)
    alone = [v[0] for v in _views(c) if len(v) == 1]
    assert () not in _views(c) and len({p for p in alone if p[0] == 1}) >= 3
    assert len({p for p in alone if p[0] == 2}) <= 2
    in_doubles = {p for v in _views(c) if len(v) == 2 for p in v if p[0] == 2}
    assert len(in_doubles - set(alone)) >= 2
    d, _ = vr.kaleidoscope_three_mirrors_one_point(0)
    orders = [len(v) for v in _views(d)]
    assert d["fiducials"] == {} and orders.count(0) == 1 and orders.count(1) == 3 and orders.count(2) == 6
    for name, cams in [("rig_two_cameras", ["left", "right"]), ("rig_three_cameras", ["left", "right", "top"])]:
        e, truth = vr.CASES[name](0)
        assert list(e["cameras"]) == cams and "camera" not in e
        intrinsics = [(k["width"], k["fx"]) for k in e["cameras"].values()]
        assert len(set(intrinsics)) == len(cams)
        seen = {cam: {v[0] for v in _views(e, cam)} for cam in cams}
        shared = seen["left"] & seen["right"]
        assert len(shared) >= 2
        for cam in ["left", "right"]:
            assert len(seen[cam] - shared) >= 3
        assert truth.owners[sorted(seen["right"] - shared)[0]] == "right"
        assert all(truth.owners[p] == "left" for p in shared)
        if "top" in cams:
            assert len(seen["top"]) == 2 and seen["top"] <= shared


def test_rig_transform_and_its_covariance():
    dataset, truth = vr.rig_two_cameras(0)
    ref = vr.reference_mle(dataset, truth)
    R, t, cov = ref.rig("left", "right")
    (Rl, tl), (Rr, tr) = ref.poses["left"], ref.poses["right"]
    x = np.array([0.1, -0.2, 0.9])  # a point in the left camera's frame
    np.testing.assert_allclose(R @ x + t, Rr @ (Rl.T @ (x - tl)) + tr, atol=1e-12)
    # the propagation against the first-order rig error by hand: R' = Exp(a_r) R Exp(-a_l) = Exp(a_r - R a_l) R,
    # t' = t_r + dt_r - R' (t_l + dt_l) ~ t + dt_r - R dt_l - [a_r - R a_l]x R t_l
    G = np.zeros((6, 12))
    G[:3, :3], G[:3, 6:9] = -R, np.eye(3)
    G[3:, 3:6], G[3:, 9:12] = -R, np.eye(3)
    G[3:, :] += vr.skew(R @ tl) @ G[:3, :]  # -[d]x R t_l = [R t_l]x d
    np.testing.assert_allclose(cov, G @ ref.joint_pose_cov @ G.T, rtol=1e-7, atol=1e-7 * np.abs(cov).max())
    # and against a Monte Carlo of the joint pose covariance (linear regime: samples x 1e-3)
    rng = np.random.default_rng(0)
    L = np.linalg.cholesky(ref.joint_pose_cov + 1e-30 * np.eye(12))
    samples = []
    for _ in range(4000):
        e = 1e-3 * (L @ rng.normal(size=12))
        Rf, tf = vr.exp_so3(e[:3]) @ Rl, tl + e[3:6]
        Rt, tt = vr.exp_so3(e[6:9]) @ Rr, tr + e[9:12]
        samples.append(vr.pose_error(R, t, Rt @ Rf.T, tt - Rt @ Rf.T @ tf) / 1e-3)
    sample_cov = np.cov(np.array(samples).T)
    np.testing.assert_allclose(np.sqrt(np.diag(sample_cov)), np.sqrt(np.diag(cov)), rtol=0.06)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # shared placements correlate the cameras: the rig is better known than the poses' sum would say
    uncorrelated = ref.joint_pose_cov.copy()
    uncorrelated[:6, 6:] = uncorrelated[6:, :6] = 0
    independent = vr.rig_transform(ref.poses, uncorrelated, ["left", "right"], "left", "right")[2]
    assert not np.allclose(cov, independent, rtol=0.05)


def _as_calibration(ref, dataset, shift_sigmas=0.0, cov_scale=1.0):
    """The reference dressed as a mirror_fg.Calibration (the attributes compare reads), every estimate
    moved by ``shift_sigmas`` of its own sigma, every covariance scaled by ``cov_scale``."""
    def moved(x, cov):
        return x + shift_sigmas * np.sqrt(np.diag(cov))

    cams = {}
    for c, (R, t) in ref.poses.items():
        e = shift_sigmas * np.sqrt(np.diag(ref.pose_cov[c]))
        cams[c] = SimpleNamespace(R_cam_base=vr.exp_so3(e[:3]) @ R, t_cam_base=t + e[3:],
                                  covariance=cov_scale * ref.pose_cov[c])
    cal = SimpleNamespace(mirror_vectors={p: moved(v, ref.mirror_cov[p]) for p, v in ref.mirrors.items()},
                          mirror_covariances={p: cov_scale * c for p, c in ref.mirror_cov.items()},
                          points={n: moved(x, ref.point_cov[n]) for n, x in ref.points.items()},
                          point_covariances={n: cov_scale * c for n, c in ref.point_cov.items()},
                          cameras=cams if "cameras" in dataset else None)
    if "cameras" not in dataset:
        first = cams[vr.SINGLE]
        cal.R_cam_base, cal.t_cam_base, cal.covariance = first.R_cam_base, first.t_cam_base, first.covariance
    return cal


@pytest.mark.parametrize("name", ["kaleidoscope_three_mirrors_one_point", "rig_three_cameras"])
def test_compare_measures_in_reference_sigmas(name):
    dataset, truth = vr.CASES[name](0)
    ref = vr.reference_mle(dataset, truth)
    same = vr.compare(_as_calibration(ref, dataset), ref, dataset)
    assert same.worst_sigmas < 1e-9 and abs(same.ratio_min - 1) < 1e-12 and abs(same.ratio_max - 1) < 1e-12
    assert same.gauge_error == 0.0
    off = vr.compare(_as_calibration(ref, dataset, shift_sigmas=0.1, cov_scale=1.21), ref, dataset)
    assert abs(off.worst_sigmas - 0.1) < 1e-3, off.worst_label
    assert abs(off.ratio_min - 1.1) < 1e-9 and abs(off.ratio_max - 1.1) < 1e-9


def test_reference_imports_nothing_from_mirror_fg():
    import ast
    from pathlib import Path

    for module in ("views_reference.py", "views_scenes.py"):
        tree = ast.parse((Path(__file__).parent / module).read_text())
        names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
        assert not [n for n in names if n.split(".")[0] == "mirror_fg"], module
