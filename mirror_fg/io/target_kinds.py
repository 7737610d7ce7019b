"""The kinds of known target a capture@1 names (docs/formats.md "Targets"): chessboard, ChArUco board,
AprilTag / ArUco board and a points list, each with its points in the target frame (metres), its
symmetries and its tag dictionary; and the field readers the target readers share (io/target.py,
io/screen_target.py)."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import finite, is_int, short

__all__ = ["ChessboardTarget", "Symmetry", "target_symmetries", "CharucoTarget", "TagTarget", "PointsTarget", "Target",
           "tag_dictionary", "ROTATION_TOL", "count_field", "length_field"]


#: Largest ``|R^T R - I|`` entry accepted for a rotation matrix typed into a capture file.
ROTATION_TOL = 1e-4

#: Short AprilTag family names -> OpenCV dictionary attribute.
_APRILTAG_NAMES = {
    "tag16h5": "DICT_APRILTAG_16h5",
    "tag25h9": "DICT_APRILTAG_25h9",
    "tag36h10": "DICT_APRILTAG_36h10",
    "tag36h11": "DICT_APRILTAG_36h11",
}


@dataclass(frozen=True)
class ChessboardTarget:
    """Chessboard of ``cols`` x ``rows`` inner corners, ``square`` metres; fiducial ``C{row*cols+col:02d}``."""

    cols: int
    rows: int
    square: float
    kind: str = "chessboard"

    def name(self, col: int, row: int) -> str:
        """Fiducial name of inner corner (col, row)."""
        return f"C{row * self.cols + col:02d}"

    def target_points(self) -> dict[str, np.ndarray]:
        """Corner positions in the board frame (metres), row-major."""
        return {
            self.name(c, r): np.array([c * self.square, r * self.square, 0.0])
            for r in range(self.rows)
            for c in range(self.cols)
        }

    @property
    def symmetric(self) -> bool:
        """True when the board looks the same turned half a turn (``cols + rows`` even)."""
        return (self.cols + self.rows) % 2 == 0

    def symmetries(self) -> list[Symmetry]:
        """The turns of the board in its plane that its colours do not tell apart, identity first.

        ``cols + rows`` odd: the identity only. Even: the half turn; a square board with an even count
        also the quarter turns (with an odd count a quarter turn swaps the colours of the squares
        next to the corners, which the detector sees).
        """
        identity = {n: n for n in self.target_points()}
        if not self.symmetric:
            return [Symmetry("identity", identity)]
        last_c, last_r = self.cols - 1, self.rows - 1
        half = {self.name(c, r): self.name(last_c - c, last_r - r) for r in range(self.rows) for c in range(self.cols)}
        if self.cols != self.rows or self.cols % 2 == 1:
            return [Symmetry("identity", identity), Symmetry("half turn", half)]
        # (col, row) -> (n-1-row, col): a quarter turn about the board's centre, x towards y
        quarter = {self.name(c, r): self.name(last_r - r, c) for r in range(self.rows) for c in range(self.cols)}
        three_quarters = {n: half[quarter[n]] for n in quarter}
        return [Symmetry("identity", identity), Symmetry("quarter turn", quarter), Symmetry("half turn", half),
                Symmetry("three-quarter turn", three_quarters)]

    def top_and_bottom_rows(self) -> tuple[list[str], list[str]]:
        """Names of the first and last row: their direction in an image says whether it shows the board upright."""
        return ([self.name(c, 0) for c in range(self.cols)], [self.name(c, self.rows - 1) for c in range(self.cols)])


@dataclass(frozen=True)
class Symmetry:
    """A turn of a target in its plane that maps its fiducials onto one another (metres stay exact).

    ``permutation[n]`` is the fiducial at the position fiducial ``n`` moves to. A detection in one
    labelling, ``points``, is in this one ``{n: points[permutation[n]]}`` (:meth:`relabel`).
    """

    name: str
    permutation: dict[str, str]

    def relabel(self, points: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``points`` (name -> pixel) in the labelling turned by this symmetry; other names unchanged."""
        out = {n: p for n, p in points.items() if n not in self.permutation}
        out.update({n: points[m] for n, m in self.permutation.items() if m in points})
        return out


@dataclass(frozen=True)
class TagTarget:
    """AprilTag/ArUco markers: ``tags`` maps an id to its frame ``(R, t)`` in the frame named by ``frame``.

    ``frame`` is ``"base"`` for tags listed under ``tags`` and ``"target"`` for a grid (then
    ``T_base_target`` applies). ``dictionary_id`` is the ``cv2.aruco.DICT_*`` constant.
    """

    dictionary: str
    dictionary_id: int
    tag_size: float
    tags: dict[int, tuple[np.ndarray, np.ndarray]]
    frame: str = "base"
    corner_refinement: str = "subpix"
    image_gamma: str = "srgb"
    kind: str = "apriltag"

    @staticmethod
    def corner_name(tag_id: int, k: int) -> str:
        """Fiducial name of corner k (cv2.aruco order) of tag ``tag_id``."""
        return f"T{tag_id}_{k}"

    def corners_in_tag(self) -> np.ndarray:
        """(4, 3) corners in the tag frame, cv2.aruco order (metres)."""
        h = self.tag_size / 2.0
        return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])

    def target_points(self) -> dict[str, np.ndarray]:
        """Every listed tag's corners in the frame of ``tags`` (metres)."""
        corners = self.corners_in_tag()
        out: dict[str, np.ndarray] = {}
        for tag_id in sorted(self.tags):
            R, t = self.tags[tag_id]
            for k in range(4):
                out[self.corner_name(tag_id, k)] = R @ corners[k] + t
        return out


@dataclass(frozen=True)
class CharucoTarget:
    """ChArUco board of ``cols`` x ``rows`` squares (``square``, ``marker`` metres); fiducial ``C{id:02d}``.

    ``dictionary_id`` is the ``cv2.aruco.DICT_*`` constant; ``legacy_pattern`` OpenCV's pre-4.6 layout.
    """

    cols: int
    rows: int
    square: float
    marker: float
    dictionary: str
    dictionary_id: int
    legacy_pattern: bool = False
    kind: str = "charuco"

    @staticmethod
    def name(corner_id: int) -> str:
        """Fiducial name of ChArUco corner ``corner_id`` (OpenCV's numbering)."""
        return f"C{corner_id:02d}"

    def board(self) -> Any:
        """The ``cv2.aruco.CharucoBoard`` (its frame is the board frame of the fiducials)."""
        import cv2

        dictionary = cv2.aruco.getPredefinedDictionary(self.dictionary_id)
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker, dictionary)
        board.setLegacyPattern(self.legacy_pattern)
        return board

    def target_points(self) -> dict[str, np.ndarray]:
        """Inner corners in the board frame (metres), by id: ``((col+1)*square, (row+1)*square, 0)``."""
        return {
            self.name(r * (self.cols - 1) + c): np.array([(c + 1) * self.square, (r + 1) * self.square, 0.0])
            for r in range(self.rows - 1)
            for c in range(self.cols - 1)
        }


@dataclass(frozen=True)
class PointsTarget:
    """Points measured on the robot (target frame, metres); pixels come with each image."""

    fiducials: dict[str, np.ndarray]
    kind: str = "points"

    def target_points(self) -> dict[str, np.ndarray]:
        return {name: p.copy() for name, p in self.fiducials.items()}


Target = ChessboardTarget | CharucoTarget | TagTarget | PointsTarget


def target_symmetries(target: Target) -> list[Symmetry]:
    """The target's symmetries that detection cannot tell apart (identity first; only the identity
    for every target but a symmetric chessboard: tag and ChArUco ids name every corner)."""
    if isinstance(target, ChessboardTarget):
        return target.symmetries()
    return [Symmetry("identity", {n: n for n in target.target_points()})]


def tag_dictionary(name: Any, where: str = "dictionary") -> tuple[str, int]:
    """``(canonical name, cv2.aruco.DICT_* value)`` of an AprilTag family or ArUco dictionary name."""
    import cv2

    if not isinstance(name, str) or not name:
        raise DatasetError(f"{where}: must be a name such as 'tag36h11' or 'DICT_4X4_50', got {short(name)}")
    key = name.strip()
    attr = _APRILTAG_NAMES.get(key.lower())
    if attr is None:
        upper = key.upper()
        candidates = [upper, "DICT_" + upper, "DICT_APRILTAG_" + upper.removeprefix("TAG")]
        attr = next((c for c in candidates if hasattr(cv2.aruco, c)), None)
    if attr is None or not hasattr(cv2.aruco, attr):
        raise DatasetError(
            f"{where}: unknown dictionary {short(name)} (AprilTag: tag16h5, tag25h9, tag36h10, tag36h11; "
            "ArUco: DICT_4X4_50 ... DICT_7X7_1000, DICT_ARUCO_ORIGINAL)"
        )
    return key, int(getattr(cv2.aruco, attr))


def count_field(m: Mapping[str, Any], key: str, minimum: int, where: str, what: str = "") -> int:
    """``m[key]`` checked to be an integer >= ``minimum``; ``what`` follows the bound in the message."""
    value = m.get(key)
    if not is_int(value) or value < minimum:
        raise DatasetError(f"{where}: {key} must be an integer >= {minimum}{what}, got {short(value)}")
    return int(value)


def length_field(m: Mapping[str, Any], key: str, where: str, what: str = "metres") -> float:
    """``m[key]`` checked to be a finite number > 0 (a length, ``what`` says in what)."""
    value = finite(m.get(key))
    if value is None or value <= 0:
        raise DatasetError(f"{where}: {key} must be a number > 0 ({what}), got {short(m.get(key))}")
    return value
