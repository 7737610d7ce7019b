"""Consensus initial estimate: wrong corner orders and gross corners are left out, each named
with its reason, and the capture calibrates to the answer of the capture without them."""
import numpy as np
import pytest

from conftest import pose_difference
from mirror_fg import DatasetError, calibrate, load_dataset
from mirror_fg.data import Dataset, Image
from mirror_fg.solver.result.calibration import Calibration
from mirror_fg.solver.screen.consensus import FINAL_SIGMAS, PNP_POINT_SIGMAS, screen, without
from mirror_fg.simulate.tree import GroundTruth, default_camera, measure, simulate_base_case

# --------------------------------------------------------------------------------------------------
# Chessboard labellings gone wrong (what a detector returns at steep mirror angles)


def _relabel(observations, cols, rows, moved):
    """Corner (col, row)'s observation labelled as corner ``moved(col, row)`` (names C{row*cols+col:02d})."""
    relabelled = {}
    for row in range(rows):
        for col in range(cols):
            c, r = moved(col, row)
            relabelled[f"C{r * cols + c:02d}"] = observations[f"C{row * cols + col:02d}"]
    return relabelled


def reversed_rows(observations, cols, rows, rng):
    return _relabel(observations, cols, rows, lambda c, r: (c, rows - 1 - r))


def reversed_columns(observations, cols, rows, rng):
    return _relabel(observations, cols, rows, lambda c, r: (cols - 1 - c, r))


def half_turn(observations, cols, rows, rng):
    return _relabel(observations, cols, rows, lambda c, r: (cols - 1 - c, rows - 1 - r))


def shuffled_row(observations, cols, rows, rng):
    order = rng.permutation(cols)
    while np.sum(order != np.arange(cols)) < cols - 1:  # (nearly) every corner of the row moved
        order = rng.permutation(cols)
    return _relabel(observations, cols, rows, lambda c, r: (int(order[c]), r) if r == rows // 2 else (c, r))


GROSS_CORNERS = 3


def gross_corners(observations, cols, rows, rng):
    """Three corners moved by 15-40 px in x and y (a detection that snapped to something else)."""
    moved = dict(observations)
    for name in rng.choice(sorted(moved), size=GROSS_CORNERS, replace=False):
        moved[name] = moved[name] + rng.choice([-1.0, 1.0], size=2) * rng.uniform(15.0, 40.0, size=2)
    return moved


WRONG_ORDERS = {"reversed rows": reversed_rows, "reversed columns": reversed_columns, "half turn": half_turn,
                "shuffled row": shuffled_row}


def _corrupted(dataset: Dataset, corruptions: dict[int, object], cols: int, rows: int, seed: int = 0) -> Dataset:
    rng = np.random.default_rng(seed)
    images = [
        Image(im.id, im.mirror_configs, corruptions[i](dict(im.observations), cols, rows, rng)) if i in corruptions
        else Image(im.id, im.mirror_configs, dict(im.observations))
        for i, im in enumerate(dataset.images)
    ]
    return Dataset(dataset.num_mirrors, dataset.camera, dataset.pixel_sigma, dataset.fiducials, images,
                   source="<corrupted>")


def _moved_corners(clean: Dataset, bad: Dataset) -> set[tuple[str, str]]:
    return {(b.id, name) for a, b in zip(clean.images, bad.images) for name in a.observations
            if not np.array_equal(a.observations[name], b.observations[name])}


def _reference(clean: Dataset, bad_images: set[str], bad_points: set[tuple[str, str]]) -> Calibration:
    """The capture without its bad images and corners, calibrated as it is (nothing for the consensus to do)."""
    images = [Image(im.id, im.mirror_configs, {n: z for n, z in im.observations.items() if (im.id, n) not in bad_points})
              for im in clean.images if im.id not in bad_images]
    reference = calibrate(Dataset(clean.num_mirrors, clean.camera, clean.pixel_sigma, clean.fiducials, images,
                                  source="<reference>"))
    assert reference.excluded == []
    return reference


def _assert_same_answer(calibration: Calibration, reference: Calibration, within_sigmas: float = 0.1) -> float:
    difference = pose_difference(reference.R_cam_base, reference.t_cam_base, calibration.R_cam_base, calibration.t_cam_base)
    off = float(np.max(np.abs(difference / np.sqrt(np.diag(reference.covariance)))))
    assert off < within_sigmas, f"{off:.3g} sigma from the capture without the bad images"
    assert calibration.converged and calibration.cost_plausible
    return off


def _excluded_images(calibration: Calibration) -> set[str]:
    return {e.image for e in calibration.excluded if e.point is None}


def _excluded_points(calibration: Calibration) -> set[tuple[str, str]]:
    return {(e.image, e.point) for e in calibration.excluded if e.point is not None}


# --------------------------------------------------------------------------------------------------
# The real photographs (Takahashi et al.: one mirror, five placements, 10 x 7 corners)

TAKAHASHI_COLS, TAKAHASHI_ROWS = 10, 7


@pytest.fixture
def takahashi(takahashi_dir) -> Dataset:
    return load_dataset(takahashi_dir / "dataset.json")


def test_real_photographs_clean_nothing_left_out(takahashi):
    screened, excluded, _ = screen(takahashi)
    assert excluded == [] and screened is takahashi


@pytest.mark.parametrize("kind", sorted(WRONG_ORDERS))
@pytest.mark.parametrize("image", [1, 3])
def test_real_photographs_wrong_corner_order_left_out(takahashi, kind, image):
    bad = _corrupted(takahashi, {image: WRONG_ORDERS[kind]}, TAKAHASHI_COLS, TAKAHASHI_ROWS, seed=image)
    calibration = calibrate(bad)
    bad_id = takahashi.images[image].id
    assert _excluded_images(calibration) == {bad_id} and not _excluded_points(calibration)
    [exclusion] = calibration.excluded
    expected = {"reversed rows": "board seen from behind", "reversed columns": "board seen from behind",
                "half turn": "inconsistent with the other placements of mirror 1", "shuffled row": "PnP reprojection"}
    assert exclusion.reason.startswith(expected[kind]), exclusion.reason
    _assert_same_answer(calibration, _reference(takahashi, {bad_id}, set()))


def test_real_photographs_two_bad_images_and_gross_corners(takahashi):
    """Two of five images with wrong orders (the most a minority can be) and gross corners in a third."""
    bad = _corrupted(takahashi, {0: half_turn, 2: gross_corners, 4: shuffled_row}, TAKAHASHI_COLS, TAKAHASHI_ROWS)
    calibration = calibrate(bad)
    bad_ids = {takahashi.images[0].id, takahashi.images[4].id}
    moved = _moved_corners(takahashi, bad) - {(i, n) for i, n in _moved_corners(takahashi, bad) if i in bad_ids}
    assert len(moved) == GROSS_CORNERS
    assert _excluded_images(calibration) == bad_ids
    assert _excluded_points(calibration) == moved
    assert all(e.sigmas is not None and e.sigmas > PNP_POINT_SIGMAS for e in calibration.excluded if e.point)
    _assert_same_answer(calibration, _reference(takahashi, bad_ids, moved))


def test_real_photographs_majority_bad_refused_naming_what_was_left_out(takahashi):
    bad = _corrupted(takahashi, {0: shuffled_row, 1: shuffled_row, 2: shuffled_row}, TAKAHASHI_COLS, TAKAHASHI_ROWS)
    with pytest.raises(DatasetError, match=r"mirror 1 needs at least three placements, you gave two.*after leaving out image 'input1': PnP"):
        calibrate(bad)


# --------------------------------------------------------------------------------------------------
# Simulated: a 7 x 5-corner board through one or two mirrors, 28 images, 6 of them bad

BOARD_COLS, BOARD_ROWS, BOARD_SQUARE = 7, 5, 0.03


def board_scene(num_mirrors: int, num_images: int = 28, seed: int = 0, pixel_sigma: float = 0.5,
                bump: tuple[int, np.ndarray, np.ndarray] | None = None) -> tuple[Dataset, GroundTruth]:
    """``simulate_base_case``'s mirrors and ``T_cam_base`` seen on a chessboard's inner corners (base frame =
    board frame). ``bump = (k, w, dt)``: images k.. see ``T_cam_base`` moved to ``(Exp(w) R, t + dt)``."""
    from mirror_fg.core.geometry import so3_exp

    layout, truth = simulate_base_case(num_images=num_images, num_mirrors=num_mirrors, num_fiducials=4,
                                       pixel_sigma=pixel_sigma, seed=seed, tilt_deg=25.0)
    board = {f"C{r * BOARD_COLS + c:02d}": np.array([c * BOARD_SQUARE, r * BOARD_SQUARE, 0.0])
             for r in range(BOARD_ROWS) for c in range(BOARD_COLS)}
    rng = np.random.default_rng(seed + 100)
    camera = default_camera()
    images = []
    for i, im in enumerate(layout.images):
        seen = truth
        if bump is not None and i >= bump[0]:
            seen = GroundTruth(so3_exp(bump[1]) @ truth.R_cam_base, truth.t_cam_base + bump[2], truth.mirror_vectors)
        images.append(Image(im.id, im.mirror_configs, measure(seen, camera, board, im.mirror_configs, pixel_sigma, rng)))
    return Dataset(num_mirrors, camera, pixel_sigma, board, images, source="<board scene>"), truth


@pytest.mark.parametrize("num_mirrors", [1, 2])
def test_simulated_six_of_28_bad(num_mirrors):
    clean, truth = board_scene(num_mirrors)
    assert calibrate(clean).excluded == []
    picks = np.random.default_rng(5).choice(len(clean.images), size=6, replace=False)
    kinds = [reversed_rows, reversed_columns, half_turn, half_turn, shuffled_row, gross_corners]
    bad = _corrupted(clean, dict(zip(picks.tolist(), kinds)), BOARD_COLS, BOARD_ROWS)
    calibration = calibrate(bad)
    bad_ids = {clean.images[i].id for i, kind in zip(picks, kinds) if kind is not gross_corners}
    gross_id = clean.images[picks[-1]].id
    moved = {(i, n) for i, n in _moved_corners(clean, bad) if i == gross_id}
    assert _excluded_images(calibration) == bad_ids
    assert _excluded_points(calibration) == moved
    _assert_same_answer(calibration, _reference(clean, bad_ids, moved))
    error = pose_difference(truth.R_cam_base, truth.t_cam_base, calibration.R_cam_base, calibration.t_cam_base)
    assert np.all(np.abs(error) < 3.0 * np.sqrt(np.diag(calibration.covariance)))


def test_final_check_leaves_out_a_gross_measurement_of_a_reconstruction_point():
    """Three fiducials (no PnP check): a reconstruction point's gross measurement is found after LM."""
    clean, _ = simulate_base_case(num_images=60, num_points=5, pixel_sigma=0.5, seed=4)
    image = clean.images[17]
    bad_images = list(clean.images)
    bad_images[17] = Image(image.id, image.mirror_configs,
                           {**image.observations, "P2": image.observations["P2"] + np.array([25.0, -18.0])})
    bad = Dataset(clean.num_mirrors, clean.camera, clean.pixel_sigma, clean.fiducials, bad_images, source="<bad>")
    calibration = calibrate(bad)
    [exclusion] = calibration.excluded
    assert (exclusion.image, exclusion.point) == (image.id, "P2") and exclusion.sigmas > FINAL_SIGMAS
    _assert_same_answer(calibration, _reference(clean, set(), {(image.id, "P2")}))
    assert without(bad, calibration.excluded).images[17].observations.keys() == image.observations.keys() - {"P2"}


# --------------------------------------------------------------------------------------------------
# --incremental: an image refused as inconsistent does not poison the estimate


def test_incremental_refuses_the_bad_images_and_lands_on_the_batch_answer():
    from mirror_fg.solver.incremental.calibrator import calibrate_incremental

    clean, _ = board_scene(1)
    picks = np.random.default_rng(5).choice(len(clean.images), size=6, replace=False)
    kinds = [reversed_rows, reversed_columns, half_turn, half_turn, shuffled_row, gross_corners]
    bad = _corrupted(clean, dict(zip(picks.tolist(), kinds)), BOARD_COLS, BOARD_ROWS)
    calibration = calibrate_incremental(bad)
    bad_ids = {clean.images[i].id for i, kind in zip(picks, kinds) if kind is not gross_corners}
    gross_id = clean.images[picks[-1]].id
    moved = {(i, n) for i, n in _moved_corners(clean, bad) if i == gross_id}
    assert _excluded_images(calibration) == bad_ids
    assert _excluded_points(calibration) == moved
    _assert_same_answer(calibration, _reference(clean, bad_ids, moved))


def test_detect_says_what_calibrate_will_leave_out(tmp_path, capsys):
    """``mirror-fg detect`` keeps every detection but names the images that disagree with the rest."""
    import yaml

    from mirror_fg.cli import main

    clean, _ = board_scene(1, num_images=12)
    bad = _corrupted(clean, {3: reversed_rows}, BOARD_COLS, BOARD_ROWS)
    c = bad.camera
    capture = {
        "format": "mirror-fg/capture@1", "num_mirrors": 1,
        "camera": {"model": "pinhole", "width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx,
                   "cy": c.cy, "dist": list(c.dist)},
        "pixel_sigma": bad.pixel_sigma,
        "target": {"kind": "points", "fiducials": {n: p.tolist() for n, p in bad.fiducials.items()}},
        "images": [{"id": im.id, "mirror_configs": list(im.mirror_configs),
                    "observations": {n: np.asarray(xy).tolist() for n, xy in im.observations.items()}} for im in bad.images],
    }
    path = tmp_path / "capture.yaml"
    path.write_text(yaml.safe_dump(capture))
    assert main(["detect", str(path), "-o", str(tmp_path / "data.json")]) == 0
    printed = capsys.readouterr().out
    assert "check: calibrate will leave out 1 image(s)" in printed
    assert f"  image '{bad.images[3].id}': " in printed
    assert "wrote" in printed and "(12 images)" in printed  # the dataset keeps every detection
