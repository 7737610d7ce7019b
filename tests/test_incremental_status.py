"""What an incremental calibration waits for: ``IncrementalCalibrator.status`` and its repr, the
CLI's lines before start-up, and no ``nan`` / ``0 measurements`` in the estimates between images."""
import json
from collections import defaultdict

import pytest

from mirror_fg.cli import main
from mirror_fg.io.dataset import dataset_to_dict
from mirror_fg.data import Image
from mirror_fg.solver.incremental.calibrator import IncrementalCalibrator
from mirror_fg.solver.start.placement_tree import tree_shortfall
from mirror_fg.simulate.tree import simulate_base_case


def _images(configs: list[tuple[int, ...]]) -> list[Image]:
    return [Image(f"i{k}", c, {}) for k, c in enumerate(configs)]


def test_tree_shortfall_names_what_is_missing() -> None:
    full_node = [(0, 0), (0, 1), (0, 2), (1, 3), (1, 4), (1, 5)]
    assert tree_shortfall(_images(full_node + [(2, 6), (2, 7), (2, 8)]), 2) is None
    assert tree_shortfall(_images(full_node + [(2, 6), (2, 7)]), 2) == (
        "mirror 1 has 2 complete placement(s), needs 3; mirror 2 has 2 placement(s) under (1, 2), needs 3")
    assert tree_shortfall(_images(full_node), 2) == "mirror 1 has 2 complete placement(s), needs 3"
    assert tree_shortfall(_images([(0,), (1,), (1,)]), 1) == "mirror 1 has 2 placement(s), needs 3"
    # Three mirrors: along the placement nearest to complete, down to the last mirror.
    three = [(a, b, c) for a in range(3) for b in range(3 * a, 3 * a + 3) for c in range(3 * b, 3 * b + 3)]
    assert tree_shortfall(_images(three[:-1]), 3) == (
        "mirror 1 has 2 complete placement(s), needs 3; mirror 2 has 2 complete placement(s) under (1, 2), "
        "needs 3; mirror 3 has 2 placement(s) under (2, 8), needs 3")


def _complete_mirror1(images: list[Image]) -> int:
    """Placements of mirror 1 with >= 3 placements of mirror 2 seen under them (counted here, apart)."""
    children = defaultdict(set)
    for image in images:
        children[image.mirror_configs[0]].add(image.mirror_configs[1])
    return sum(1 for c in children.values() if len(c) >= 3)


def test_status_says_why_add_image_returns_none() -> None:
    dataset, _ = simulate_base_case(num_images=60, pixel_sigma=0.5, seed=1)
    calibrator = IncrementalCalibrator(dataset)
    assert calibrator.status == "waiting: no image yet"
    for index, image in enumerate(dataset.images, start=1):
        estimate = calibrator.add_image(image)
        if estimate is not None:
            break
        complete = _complete_mirror1(dataset.images[:index])
        assert calibrator.status.startswith(f"waiting: mirror 1 has {complete} complete placement(s), needs 3")
        assert calibrator.status in repr(calibrator) and f"{index} image(s) given" in repr(calibrator)
    else:
        pytest.fail("never started")
    assert _complete_mirror1(dataset.images[:index]) == 3  # it starts as soon as the tree is complete
    assert calibrator.status.startswith(("settled", "unsettled")) and "image(s) in the graph" in calibrator.status
    # The estimate between images: no residuals computed, said so (not "nan" and "0 measurements").
    text = repr(estimate)
    assert "nan" not in text and "0 measurements" not in text and "not computed" in text


def test_cli_incremental_prints_why_it_waits(tmp_path, capsys) -> None:
    dataset, _ = simulate_base_case(num_images=60, pixel_sigma=0.5, seed=1)
    path = tmp_path / "d.json"
    path.write_text(json.dumps(dataset_to_dict(dataset)))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "r.json"), "--incremental", "--every", "10",
                 "--no-ros"]) == 0
    printed = capsys.readouterr().out
    complete = _complete_mirror1(dataset.images[:10])
    assert f"[   10/60] waiting: mirror 1 has {complete} complete placement(s), needs 3" in printed
