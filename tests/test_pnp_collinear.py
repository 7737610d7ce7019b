"""PnP minima without P3P starts on three points of one line (``pnp.pnp_minima(collinear_p3p=False)``: P3P
leaves the turn about the line free; a chessboard's first corners, in a dataset's order, are its first row):
the lowest minimum is the full search's, on noisy boards near and far, seen through a mirror (parity) and
directly; P3P still sees every triple of four points in general position; the default search is unchanged.
The arm's screen, which takes that search, leaves out what the shared screen leaves out."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from mirror_fg.core.geometry import so3_exp_many
from mirror_fg.solver.start import pnp
from test_pnp_minima import _reference_minima  # noqa: E402  (the search with every start)


def _board(rows: int = 5, cols: int = 6, square: float = 0.03) -> np.ndarray:
    """A chessboard's inner corners row by row (target frame, z = 0)."""
    return np.array([[(c - (cols - 1) / 2) * square, (r - (rows - 1) / 2) * square, 0.0]
                     for r in range(rows) for c in range(cols)])


def _seen(rng, points: np.ndarray, distance: float, noise: float) -> np.ndarray:
    R = so3_exp_many(rng.normal(size=3) * rng.uniform(0.0, 0.8))[0]
    t = np.array([*rng.uniform(-0.05, 0.05, 2), distance])
    camera = points @ R.T + t
    return camera[:, :2] / camera[:, 2:3] + rng.normal(scale=noise, size=(len(points), 2))


def test_no_p3p_on_a_line(monkeypatch) -> None:
    rng = np.random.default_rng(4)
    board = _board()
    triples = []
    real = cv2.solveP3P

    def recording(obj, img, *args, **kwargs):
        triples.append(obj.reshape(-1, 3).copy())
        return real(obj, img, *args, **kwargs)

    monkeypatch.setattr(pnp.cv2, "solveP3P", recording)
    seen = _seen(rng, board, 0.5, 1e-3)
    assert len(pnp.pnp_minima(board, seen, 1, collinear_p3p=False)) >= 1
    assert triples == []  # the first four triples are all on the board's first row
    pnp.pnp_minima(board, seen, 1)
    assert len(triples) == 4  # the default search: every start
    general = rng.uniform(-0.1, 0.1, (4, 3))
    pnp.pnp_minima(general, _seen(rng, general, 0.6, 0.0), 0, collinear_p3p=False)
    assert len(triples) == 8  # four points in general position: every triple


@pytest.mark.parametrize("rows,cols", [(5, 6), (4, 4), (7, 9)])
def test_a_boards_lowest_minimum_is_that_of_every_start(rows, cols) -> None:
    rng = np.random.default_rng(rows * cols)
    board = _board(rows, cols)
    for _ in range(60):
        distance, noise = float(rng.uniform(0.3, 2.5)), float(rng.choice([0.0, 6e-4, 3e-3]))
        normalized = _seen(rng, board, distance, noise)
        for parity in (0, 1):
            observed = normalized * ([1.0, -1.0] if parity else 1.0)  # pnp_minima flips odd parity back
            found = pnp.pnp_minima(board, observed, parity, collinear_p3p=False)
            flip = np.diag([1.0, -1.0, 1.0]) if parity else np.eye(3)
            reference = [(flip @ R, flip @ t) for R, t in _reference_minima(board, normalized)]
            assert np.array_equal(found[0][0], reference[0][0]) and np.array_equal(found[0][1], reference[0][1])
            # the others are among the full search's (which finds further, shallow minima of some far, noisy boards)
            assert all(any(np.abs(R - R_ref).max() <= pnp.SAME_MINIMUM for R_ref, _ in reference) for R, _ in found)


def test_the_arms_screen_leaves_out_what_the_shared_screen_does(tmp_path) -> None:
    pytest.importorskip("pinocchio")
    from mirror_fg.io.dataset import load_dataset
    from mirror_fg.robot.simulate import simulate_arm, write_arm_simulation
    from mirror_fg.solver.screen.consensus import screen
    from mirror_fg.solver.options import SolveOptions
    from mirror_fg.solver.batch.robot_solve import RobotPipelineProblem

    dataset, truth = simulate_arm("arm6", False, placements=3, arm_poses=5, seed=2)
    dataset["images"][1]["observations"]["F8"][1] += 30.0  # a gross corner
    shuffled = dataset["images"][6]["observations"]  # a row of corners in another order
    names, values = list(shuffled), list(shuffled.values())
    values[6:12] = values[6:12][::-1]
    dataset["images"][6]["observations"] = dict(zip(names, values))
    path = tmp_path / "arm.json"
    write_arm_simulation(str(path), dataset, truth)
    ds = load_dataset(path)
    shared, shared_out, _ = screen(ds)
    arm, arm_out = RobotPipelineProblem(None, SolveOptions()).screen(ds)
    assert [(e.image, e.point, e.reason) for e in arm_out] == [(e.image, e.point, e.reason) for e in shared_out]
    assert {e.image for e in arm_out} == {ds.images[1].id, ds.images[6].id}
    assert [im.observations for im in arm.images] == [im.observations for im in shared.images]
