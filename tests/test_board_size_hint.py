"""A chessboard given by its squares instead of its inner corners: the one-line refusal
says what cols and rows count and names the size that is in the image."""
from __future__ import annotations

import cv2
import yaml

from mirror_fg.cli import main

from test_detect import board_image, perspective, warp, write_board_capture


def _capture(tmp_path, cols: int, rows: int):
    board, corners = board_image(6, 5)  # 7 x 6 squares, 6 x 5 inner corners
    size = (360, 300)
    img, _ = warp(board, corners, perspective(*size, board.shape[1], board.shape[0]), size)
    path = write_board_capture(tmp_path, {"a.png": cv2.flip(img, 1), "b.png": cv2.flip(img, 1)}, [[0], [1]])
    capture = yaml.safe_load(path.read_text())
    capture["target"].update(cols=cols, rows=rows)
    path.write_text(yaml.safe_dump(capture))
    return path


def _error(tmp_path, capsys, cols: int, rows: int) -> str:
    assert main(["detect", str(_capture(tmp_path, cols, rows)), "-o", str(tmp_path / "d.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    return err


def test_squares_counted_instead_of_corners_names_the_size_in_the_image(tmp_path, capsys):
    err = _error(tmp_path, capsys, 7, 6)
    assert "inner corners" in err and "a board of 6 x 5 inner corners is in a" in err, err
    assert "cols: 6, rows: 5" in err


def test_a_wrong_size_that_is_not_squares_says_what_cols_and_rows_count(tmp_path, capsys):
    err = _error(tmp_path, capsys, 9, 9)
    assert "cols and rows count inner corners" in err and "did you count squares" not in err, err


def test_the_right_size_is_found(tmp_path):
    assert main(["detect", str(_capture(tmp_path, 6, 5)), "-o", str(tmp_path / "d.json")]) == 0
