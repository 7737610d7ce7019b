"""Tests of mirror_fg.simulate.tree: the scenes agree with their ground truth and the paper's Sect. 7 / Fig. 3."""
from __future__ import annotations

import json
from collections import defaultdict

import numpy as np
import pytest

from mirror_fg.simulate import tree as simulate
from mirror_fg.io.dataset import DATASET_FORMAT
from mirror_fg.data import Dataset
from mirror_fg.core.geometry import apply_transform, nested_transform, project
from mirror_fg.simulate.tree import (
    GroundTruth,
    ground_truth_from_dict,
    simulate_base_case,
    simulate_tree,
    truth_path,
    write_simulation,
)


def _true_camera_points(ds: Dataset, truth: GroundTruth, image) -> tuple[list[str], np.ndarray]:
    """Names and noise-free camera-frame positions (eqs. 5-8) of everything the image observed."""
    vectors = [truth.mirror_vectors[(l + 1, m)] for l, m in enumerate(image.mirror_configs)]
    A, b = nested_transform(truth.R_cam_base, truth.t_cam_base, vectors)
    names = list(image.observations)
    base = np.array([ds.fiducials[n] if n in ds.fiducials else truth.points[n] for n in names])
    return names, apply_transform(A, b, base)


def _true_pixels(ds: Dataset, truth: GroundTruth, image) -> tuple[list[str], np.ndarray]:
    names, cam = _true_camera_points(ds, truth, image)
    z = project(cam)  # eq. (9)
    c = ds.camera
    return names, np.column_stack([c.fx * z[:, 0] + c.cx, c.fy * z[:, 1] + c.cy])


def _residuals(ds: Dataset, truth: GroundTruth) -> np.ndarray:
    out = []
    for image in ds.images:
        names, pixels = _true_pixels(ds, truth, image)
        out.append(np.array([image.observations[n] for n in names]) - pixels)
    return np.concatenate(out)


@pytest.fixture(scope="module")
def base_noise_free():
    return simulate_base_case(num_images=60, num_points=15, pixel_sigma=0.0, seed=3)


# ------------------------------------------------------------------------------------------ truth


def test_noise_free_observations_match_ground_truth(base_noise_free):
    ds, truth = base_noise_free
    assert np.max(np.abs(_residuals(ds, truth))) < 1e-9
    assert ds.pixel_sigma == simulate.NOISE_FREE_NOMINAL_SIGMA_PX == 1.0


@pytest.mark.parametrize("num_mirrors", [1, 2, 3])
def test_noise_free_tree_matches_ground_truth(num_mirrors):
    ds, truth = simulate_tree(num_mirrors, num_points=5, num_fiducials=4, seed=1)
    assert np.max(np.abs(_residuals(ds, truth))) < 1e-9


def test_every_point_visible_in_every_image(base_noise_free):
    ds, truth = base_noise_free
    margin = simulate.VISIBILITY_MARGIN_PX
    for image in ds.images:
        assert set(image.observations) == set(ds.fiducials) | set(truth.points)
        _, cam = _true_camera_points(ds, truth, image)
        assert np.all(cam[:, 2] > 0.0)
        px = np.array(list(image.observations.values()))
        assert np.all(px >= margin)
        assert np.all(px[:, 0] <= ds.camera.width - margin)
        assert np.all(px[:, 1] <= ds.camera.height - margin)


def test_visible_rejects_points_outside_or_behind():
    camera = simulate.default_camera()
    front = [np.array([0.0, 0.0, 0.5])]
    near_axis = np.array([[0.0, 0.0, 0.0], [0.05, 0.05, 0.0]])
    assert simulate.visible(camera, near_axis, front)
    assert not simulate.visible(camera, np.array([[0.0, 0.0, 0.6]]), front)  # behind the mirror
    assert not simulate.visible(camera, np.array([[0.7, 0.0, 0.0]]), front)  # outside the image
    assert not simulate.visible(camera, near_axis, [])  # no mirror: depth 0


def test_scene_geometry():
    ds, truth = simulate_base_case(num_images=30, num_points=30, pixel_sigma=0.0, num_fiducials=4, seed=5)
    R = truth.R_cam_base
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    angle = np.degrees(np.arccos((np.trace(R) - 1.0) / 2.0))
    assert 20.0 <= angle <= 40.0
    f = ds.fiducials
    assert list(f) == ["F0", "F1", "F2", "F3"]
    assert np.allclose(f["F0"], 0.0) and np.allclose(f["F1"], [0.2, 0, 0])
    assert np.allclose(f["F2"], [0, 0.2, 0])
    assert abs(f["F3"][2]) > 0.1  # off the triangle's plane
    anchors = np.array(list(f.values()))
    for p in truth.points.values():
        assert np.min(np.linalg.norm(anchors - p, axis=1)) <= simulate.POINT_RADIUS + 1e-12
    for (l, _), v in truth.mirror_vectors.items():
        d = np.linalg.norm(v)
        assert 0.45 - 1e-12 <= d <= 0.55 + 1e-12
        nominal = np.array([0.0, 0.0, 1.0 if l == 2 else -1.0])  # mirror 2 in front, mirror 1 behind
        assert np.degrees(np.arccos(v @ nominal / d)) <= 30.0 + 1e-9


# ------------------------------------------------------------------------------------------ structure


def test_base_case_configurations():
    ds, truth = simulate_base_case(num_images=200, pixel_sigma=0.0, seed=0)
    assert len(ds.images) == 200 and ds.num_mirrors == 2
    assert [im.id for im in ds.images[:2]] == ["img00000", "img00001"]
    assert [im.mirror_configs[1] for im in ds.images] == list(range(200))  # mirror 2 new in every image
    mirror1 = [im.mirror_configs[0] for im in ds.images]
    assert mirror1 == sorted(mirror1) and set(mirror1) == {0, 1, 2}
    assert sorted(mirror1.count(j) for j in range(3)) == [66, 67, 67]
    assert set(truth.mirror_vectors) == set(ds.configurations)
    assert len(ds.fiducials) == 3 and truth.points == {}


@pytest.mark.parametrize("num_mirrors", [1, 3])
def test_base_case_other_mirror_counts(num_mirrors):
    ds, truth = simulate_base_case(num_images=27, pixel_sigma=0.0, num_mirrors=num_mirrors, seed=2)
    assert all(len(im.mirror_configs) == num_mirrors for im in ds.images)
    assert [im.mirror_configs[-1] for im in ds.images] == list(range(27))
    if num_mirrors == 3:
        assert sorted({im.mirror_configs[:2] for im in ds.images}) == [(j // 3, j) for j in range(9)]
    assert np.max(np.abs(_residuals(ds, truth))) < 1e-9


@pytest.mark.parametrize("num_mirrors,children,images_per_leaf", [(1, 3, 1), (2, 3, 1), (3, 3, 1), (2, 4, 2)])
def test_tree_shape(num_mirrors, children, images_per_leaf):
    ds, truth = simulate_tree(num_mirrors, children=children, images_per_leaf=images_per_leaf, seed=4)
    assert len(ds.images) == children**num_mirrors * images_per_leaf
    leaves = [im.mirror_configs for im in ds.images]
    for l in range(1, num_mirrors + 1):
        assert sorted({c[l - 1] for c in leaves}) == list(range(children**l))
    for l in range(1, num_mirrors):
        kids = defaultdict(set)
        parents = defaultdict(set)
        for c in leaves:
            kids[c[l - 1]].add(c[l])
            parents[c[l]].add(c[l - 1])
        assert all(len(k) == children for k in kids.values())  # each node has `children` children
        assert all(len(p) == 1 for p in parents.values())  # and each child one parent
    leaf_counts = defaultdict(int)
    for c in leaves:
        leaf_counts[c] += 1
    assert set(leaf_counts.values()) == {images_per_leaf}
    assert set(truth.mirror_vectors) == set(ds.configurations)


@pytest.mark.parametrize("num_mirrors", [1, 2, 3, 4])
def test_nested_determinant_and_mirror_sides(num_mirrors):
    ds, truth = simulate_tree(num_mirrors, children=2, seed=6)
    for image in ds.images:
        A, _ = truth.transform(image.mirror_configs)
        assert np.allclose(A @ A.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(A), (-1.0) ** num_mirrors)
    for (l, _), v in truth.mirror_vectors.items():
        in_front = (num_mirrors - l) % 2 == 0  # mirror Nv in front, then alternating
        assert (v[2] > 0) == in_front


# ------------------------------------------------------------------------------------------ randomness


def test_deterministic_by_seed():
    kwargs = dict(num_images=12, num_points=4, pixel_sigma=0.5, mirror1_placements=3)
    (ds_a, tr_a), (ds_b, tr_b) = simulate_base_case(seed=7, **kwargs), simulate_base_case(seed=7, **kwargs)
    (ds_c, _) = simulate_base_case(seed=8, **kwargs)
    assert tr_a.to_dict() == tr_b.to_dict()
    for a, b in zip(ds_a.images, ds_b.images):
        assert a.mirror_configs == b.mirror_configs
        assert all(np.array_equal(a.observations[n], b.observations[n]) for n in a.observations)
    assert not np.allclose(ds_a.images[0].observations["F0"], ds_c.images[0].observations["F0"])


def test_pixel_noise_statistics():
    sigma = 0.7
    ds, truth = simulate_base_case(num_images=200, num_points=20, pixel_sigma=sigma, seed=11)
    assert ds.pixel_sigma == sigma
    r = _residuals(ds, truth)  # 200 images x 23 points x 2 coordinates
    assert r.size == 200 * 23 * 2
    assert abs(r.std() / sigma - 1.0) < 0.03
    assert np.all(np.abs(r.mean(axis=0)) < 0.05)  # about 5 standard errors
    assert abs(np.corrcoef(r[:, 0], r[:, 1])[0, 1]) < 0.06


# ------------------------------------------------------------------------------------------ files


def test_ground_truth_dict_round_trip(base_noise_free):
    _, truth = base_noise_free
    data = json.loads(json.dumps(truth.to_dict()))
    assert data["format"] == simulate.TRUTH_FORMAT
    assert {"mirror": 1, "config": 0} == {k: data["mirrors"][0][k] for k in ("mirror", "config")}
    back = ground_truth_from_dict(data)
    assert np.array_equal(back.R_cam_base, truth.R_cam_base)
    assert np.array_equal(back.t_cam_base, truth.t_cam_base)
    assert back.mirror_vectors.keys() == truth.mirror_vectors.keys()
    assert all(np.array_equal(back.mirror_vectors[k], v) for k, v in truth.mirror_vectors.items())
    assert back.points.keys() == truth.points.keys()
    assert all(np.array_equal(back.points[k], v) for k, v in truth.points.items())


def test_write_simulation(tmp_path):
    ds, truth = simulate_base_case(num_images=9, num_points=2, pixel_sigma=0.3, seed=1)
    path = tmp_path / "sim" / "scene.json"
    written = write_simulation(path, ds, truth)
    assert written == truth_path(path) == tmp_path / "sim" / "scene.truth.json"
    data = json.loads(path.read_text())
    assert data["format"] == DATASET_FORMAT
    assert data["num_mirrors"] == 2 and data["pixel_sigma"] == 0.3
    assert data["camera"]["width"] == 1024 and data["camera"]["fx"] == 800.0
    assert len(data["images"]) == 9
    first = data["images"][0]
    assert first["id"] == "img00000" and list(first["mirror_configs"]) == [0, 0]
    assert np.allclose(first["observations"]["P1"], ds.images[0].observations["P1"], rtol=0, atol=1e-9)
    back = ground_truth_from_dict(json.loads(written.read_text()))
    assert np.array_equal(back.R_cam_base, truth.R_cam_base)


def test_written_dataset_loads_and_normalizes(tmp_path):
    from mirror_fg.io.dataset import load_dataset

    ds, truth = simulate_tree(3, num_points=3, num_fiducials=4, seed=2)
    path = tmp_path / "tree.json"
    write_simulation(path, ds, truth)
    back = load_dataset(path)
    assert back.num_mirrors == 3 and back.camera == ds.camera
    assert [im.mirror_configs for im in back.images] == [im.mirror_configs for im in ds.images]
    for image in back.images:
        names, cam = _true_camera_points(back, truth, image)
        normalized = back.normalized(image)
        assert np.max(np.abs(np.array([normalized[n] for n in names]) - project(cam))) < 1e-9


@pytest.mark.parametrize("num_mirrors", [2, 3])
def test_sibling_normals_not_coplanar(num_mirrors):
    ds, truth = simulate_tree(num_mirrors, seed=0)
    for level in range(1, num_mirrors + 1):
        siblings = defaultdict(set)
        for image in ds.images:
            siblings[image.mirror_configs[: level - 1]].add(image.mirror_configs[level - 1])
        for configs in siblings.values():
            vectors = [truth.mirror_vectors[(level, m)] for m in configs]
            assert simulate.normal_spread(vectors) >= np.sin(np.deg2rad(2.0))


def test_degenerate_motion_only_on_request():
    ds, truth = simulate_tree(2, tilt_deg=0.0, min_normal_spread_deg=0.0, seed=0)
    assert simulate.normal_spread(list(truth.mirror_vectors.values())) < 1e-12  # all parallel
    assert np.max(np.abs(_residuals(ds, truth))) < 1e-9
    with pytest.raises(RuntimeError, match="coplanar"):
        simulate_tree(2, tilt_deg=0.0, seed=0)
