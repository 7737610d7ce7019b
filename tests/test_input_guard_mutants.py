"""The input guards that catch a wrong unit or a mislabelled image, on hand-made inputs whose right answer
is known: a scene typed in centimetres or millimetres (docs/formats.md, lengths in metres), and two rig
images of one camera through one placement that see the same points (docs/formats.md "Several cameras")."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mirror_fg.core.errors import DatasetError


# -- lengths in the wrong unit ------------------------------------------------------------------------------


def _solved(mirror_m: float, point_m: float) -> SimpleNamespace:
    """A solved calibration's estimates as check_within_reach reads them: one mirror ``mirror_m`` and one
    point ``point_m`` from the camera (the camera 1 m from the base along z)."""
    return SimpleNamespace(mirror_vectors={(1, 0): np.array([0.0, 0.6, 0.8]) * mirror_m}, R_cam_base=np.eye(3),
                           t_cam_base=np.array([0.0, 0.0, 1.0]), points={"p": np.array([0.0, 0.0, point_m - 1.0])})


@pytest.mark.parametrize("unit", [100.0, 1000.0], ids=["centimetres", "millimetres"])
@pytest.mark.parametrize("far", ["mirror", "point"])
def test_a_scene_in_the_wrong_unit_is_refused(unit, far):
    """A desk-sized scene (mirror 0.4 m, point 1.5 m away) typed in cm or mm is 100 or 1000 times as large."""
    from mirror_fg.solver.result.guard import check_within_reach

    scene = _solved(0.4 * (unit if far == "mirror" else 1.0), 1.5 * (unit if far == "point" else 1.0))
    with pytest.raises(DatasetError, match="metres, not millimetres or centimetres"):
        check_within_reach(scene, "data.json")


def test_a_scene_in_metres_is_within_reach():
    from mirror_fg.solver.result.guard import check_within_reach

    check_within_reach(_solved(0.4, 1.5), "data.json")
    check_within_reach(_solved(3.0, 8.0), "data.json")  # a room


@pytest.mark.parametrize("distance, accepted", [(0.219, True), (4.0, True), (21.9, False), (219.0, False)])
def test_a_scale_distance_in_centimetres_or_millimetres_is_refused_at_load(distance, accepted):
    """A 219 mm mirror distance typed as 219 (or 21.9 cm as 21.9) is no length a camera sees a mirror at."""
    from mirror_fg.io.dataset_fields import scale_from_dict

    value = {"mirror": 1, "config": 0, "distance": distance}
    if accepted:
        assert scale_from_dict(value, "data.json") == (distance, (1, 0), None)
    else:
        with pytest.raises(DatasetError, match="distance must be a length in metres"):
            scale_from_dict(value, "data.json")


# -- rig images naming the wrong camera ---------------------------------------------------------------------


def _image(name: str, camera: str, reflections: list, pixels: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(id=name, camera=camera, reflections=reflections,
                           observations={f"p{k}": pixels[k] for k in range(len(pixels))})


def _rig(images: list) -> SimpleNamespace:
    return SimpleNamespace(source="data.json", cameras={"left": None, "right": None}, images=images,
                           pixel_sigma=0.5, point_sigma=None)


@pytest.mark.parametrize("offset_px, refused", [(0.0, False), (1.0, False), (100.0, True)])
def test_two_images_of_one_camera_and_placement_agree_within_the_noise(offset_px, refused):
    """The same points through the same mirror plane land on the same pixels up to the noise (sigma 0.5 px:
    the difference has sigma 0.7 px per coordinate); a 100 px shift is another camera's image."""
    from mirror_fg.solver.screen.camera_labels import check_camera_labels

    rng = np.random.default_rng(3)
    pixels = rng.uniform(100.0, 500.0, (20, 2))
    second = pixels + rng.normal(0.0, 0.5 * np.sqrt(2.0), pixels.shape) + [offset_px, 0.0]
    dataset = _rig([_image("a.png", "left", [(1, 0)], pixels), _image("b.png", "left", [(1, 0)], second),
                    _image("c.png", "right", [(1, 1)], pixels + 40.0)])
    if refused:
        with pytest.raises(DatasetError, match="'a.png' and 'b.png' look mislabelled"):
            check_camera_labels(dataset)
    else:
        check_camera_labels(dataset)


def test_a_lone_image_through_another_camera_s_placement_is_suspected():
    """Camera right sees placement (1, 0) in two images; left's only image through it was likely right's."""
    from mirror_fg.solver.screen.camera_labels import lone_image_hint

    pixels = np.zeros((4, 2))
    dataset = _rig([_image("r1.png", "right", [(1, 0)], pixels), _image("r2.png", "right", [(1, 0)], pixels),
                    _image("l1.png", "left", [(1, 0)], pixels), _image("l2.png", "left", [(2, 0)], pixels),
                    _image("l3.png", "left", [(2, 0)], pixels)])
    hint = lone_image_hint(dataset)
    assert "image 'l1.png' is the only image of camera 'left' through mirror 1 placement 0" in hint, hint
    assert "r1.png" not in hint and "l2.png" not in hint
    assert lone_image_hint(_rig(dataset.images[:2] + dataset.images[3:])) == ""  # nobody alone
