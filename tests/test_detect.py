"""Detectors and detect_capture (mirror_fg.vision.detect) on the real Takahashi photographs and synthetic images."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from conftest import TAKAHASHI
from mirror_fg.io.capture import load_capture
from mirror_fg.core.errors import DatasetError
from mirror_fg.io.dataset import dataset_from_dict, dataset_to_dict
from mirror_fg.io.target import ChessboardTarget, TagTarget, tag_dictionary
from mirror_fg.vision.detectors import FOUND, NOT_FOUND, REFUSED
from mirror_fg.vision.detect import detect_capture, format_reports
from mirror_fg.vision.detectors import _first_square_dark, detect_chessboard, detect_tags

DATA = Path(__file__).parent / "data" / "capture"
needs_takahashi = pytest.mark.skipif(not TAKAHASHI.is_dir(), reason="examples/takahashi2012 missing")

SQUARE_PX = 24
MARGIN_PX = 24


# --------------------------------------------------------------------------------------------------
# Synthetic images with known corners
# --------------------------------------------------------------------------------------------------


def board_image(cols: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Front view of a board whose top-left square is black; (rows*cols, 2) inner corners (C00 first)."""
    h, w = (rows + 1) * SQUARE_PX + 2 * MARGIN_PX, (cols + 1) * SQUARE_PX + 2 * MARGIN_PX
    img = np.full((h, w), 230, np.uint8)
    for r in range(rows + 1):
        for c in range(cols + 1):
            if (r + c) % 2 == 0:
                y, x = MARGIN_PX + r * SQUARE_PX, MARGIN_PX + c * SQUARE_PX
                img[y : y + SQUARE_PX, x : x + SQUARE_PX] = 25
    # pixel k covers [k - 0.5, k + 0.5]: the edge between squares is at MARGIN + n*SQUARE - 0.5
    corners = np.array([[MARGIN_PX + (c + 1) * SQUARE_PX - 0.5, MARGIN_PX + (r + 1) * SQUARE_PX - 0.5]
                        for r in range(rows) for c in range(cols)])
    return img, corners


def warp(img: np.ndarray, points: np.ndarray, H: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    # anti-aliased: render at 4x and shrink (pixel centres: x_small = (x_big + 0.5) / 4 - 0.5)
    S = np.diag([4.0, 4.0, 1.0])
    big = cv2.warpPerspective(img, S @ H, (size[0] * 4, size[1] * 4), flags=cv2.INTER_LINEAR, borderValue=128)
    small = cv2.resize(big, size, interpolation=cv2.INTER_AREA)
    p = cv2.perspectiveTransform(points.reshape(1, -1, 2), S @ H)[0]
    return small, (p + 0.5) / 4 - 0.5


def perspective(w: int, h: int, src_w: int, src_h: int) -> np.ndarray:
    src = np.float32([[0, 0], [src_w, 0], [src_w, src_h], [0, src_h]])
    dst = np.float32([[0.18 * w, 0.15 * h], [0.8 * w, 0.22 * h], [0.75 * w, 0.85 * h], [0.22 * w, 0.78 * h]])
    return cv2.getPerspectiveTransform(src, dst)


def tag_canvas(ids: list[int], dictionary: str = "tag36h11", side: int = 80) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """White canvas with tags in a row; their corners in cv2.aruco order (pixel-edge convention)."""
    d = cv2.aruco.getPredefinedDictionary(tag_dictionary(dictionary)[1])
    img = np.full((side * 2, side * (len(ids) * 2 + 1)), 255, np.uint8)
    corners = {}
    for n, tag_id in enumerate(ids):
        x0, y0 = side * (2 * n + 1), side // 2
        img[y0 : y0 + side, x0 : x0 + side] = cv2.aruco.generateImageMarker(d, tag_id, side, borderBits=1)
        box = np.array([[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side]], float) - 0.5
        for k in range(4):
            corners[f"T{tag_id}_{k}#{n}"] = box[k]
    return img, corners


# --------------------------------------------------------------------------------------------------
# Takahashi photographs
# --------------------------------------------------------------------------------------------------


@needs_takahashi
def test_takahashi_all_corners_in_published_order():
    cap = load_capture(DATA / "takahashi.yaml")
    ds, reports = detect_capture(cap, progress=False)
    d = dataset_to_dict(ds)
    assert [r.status for r in reports] == [FOUND] * 5
    assert [im["id"] for im in d["images"]] == [f"input{n}" for n in range(1, 6)]
    assert [im["mirror_configs"] for im in d["images"]] == [[0], [1], [2], [3], [4]]
    for im in d["images"]:
        published = np.loadtxt(TAKAHASHI / f"{im['id']}.txt")
        assert len(im["observations"]) == 70
        found = np.array([im["observations"][f"C{i:02d}"] for i in range(70)])
        error = np.linalg.norm(found - published, axis=1)
        assert np.median(error) < 0.2 and error.max() < 0.5, (im["id"], np.median(error), error.max())
    ds = dataset_from_dict(d, source="takahashi")
    assert ds.num_mirrors == 1 and len(ds.fiducials) == 70 and ds.camera.width == 1600


# --------------------------------------------------------------------------------------------------
# Chessboard order
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("view", ["direct", "half turn", "quarter turn", "through one mirror"])
def test_chessboard_order_is_physical(view):
    """C00 is the inner corner of the black corner square, the rows run right, in every view."""
    cols, rows = 6, 5
    board, corners = board_image(cols, rows)
    target = ChessboardTarget(cols, rows, 0.02)
    size = (360, 300)
    H = perspective(*size, board.shape[1], board.shape[0])
    img, truth = warp(board, corners, H, size)
    mirrored = False
    if view == "half turn":
        img = cv2.rotate(img, cv2.ROTATE_180)
        truth = np.array([size[0] - 1, size[1] - 1]) - truth
    elif view == "quarter turn":
        img = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)  # (x, y) -> (h - 1 - y, x)
        truth = np.stack([size[1] - 1 - truth[:, 1], truth[:, 0]], axis=1)
    elif view == "through one mirror":
        img = cv2.flip(img, 1)
        truth = np.stack([size[0] - 1 - truth[:, 0], truth[:, 1]], axis=1)
        mirrored = True
    det = detect_chessboard(img, target, mirrored)
    assert det.status == FOUND, det.reason
    found = np.array([det.points[f"C{i:02d}"] for i in range(cols * rows)])
    assert np.max(np.linalg.norm(found - truth, axis=1)) < 0.3


def test_chessboard_not_found_and_colour_refusal():
    target = ChessboardTarget(6, 5, 0.02)
    det = detect_chessboard(np.full((200, 200), 128, np.uint8), target, False)
    assert det.status == NOT_FOUND and "not found" in det.reason
    grid = np.stack(np.meshgrid(np.arange(6) * 20.0 + 30, np.arange(5) * 20.0 + 30), axis=-1)
    dark, why = _first_square_dark(np.full((200, 200), 128, np.uint8), grid)
    assert dark is None and "differ by only" in why
    checker = ((np.indices((200, 200)) // 20).sum(axis=0) % 2 * 200 + 20).astype(np.uint8)
    grid = grid - 10 + 0.5  # corners of the 20-px checker at 19.5, 39.5, ...
    assert _first_square_dark(checker, grid)[0] is True  # square between (20,20) and (40,40) is dark
    scrambled = checker.copy()
    scrambled[40:60, 20:100] = 220  # a row of squares all light
    scrambled[60:80, 20:100] = 20
    dark, why = _first_square_dark(scrambled, grid)
    assert dark is None and "alternate" in why


# --------------------------------------------------------------------------------------------------
# Tags
# --------------------------------------------------------------------------------------------------


def tag_target(ids, refine="subpix", gamma="linear") -> TagTarget:
    name, dict_id = tag_dictionary("tag36h11")
    return TagTarget(name, dict_id, 0.1, {i: (np.eye(3), np.zeros(3)) for i in ids},
                     corner_refinement=refine, image_gamma=gamma)


@pytest.mark.parametrize("refine", ["subpix", "contour", "none"])
def test_tags_direct_and_mirrored(refine):
    img, corners = tag_canvas([3, 8])
    h, w = img.shape
    for mirrored in (False, True):
        view = cv2.flip(img, 1) if mirrored else img
        det = detect_tags(view, tag_target([3, 8], refine), mirrored)
        assert det.status == FOUND and len(det.points) == 8, det.reason
        for key, truth in corners.items():
            name = key.split("#")[0]
            expected = np.array([w - 1 - truth[0], truth[1]]) if mirrored else truth
            assert np.linalg.norm(det.points[name] - expected) < 1.0, (name, mirrored)
    # a mirror image is not decoded as the same tags when the capture says there is no mirror
    det = detect_tags(cv2.flip(img, 1), tag_target([3, 8], refine), False)
    assert not det.points


def test_tags_unlisted_and_duplicated():
    img, _ = tag_canvas([3, 8, 3])
    det = detect_tags(img, tag_target([3, 8]), False)
    assert set(det.points) == {f"T8_{k}" for k in range(4)} and "tag 3 seen more than once" in det.reason
    det = detect_tags(img, tag_target([5]), False)
    assert det.status == NOT_FOUND and "only tags not in target.tags seen (3, 8" in det.reason


# --------------------------------------------------------------------------------------------------
# detect_capture
# --------------------------------------------------------------------------------------------------


def write_board_capture(tmp_path: Path, images: dict[str, np.ndarray], configs: list, num_mirrors: int = 1) -> Path:
    names = []
    for name, img in images.items():
        cv2.imwrite(str(tmp_path / name), img)
        names.append(name)
    h, w = next(iter(images.values())).shape
    capture = {
        "format": "mirror-fg/capture@1", "num_mirrors": num_mirrors,
        "camera": {"model": "pinhole", "width": w, "height": h, "fx": 300.0, "fy": 300.0, "cx": w / 2, "cy": h / 2},
        "target": {"kind": "chessboard", "cols": 6, "rows": 5, "square": 0.02},
        "images": [{"file": n, "mirror_configs": c} for n, c in zip(names, configs)],
    }
    path = tmp_path / "capture.yaml"
    path.write_text(yaml.safe_dump(capture))
    return path


def test_detect_capture_reports_and_each(tmp_path, capsys):
    board, corners = board_image(6, 5)
    size = (360, 300)
    img, _ = warp(board, corners, perspective(*size, board.shape[1], board.shape[0]), size)
    mirrored = cv2.flip(img, 1)
    blank = np.full((size[1], size[0]), 128, np.uint8)
    path = write_board_capture(
        tmp_path, {"a.png": mirrored, "b.png": blank, "c.png": mirrored, "d.png": cv2.resize(mirrored, (180, 150))},
        [[0, "each"], [0, "each"], [2, "each"], [0, 4]], num_mirrors=2,
    )
    # two mirrors: the image is not mirror-imaged, so the mirrored board is read in the other handedness
    cap = load_capture(path)
    ds, reports = detect_capture(cap, progress=True)  # stderr is not a terminal here: no bar
    d = dataset_to_dict(ds)
    assert capsys.readouterr().err == ""
    assert [r.status for r in reports] == [FOUND, NOT_FOUND, FOUND, REFUSED]
    assert "150" in reports[3].reason and "not found" in reports[1].reason
    assert [im["mirror_configs"] for im in d["images"]] == [[0, 5], [2, 6]]  # fresh above the 4 in use
    text = format_reports(reports)
    assert "a: found, 30 points" in text and text.endswith("4 images: 2 found, 1 not found, 1 refused")
    dataset_from_dict(d, source=str(path))


def test_target_never_found_and_undecodable_image(tmp_path):
    blank = np.full((100, 120), 128, np.uint8)
    path = write_board_capture(tmp_path, {"a.png": blank, "b.png": blank}, [[0], [1]])
    with pytest.raises(DatasetError) as info:
        detect_capture(load_capture(path), progress=False)
    message = str(info.value)
    assert "\n" not in message and "found in none of the 2 images" in message and "a: not found" in message
    (tmp_path / "b.png").write_bytes(b"\x89PNG but not really")
    with pytest.raises(DatasetError, match=r"images\[1\] \(b.png\): cannot decode the image"):
        detect_capture(load_capture(path), progress=False)


def test_grid_misfit_flags_corners_off_a_plane():
    from mirror_fg.vision.detectors import _grid_misfit_px

    target = ChessboardTarget(6, 5, 0.02)
    camera = {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "dist": [0.0] * 5}
    _, corners = board_image(6, 5)
    assert _grid_misfit_px(corners, target, camera) < 1e-3
    bent = corners.copy()
    bent[::7] += 15.0  # a false detection's corners off the grid
    assert _grid_misfit_px(bent, target, camera) > 2.0
