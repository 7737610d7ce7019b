"""Simulated kaleidoscopes, mixed reflection orders and rigs (mirror_fg.simulate.views / _rig).

The datasets are checked as dicts (the dataset@1 parser of `reflections` / `cameras` lands separately):
their shape, that every observation is the truth re-projected through the image's reflections (own
projection code below: point-normal planes, not the Householder form the simulator uses), and that a
point is observed exactly where the light can take the view's path (own segment test below).
"""
from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from mirror_fg.cli import main
from mirror_fg.core.camera import Camera
from mirror_fg.core.geometry import measurement
from mirror_fg.simulate.tree import ground_truth_from_dict
from mirror_fg.simulate.rig import simulate_rig_mixed, simulate_rig_tree
from mirror_fg.simulate.views import (
    MIN_FIDUCIALS_PER_VIEW,
    observe,
    simulate_kaleidoscope,
    simulate_mixed,
)
from mirror_fg.simulate.views_truth import load_views_truth, views_truth_from_dict

MARGIN = 20.0


# --- independent geometry -------------------------------------------------------------------------


def plane_point_normal(truth, placement, camera):
    """(q, n): a point of the placement's plane and its unit normal in ``camera``'s frame, moved there
    from the owner's frame through the base frame point by point."""
    owner = truth.mirror_cameras.get(placement, truth.first_camera)
    v = truth.mirror_vectors[placement]
    n = v / np.linalg.norm(v)
    R_o, t_o = truth.poses[owner]
    R_c, t_c = truth.poses[camera]
    q_base, n_base = R_o.T @ (v - t_o), R_o.T @ n
    return R_c @ q_base + t_c, R_c @ n_base


def mirror_point(x, q, n):
    return x - 2.0 * float(n @ (x - q)) * n


def camera_matrix(camera: dict) -> np.ndarray:
    return np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])


def base_points(dataset, truth):
    points = {name: np.array(p) for name, p in dataset["fiducials"].items()}
    points.update(truth.points)
    return points


def image_camera(dataset, image):
    if "cameras" in dataset:
        return image["camera"], dataset["cameras"][image["camera"]]
    return None, dataset["camera"]


def reflections_of(image):
    if "reflections" in image:
        return [tuple(p) for p in image["reflections"]]
    return [(l + 1, m) for l, m in enumerate(image["mirror_configs"])]


def crosses(a, b, q, n):
    """Whether the open segment a-b crosses the plane (q, n)."""
    sa, sb = float(n @ (a - q)), float(n @ (b - q))
    return (sa < -1e-12 and sb > 1e-12) or (sa > 1e-12 and sb < -1e-12)


def physically_seen(x, path, planes):
    """Whether light from camera-frame point ``x`` reaches the camera (origin) through ``path``
    (point-normal planes in light order), every plane in ``planes`` infinite and reflective on the camera's
    side: unfold with virtual points, find the reflection points one by one, and require that no leg
    crosses any plane except at its ends."""
    virtual = [x]
    for q, n in path:
        if float(n @ (virtual[-1] - q)) >= 0.0:  # not on the reflective side
            return False
        virtual.append(mirror_point(virtual[-1], q, n))
    # Walk back from the camera: leg k goes from the last bounce to the plane before it.
    start, vertices = np.zeros(3), [np.zeros(3)]
    for k in range(len(path) - 1, -1, -1):
        q, n = path[k]
        target = virtual[k + 1]  # the image of x in mirrors 1..k+1, seen from `start` straight
        d = target - start
        s = float(n @ (q - start)) / float(n @ d)
        if not 0.0 < s < 1.0:
            return False
        hit = start + s * d
        vertices.append(hit)
        start = hit  # reflected there, the light came from the image of x in the mirrors before it
    vertices.append(x)
    for a, b in zip(vertices[:-1], vertices[1:]):
        for q, n in planes:
            if crosses(a, b, q, n):
                return False
    return True


def noise_free_check(dataset, truth):
    """Every observation = the truth re-projected through the image's reflections (<= 1e-8 px), inside
    the image by the margin."""
    points = base_points(dataset, truth)
    worst = 0.0
    for image in dataset["images"]:
        name, camera = image_camera(dataset, image)
        R, t = truth.poses[name]
        K = camera_matrix(camera)
        path = [plane_point_normal(truth, p, name) for p in reflections_of(image)]
        for point, z in image["observations"].items():
            x = R @ points[point] + t
            for q, n in path:
                x = mirror_point(x, q, n)
            pixel = (K @ x)[:2] / x[2]
            worst = max(worst, float(np.max(np.abs(pixel - z))))
            assert MARGIN <= z[0] <= camera["width"] - MARGIN and MARGIN <= z[1] <= camera["height"] - MARGIN
    assert worst < 1e-8, worst
    return worst


def seen_check(dataset, truth, candidate_views, photos):
    """For each photograph (its planes) and each candidate view: a point is observed in an image of that
    view iff it is physically seen; views without an image see too few points."""
    points = base_points(dataset, truth)
    by_key = {(image.get("camera"), image["id"].rsplit("_", 1)[0] if photos else "", tuple(reflections_of(image))): image
              for image in dataset["images"]}
    checked = 0
    for (camera_name, photo), planes_keys, views in candidate_views:
        R, t = truth.poses[camera_name]
        camera = dataset["cameras"][camera_name] if camera_name is not None else dataset["camera"]
        K = camera_matrix(camera)
        planes = [plane_point_normal(truth, p, camera_name) for p in planes_keys]
        for view in views:
            image = by_key.get((camera_name, photo, tuple(view)))
            path = [plane_point_normal(truth, p, camera_name) for p in view]
            seen = set()
            for point, Bp in points.items():
                x = R @ Bp + t
                if not physically_seen(x, path, planes):
                    continue
                for q, n in path:
                    x = mirror_point(x, q, n)
                pixel = (K @ x)[:2] / x[2]
                if x[2] > 0 and MARGIN <= pixel[0] <= camera["width"] - MARGIN and MARGIN <= pixel[1] <= camera["height"] - MARGIN:
                    seen.add(point)
            if image is None:
                assert len(seen & set(dataset["fiducials"])) < MIN_FIDUCIALS_PER_VIEW or not seen, (photo, view)
            else:
                checked += 1
                assert set(image["observations"]) == seen, (photo, view)
    return checked


# --- kaleidoscopes --------------------------------------------------------------------------------


@pytest.mark.parametrize("num_mirrors", [2, 3])
@pytest.mark.parametrize("target", [True, False])
def test_kaleidoscope_views_shape_truth_and_visibility(num_mirrors, target):
    dataset, truth = simulate_kaleidoscope(num_mirrors, target=target, num_points=None if target else 2,
                                           pixel_sigma=0.0, seed=1)
    assert dataset["format"] == "mirror-fg/dataset@1" and dataset["num_mirrors"] == num_mirrors
    assert "cameras" not in dataset and dataset["camera"]["width"] == 1024
    views = [tuple(reflections_of(image)) for image in dataset["images"]]
    assert len(set(views)) == len(views)
    mirrors = range(1, num_mirrors + 1)
    assert views.count(()) == 1
    assert {v for v in views if len(v) == 1} == {((l, 0),) for l in mirrors}
    seconds = {v for v in views if len(v) == 2}
    assert len(seconds) >= 2 and seconds <= {((i, 0), (j, 0)) for i in mirrors for j in mirrors if i != j}
    assert set(truth.mirror_vectors) == {(l, 0) for l in mirrors}
    if target:
        assert len(dataset["fiducials"]) == 4 and "scale" not in dataset
        assert all(len(set(im["observations"]) & set(dataset["fiducials"])) >= 4 for im in dataset["images"])
    else:
        assert dataset["fiducials"] == {} and set(truth.points) == {"P0", "P1"}
        assert dataset["scale"] == {"mirror": 1, "config": 0,
                                    "distance": pytest.approx(float(np.linalg.norm(truth.mirror_vectors[(1, 0)])), abs=0)}
        R, t = truth.poses[None]
        np.testing.assert_array_equal(R, np.eye(3))
        np.testing.assert_array_equal(t, np.zeros(3))
    noise_free_check(dataset, truth)
    all_views = [[]] + [[(l, 0)] for l in mirrors] + [[(i, 0), (j, 0)] for i in mirrors for j in mirrors if i != j]
    assert seen_check(dataset, truth, [((None, ""), list(truth.mirror_vectors), all_views)], photos=False) == len(views)


def test_kaleidoscope_refuses_views_the_light_cannot_take():
    """A 72 deg wedge has five chambers: the third-order views are blocked (the traced check drops
    them), although each point is on the reflective side of every mirror in turn."""
    dataset, truth = simulate_kaleidoscope(2, pixel_sigma=0.0, seed=0)
    points = base_points(dataset, truth)
    R, t = truth.poses[None]
    planes = [plane_point_normal(truth, p, None) for p in truth.mirror_vectors]
    camera_points = np.array([R @ p + t for p in points.values()])
    sides_only = 0
    for view in ([(1, 0), (2, 0), (1, 0)], [(2, 0), (1, 0), (2, 0)]):
        path = [plane_point_normal(truth, p, None) for p in view]
        assert not any(physically_seen(x, path, planes) for x in camera_points)
        vectors = [truth.mirror_vectors[p] for p in view]
        _, seen = observe(Camera(**{k: dataset["camera"][k] for k in ("width", "height", "fx", "fy", "cx", "cy")}),
                          camera_points, vectors, list(truth.mirror_vectors.values()))
        assert not seen.any()
        sides_only += observe(Camera(1024, 768, 800.0, 800.0, 512.0, 384.0), camera_points, vectors)[1].sum()
    assert sides_only > 0  # the sides and the image alone would have kept some


def test_measurement_model_agrees_on_a_kaleidoscope():
    """The library's eq. (5)/(9) prediction of each noise-free observation, normalized."""
    dataset, truth = simulate_kaleidoscope(3, pixel_sigma=0.0, seed=2)
    K_inv = np.linalg.inv(camera_matrix(dataset["camera"]))
    R, t = truth.poses[None]
    for image in dataset["images"]:
        vectors = [truth.vector(p) for p in reflections_of(image)]
        for name, z in image["observations"].items():
            expected = (K_inv @ [z[0], z[1], 1.0])[:2]
            np.testing.assert_allclose(measurement(R, t, vectors, dataset["fiducials"][name]), expected, atol=1e-12)


# --- two hand-held mirrors ------------------------------------------------------------------------


@pytest.mark.parametrize("placements, direct", [((4, 4), 0), ((4, 2), 2)])
def test_mixed_views(placements, direct):
    dataset, truth = simulate_mixed(placements, direct=direct, pixel_sigma=0.0, seed=3)
    n1, n2 = placements
    photos = {}
    for image in dataset["images"]:
        photos.setdefault(image["id"].rsplit("_", 1)[0], []).append(tuple(reflections_of(image)))
    assert len(photos) == max(n1, n2)
    for i, views in enumerate(photos.values()):
        a, b = (1, i % n1), (2, i % n2)
        assert sorted(views) == sorted([(a,), (b,), (a, b), (b, a)] + ([()] if i < direct else []))
    assert set(truth.mirror_vectors) == {(1, m) for m in range(n1)} | {(2, k) for k in range(n2)}
    alone = {v[0] for image in dataset["images"] if len(v := reflections_of(image)) == 1}
    assert len({p for p in alone if p[0] == 1}) == n1  # >= 3 placements of mirror 1 seen alone
    normals = np.array([truth.mirror_vectors[(1, m)] / np.linalg.norm(truth.mirror_vectors[(1, m)]) for m in range(n1)])
    assert np.linalg.svd(normals, compute_uv=False)[2] >= np.sin(np.deg2rad(2.0))
    noise_free_check(dataset, truth)
    candidates = []
    for i in range(max(n1, n2)):
        a, b = (1, i % n1), (2, i % n2)
        views = [[a], [b], [a, b], [b, a]] + ([[]] if i < direct else [])
        candidates.append(((None, f"img{i:03d}"), [a, b], views))
    assert seen_check(dataset, truth, candidates, photos=True) == len(dataset["images"])


def test_mixed_refuses_data_without_a_start():
    with pytest.raises(ValueError, match="3 placements"):
        simulate_mixed((2, 2))
    simulate_mixed((2, 2), direct=1, pixel_sigma=0.0)  # a direct view gives the pose


# --- rigs -----------------------------------------------------------------------------------------


def placement_cameras(dataset):
    seen = {}
    for image in dataset["images"]:
        for p in reflections_of(image):
            seen.setdefault(p, []).append(image["camera"])
    return seen


def check_rig(dataset, truth):
    names = list(dataset["cameras"])
    assert list(truth.poses) == names and all(image["camera"] in names for image in dataset["images"])
    intrinsics = {(c["width"], c["fx"], c["cx"]) for c in dataset["cameras"].values()}
    assert len(intrinsics) == len(names)
    seen = placement_cameras(dataset)
    for p, cameras in seen.items():  # the frame of each mirror vector: the first camera that sees it
        assert truth.mirror_cameras[p] == min(cameras, key=names.index)
    noise_free_check(dataset, truth)
    return seen


def test_rig_tree_shared_and_own_placements():
    dataset, truth = simulate_rig_tree(2, own=[27, 27], shared=6, pixel_sigma=0.0, seed=4)
    seen = check_rig(dataset, truth)
    shared = {p for p, cams in seen.items() if len(set(cams)) == 2}
    assert len({p for p in shared if p[0] == 2}) == 6 and len({p for p in shared if p[0] == 1}) == 3
    assert any(len(set(cams)) == 1 for cams in seen.values())
    assert {p for p, cams in seen.items() if set(cams) == {"cam1"}} and truth.mirror_cameras[next(
        p for p, cams in seen.items() if set(cams) == {"cam1"})] == "cam1"
    by_id = {}
    for image in dataset["images"]:  # shared photographs: the same mirror_configs in both cameras' images
        by_id.setdefault(image["id"].split("_")[1], []).append(image)
    assert sum(1 for imgs in by_id.values() if len(imgs) == 2 and imgs[0]["mirror_configs"] == imgs[1]["mirror_configs"]) == 6
    R0, t0 = truth.poses["cam0"]
    R1, t1 = truth.poses["cam1"]
    baseline = -R1.T @ t1 + R0.T @ t0  # camera centres in the base frame
    assert 0.03 < np.linalg.norm(baseline) < 0.2


def test_rig_whose_third_camera_sees_only_two_shared_placements():
    dataset, truth = simulate_rig_tree(3, own=[27, 27, 0], shared=2, pixel_sigma=0.0, seed=5)
    check_rig(dataset, truth)
    third = [image for image in dataset["images"] if image["camera"] == "cam2"]
    assert len(third) == 2
    others = {tuple(image["mirror_configs"]) for image in dataset["images"] if image["camera"] != "cam2"}
    assert all(tuple(image["mirror_configs"]) in others for image in third)
    assert all(truth.mirror_cameras[p] == "cam0" for image in third for p in reflections_of(image))


def test_rig_mixed():
    dataset, truth = simulate_rig_mixed(3, own=[3, 1, 0], shared=1, direct=1, pixel_sigma=0.0, seed=6)
    seen = check_rig(dataset, truth)
    assert {p for p, cams in seen.items() if len(set(cams)) == 3} == {(1, 0), (2, 0)}
    assert any(len(reflections_of(image)) == 0 for image in dataset["images"])
    assert {len(reflections_of(image)) for image in dataset["images"]} == {0, 1, 2}
    candidates = []
    photo_cameras = {}
    for image in dataset["images"]:
        photo_cameras.setdefault(int(image["id"].split("_")[1]), set()).add(image["camera"])
    for i, cameras in photo_cameras.items():
        a, b = (1, i), (2, i)
        for name in cameras:
            views = [[a], [b], [a, b], [b, a]] + ([[]] if i < 1 else [])
            candidates.append(((name, f"{name}_{i:03d}"), [a, b], views))
    assert seen_check(dataset, truth, candidates, photos=True) == len(dataset["images"])


@pytest.mark.parametrize("call, words", [
    (lambda: simulate_rig_tree(2, own=[27, 5], shared=1), "camera cam1"),
    (lambda: simulate_rig_tree(2, own=[5, 5], shared=4), "no camera of the rig"),
    (lambda: simulate_rig_mixed(2, own=[3, 2], shared=0), "camera cam1"),
    (lambda: simulate_rig_tree(2, own=[1, 2, 3]), "3 counts given for 2 cameras"),
])
def test_unsolvable_rigs_are_refused_naming_the_camera(call, words):
    with pytest.raises(ValueError, match=words):
        call()


def test_noise_is_the_given_sigma_and_seeds_reproduce():
    noisy, _ = simulate_rig_tree(2, own=[27, 27], shared=6, pixel_sigma=1.0, seed=7)
    clean, _ = simulate_rig_tree(2, own=[27, 27], shared=6, pixel_sigma=0.0, seed=7)
    again, _ = simulate_rig_tree(2, own=[27, 27], shared=6, pixel_sigma=1.0, seed=7)
    other, _ = simulate_rig_tree(2, own=[27, 27], shared=6, pixel_sigma=1.0, seed=8)
    assert json.dumps(noisy) == json.dumps(again) and json.dumps(noisy) != json.dumps(other)
    errors = np.array([np.subtract(z, c["observations"][n]) for a, c in zip(noisy["images"], clean["images"])
                       for n, z in a["observations"].items()]).ravel()
    assert len(errors) > 300 and 0.85 < errors.std() < 1.15 and abs(errors.mean()) < 0.15
    assert noisy["pixel_sigma"] == 1.0 and clean["pixel_sigma"] == 1.0  # nominal when noise-free


# --- truth files and the command line -------------------------------------------------------------


def test_truth_round_trip_and_single_camera_compatibility():
    dataset, truth = simulate_mixed((4, 3), pixel_sigma=0.0, seed=9)
    data = json.loads(json.dumps(truth.to_dict()))
    assert "cameras" not in data and all("camera" not in m for m in data["mirrors"])
    old = ground_truth_from_dict(data)  # the existing reader
    for p, v in truth.mirror_vectors.items():
        np.testing.assert_array_equal(old.mirror_vectors[p], v)
    rig_data, rig = simulate_rig_tree(2, own=[27, 27], shared=3, pixel_sigma=0.0, seed=9)
    back = views_truth_from_dict(json.loads(json.dumps(rig.to_dict())))
    assert list(back.poses) == ["cam0", "cam1"] and back.mirror_cameras == rig.mirror_cameras
    for p in rig.mirror_vectors:
        np.testing.assert_array_equal(back.mirror_vectors[p], rig.mirror_vectors[p])
        q, n = plane_point_normal(rig, p, "cam0")  # ground_truth(): every vector in the first camera's frame
        np.testing.assert_allclose(back.ground_truth().mirror_vectors[p], float(n @ q) * n, atol=1e-12)
    with pytest.raises(ValueError, match="not in cameras"):
        views_truth_from_dict({**rig.to_dict(), "mirrors": [{"mirror": 1, "config": 0, "v": [0, 0, 1], "camera": "x"}]})


@pytest.mark.parametrize("options, images", [
    (["--kind", "kaleidoscope", "--mirrors", "3"], 10),
    (["--kind", "kaleidoscope", "--no-target", "--points", "2"], 5),
    (["--kind", "mixed", "--direct", "1", "--placements", "4,3"], 17),
    (["--cameras", "3", "--own", "27,27,0", "--shared", "2"], 27 * 2 + 2 * 3),
    (["--kind", "mixed", "--cameras", "2", "--own", "3,0", "--shared", "1"], 4 * 5),
])
def test_cli_writes_dataset_and_truth(tmp_path, capsys, options, images):
    out = tmp_path / "sim.json"
    assert main(["simulate", *options, "--seed", "2", "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    dataset = json.loads(out.read_text())
    truth = load_views_truth(tmp_path / "sim.truth.json")
    assert dataset["format"] == "mirror-fg/dataset@1" and len(dataset["images"]) == images
    if "--no-target" in options:
        assert dataset["fiducials"] == {} and dataset["scale"]["mirror"] == 1
    assert set(truth.mirror_vectors) == {p for image in dataset["images"] for p in reflections_of(image)}


@pytest.mark.parametrize("options, words", [
    (["--kind", "kaleidoscope", "--mirrors", "4"], "2 or 3 mirrors"),
    (["--no-target"], "--no-target does not go with --kind tree"),
    (["--kind", "kaleidoscope", "--cameras", "2"], "--cameras does not go with --kind kaleidoscope"),
    (["--shared", "2"], "--shared goes with --cameras"),
    (["--cameras", "2", "--own", "5,5", "--shared", "1"], "camera cam0"),
    (["--kind", "mixed", "--placements", "2"], "3 placements"),
    (["--kind", "mixed", "--placements", "1,x"], "--placements takes"),
    (["--cameras", "3", "--own", "1,2"], "--own takes"),
    (["--cameras", "1"], "--cameras"),
    (["--kind", "mixed", "--mirrors", "3"], "two hand-held mirrors"),
])
def test_cli_bad_options_exit_2_with_one_line(tmp_path, capsys, options, words):
    out = tmp_path / "x.json"
    try:
        status = main(["simulate", *options, "-o", str(out)])
    except SystemExit as stop:  # argparse's own checks (one line too: mirror_fg.cli.parser._Parser)
        status = stop.code
    assert status == 2
    err = capsys.readouterr().err
    assert words in err and err.count("\n") == 1, err
    assert not out.exists()


def test_second_order_views_are_ordered_pairs():
    """The second-order views of a three-mirror kaleidoscope are ordered pairs: (1, 2) and (2, 1) differ."""
    dataset, truth = simulate_kaleidoscope(3, pixel_sigma=0.0, seed=1)
    pairs = {tuple(l for l, _ in reflections_of(im)) for im in dataset["images"] if len(reflections_of(im)) == 2}
    assert any((j, i) in pairs for i, j in pairs)
    assert pairs <= set(itertools.permutations(range(1, 4), 2))


# --- the simulated data determine their unknowns ----------------------------------------------------


def pixel_jacobian(dataset, truth, step=1e-6):
    """Central-difference Jacobian of every noise-free pixel prediction (own projection code) with respect
    to every unknown: each camera's pose (rotation about its axes, translation; none without fiducials,
    the base frame is then the camera's), each mirror vector in its own frame, each reconstruction point."""
    from dataclasses import replace

    from mirror_fg.core.geometry import so3_exp

    blocks = [("pose", name, 6) for name in truth.poses] if dataset["fiducials"] else []
    blocks += [("mirror", p, 3) for p in sorted(truth.mirror_vectors)] + [("point", n, 3) for n in sorted(truth.points)]
    starts = np.concatenate([[0], np.cumsum([size for *_, size in blocks])]).astype(int)

    def model(delta):
        poses, vectors, points = dict(truth.poses), dict(truth.mirror_vectors), dict(truth.points)
        for (kind, key, size), start in zip(blocks, starts):
            d = delta[start: start + size]
            if kind == "pose":
                R, t = poses[key]
                poses[key] = (so3_exp(d[:3]) @ R, t + d[3:])
            elif kind == "mirror":
                vectors[key] = vectors[key] + d
            else:
                points[key] = points[key] + d
        return replace(truth, poses=poses, mirror_vectors=vectors, points=points)

    def predict(m):
        points = base_points(dataset, m)
        rows = []
        for image in dataset["images"]:
            name, camera = image_camera(dataset, image)
            R, t = m.poses[name]
            path = [plane_point_normal(m, p, name) for p in reflections_of(image)]
            for point in image["observations"]:
                x = R @ points[point] + t
                for q, n in path:
                    x = mirror_point(x, q, n)
                rows.append((camera_matrix(camera) @ x)[:2] / x[2])
        return np.concatenate(rows)

    columns = []
    for i in range(int(starts[-1])):
        e = np.zeros(int(starts[-1]))
        e[i] = step
        columns.append((predict(model(e)) - predict(model(-e))) / (2.0 * step))
    return np.column_stack(columns)


@pytest.mark.parametrize("make, gauge", [
    (lambda: simulate_kaleidoscope(2, pixel_sigma=0.0, seed=1), 0),
    (lambda: simulate_kaleidoscope(3, target=False, pixel_sigma=0.0, seed=1), 1),  # the scale
    (lambda: simulate_kaleidoscope(2, target=False, pixel_sigma=0.0, seed=2), 1),
    (lambda: simulate_mixed((4, 2), pixel_sigma=0.0, seed=3), 0),
    (lambda: simulate_rig_tree(3, own=[9, 9, 0], shared=2, pixel_sigma=0.0, seed=5), 0),
    (lambda: simulate_rig_mixed(3, own=[3, 1, 0], shared=1, pixel_sigma=0.0, seed=6), 0),
])
def test_simulated_data_determine_every_unknown(make, gauge):
    """The pixel Jacobian has full rank but for the gauge (the scale without a known target): every
    camera, placement and point is determined (locally), so an MLE of these data is well posed."""
    dataset, truth = make()
    J = pixel_jacobian(dataset, truth)
    singular = np.linalg.svd(J, compute_uv=False)
    rank = int(np.sum(singular > 1e-7 * singular[0]))
    assert rank == J.shape[1] - gauge, (rank, J.shape, singular[-3:] / singular[0])
    if gauge:
        assert singular[-1] < 1e-9 * singular[0]  # the unseen scale, nothing else
    assert singular[-1 - gauge] > 1e-5 * singular[0]
