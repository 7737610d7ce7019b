"""The propagation's start (solver/start/propagation.py) is a result: on noise-free scenes every plane and
point it finds equals the truth (to 1e-6), whatever rule found it.

The scenes are those of views_scenes.py (independent of mirror_fg); a kaleidoscope here adds points
seen only through two mirrors in both orders, so they are found only by carrying each ray back
through the view's reflections in reverse order (rule 4)."""
import numpy as np
import pytest

import views_scenes as scenes
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.solver.start.propagation import propagate
from mirror_fg.solver.model.views import ViewProblem
from mirror_fg.solver.batch.views_solve import tree_start_for
from mirror_fg.solver.options import SolveOptions

TOLERANCE = 1e-6  # metres, and for unit normals


def start(data: dict):
    dataset = dataset_from_dict(data)
    problem = ViewProblem(dataset)
    return propagate(problem.views, dataset.fiducials, problem.cameras, problem.fixed, tree_start_for(dataset, SolveOptions()),
                     dataset.scale)


def kaleidoscope_points_seen_twice_reflected() -> tuple[dict, scenes.Truth, dict]:
    """The known board and the two fixed mirrors of ``kaleidoscope_two_mirrors``, and four points 2-6 cm
    in front of the board seen only in the views through mirror 1 then 2 and through 2 then 1."""
    camera, (R, t), fiducials = scenes._side_mirror_scene()
    planes = {(1, 0): scenes._plane_cam_to_base(R, t, *scenes.LEFT), (2, 0): scenes._plane_cam_to_base(R, t, *scenes.BELOW)}
    points = {f"P{k}": np.array([x, y, -z]) for k, (x, y, z) in
              enumerate([(0.02, 0.01, 0.03), (-0.04, 0.02, 0.05), (0.05, -0.03, 0.02), (-0.01, -0.04, 0.06)])}
    views = [("direct", "camera", [], True), ("m1", "camera", [[1, 0]], True), ("m2", "camera", [[2, 0]], True),
             ("m1m2", "camera", [[1, 0], [2, 0]], True), ("m2m1", "camera", [[2, 0], [1, 0]], True)]
    data, truth = scenes.build({"camera": camera}, {"camera": (R, t)}, fiducials, points, planes, views, 0.5, None, 2,
                               single_camera=True, min_points=20)
    for image in data["images"]:
        seen = [name for name in points if name in image["observations"]]
        if len(image["reflections"]) < 2:
            for name in seen:
                del image["observations"][name]
        else:
            assert seen == list(points), (image["id"], seen)  # every point in both double views
    return data, truth, points


def test_points_seen_only_through_two_mirrors_are_triangulated_exactly():
    data, truth, points = kaleidoscope_points_seen_twice_reflected()
    known = start(data)
    for name, true in points.items():
        assert np.linalg.norm(known.points[name] - true) < TOLERANCE, (name, known.points[name], true)


@pytest.mark.parametrize("scene", ["kaleidoscope_two_mirrors", "mixed_two_handheld", "mixed_one_mirror_gives_pose",
                                   "rig_two_cameras", "rig_three_cameras"])
def test_every_plane_of_the_start_is_the_truth_on_noise_free_data(scene):
    data, truth = scenes.CASES[scene](seed=None)
    known = start(data)
    assert set(known.planes) == set(truth.planes)
    for placement, (n, d) in known.planes.items():
        n_true, d_true = truth.planes[placement]
        if n @ n_true < 0:  # (n, d) and (-n, -d) are one plane
            n_true, d_true = -n_true, -d_true
        assert np.linalg.norm(n - n_true) < TOLERANCE and abs(d - d_true) < TOLERANCE, (placement, n, d, n_true, d_true)
    for camera, (R, t) in known.poses.items():
        R_true, t_true = truth.T_cam_base[camera]
        assert np.abs(R - R_true).max() < TOLERANCE and np.linalg.norm(t - t_true) < TOLERANCE, camera
