"""Target kind ``screen`` of a capture@1: a pattern shown full screen on a monitor (``mirror-fg pattern``).

``target: {kind: screen, width_px, height_px, width_mm, height_mm, pattern: {...}}`` (docs/formats.md,
"Screens"). The base frame is the *screen frame*: origin at the top-left corner of the active area, x to
the right along the pixel rows, y down, z into the screen, metres. Pixel (i, j) covers [i, i + 1) x
[j, j + 1) of the pixel-edge coordinates (e_u, e_v), which lie at
``(e_u * width_mm / width_px, e_v * height_mm / height_px, 0) / 1000`` (:meth:`ScreenTarget.screen_point`).

``pattern`` is what ``mirror-fg pattern`` drew, in screen pixels (pixel-edge coordinates):

* ``{kind: charuco, cols, rows, square_px, marker_px, dictionary, origin_px: [u, v]}``: OpenCV's
  ``cv2.aruco.CharucoBoard`` of ``cols`` x ``rows`` squares (top-left square black) whose top-left outer
  corner is at ``origin_px``; corner ``id`` (``row*(cols-1) + col``) is fiducial ``C{id:02d}`` at
  ``origin_px + ((col+1), (row+1)) * square_px``.
* ``{kind: chessboard, cols, rows, square_px, origin_px}``: ``cols`` x ``rows`` inner corners, ``cols + 1``
  x ``rows + 1`` squares from ``origin_px`` with the top-left one black; inner corner (col, row) is
  fiducial ``C{row*cols+col:02d}`` at ``origin_px + (col+1, row+1) * square_px``. ``cols + rows`` must be
  odd (a board that looks the same turned half a turn cannot be told from its turn).
* ``{kind: apriltag, dictionary, tag_px, spacing_px, cols, rows, first_id, origin_px}``: a grid of tags,
  tag ``first_id + row*cols + col`` with the top-left corner of its black square at ``origin_px + (col,
  row) * spacing_px``; fiducial ``T{id}_{k}`` is corner k in cv2.aruco's order (top-left, top-right,
  bottom-right, bottom-left as shown on the screen).

Detection runs on :attr:`ScreenTarget.pattern_target`, the pattern as an ordinary chessboard, ChArUco or
tag target in screen-pixel units (same fiducial names); :meth:`ScreenTarget.target_points` puts each
fiducial in the screen frame.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import check_keys, finite, is_int, short, type_name
from mirror_fg.io.target_kinds import (
    CharucoTarget,
    ChessboardTarget,
    TagTarget,
    count_field,
    length_field,
    tag_dictionary,
)

__all__ = ["ScreenTarget", "screen_target_from_dict", "PATTERN_KINDS", "check_screen_mm", "MAX_SCREEN_PX",
           "MIN_SCREEN_MM", "MAX_SCREEN_MM"]

#: Most pixels on a side of a screen accepted (16K displays have 15360): a larger count is a typing
#: mistake, and ``mirror-fg pattern`` would allocate an image of that size.
MAX_SCREEN_PX = 16384
#: Smallest and largest side of a screen's active area accepted (millimetres): a watch face to a video
#: wall. ``0.6`` is a size typed in metres; ``600000`` one typed in micrometres.
MIN_SCREEN_MM = 5.0
MAX_SCREEN_MM = 10000.0

PATTERN_KINDS = ("charuco", "chessboard", "apriltag")
_SCREEN_KEYS = ("kind", "width_px", "height_px", "width_mm", "height_mm", "pattern")
_PATTERN_KEYS = {
    "charuco": ("kind", "cols", "rows", "square_px", "marker_px", "dictionary", "origin_px"),
    "chessboard": ("kind", "cols", "rows", "square_px", "origin_px"),
    "apriltag": ("kind", "dictionary", "tag_px", "spacing_px", "cols", "rows", "first_id", "origin_px"),
}


@dataclass(frozen=True)
class ScreenTarget:
    """A pattern on a screen of ``width_px`` x ``height_px`` pixels and ``width_mm`` x ``height_mm`` active area.

    ``pattern``: the pattern block as validated (plain values). ``pattern_target``: the pattern as a
    chessboard / ChArUco / tag target whose board coordinates are screen pixels; ``offset_px`` and
    ``y_sign`` map its board point (x, y) to pixel-edge coordinates ``offset_px + (x, y_sign * y)``.
    """

    width_px: int
    height_px: int
    width_mm: float
    height_mm: float
    pattern: dict[str, Any]
    pattern_target: ChessboardTarget | CharucoTarget | TagTarget
    offset_px: tuple[float, float]
    y_sign: float = 1.0
    kind: str = "screen"

    @property
    def metres_per_px(self) -> np.ndarray:
        """(2,) metres per pixel along x (rows) and y (columns) of the screen."""
        return np.array([self.width_mm / self.width_px, self.height_mm / self.height_px]) / 1000.0

    def screen_point(self, edge_px: Any) -> np.ndarray:
        """Screen-frame points (N, 3) or (3,), metres, of pixel-edge coordinates (N, 2) or (2,)."""
        e = np.asarray(edge_px, dtype=float)
        xy = e * self.metres_per_px
        return np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1)

    def fiducial_pixels(self) -> dict[str, np.ndarray]:
        """Every fiducial's pixel-edge coordinates (2,) on the screen, in the pattern's order."""
        offset = np.asarray(self.offset_px, dtype=float)
        return {name: offset + np.array([p[0], self.y_sign * p[1]])
                for name, p in self.pattern_target.target_points().items()}

    def target_points(self) -> dict[str, np.ndarray]:
        """Fiducials in the screen frame (metres): the base frame of a screen capture."""
        return {name: self.screen_point(e) for name, e in self.fiducial_pixels().items()}

    def to_dict(self) -> dict[str, Any]:
        """The capture@1 ``target`` block (what ``pattern.target.yaml`` holds)."""
        return {"kind": "screen", "width_px": self.width_px, "height_px": self.height_px,
                "width_mm": self.width_mm, "height_mm": self.height_mm, "pattern": dict(self.pattern)}


def screen_target_from_dict(t: Mapping[str, Any], where: str) -> ScreenTarget:
    """The ``screen`` target ``t`` (``where`` starts every message); DatasetError on any problem."""
    check_keys(t, _SCREEN_KEYS, where)
    width_px, height_px = (count_field(t, key, 1, where, " (screen pixels)") for key in ("width_px", "height_px"))
    for key, pixels in (("width_px", width_px), ("height_px", height_px)):
        if pixels > MAX_SCREEN_PX:
            raise DatasetError(f"{where}: {key} {pixels} is not a plausible screen (at most {MAX_SCREEN_PX} pixels a side)")
    width_mm, height_mm = (length_field(t, key, where, "millimetres of the active area") for key in ("width_mm", "height_mm"))
    for key, mm in (("width_mm", width_mm), ("height_mm", height_mm)):
        check_screen_mm(mm, f"{where}: {key}")
    p = t.get("pattern")
    pw = f"{where}: pattern"
    if not isinstance(p, Mapping):
        raise DatasetError(f"{pw}: expected a mapping with 'kind' (as mirror-fg pattern writes it), got {type_name(p)}")
    kind = p.get("kind")
    if kind not in PATTERN_KINDS:
        raise DatasetError(f"{pw}: kind must be one of {', '.join(PATTERN_KINDS)}, got {short(kind)}")
    check_keys(p, _PATTERN_KEYS[kind], pw)
    origin = _origin(p.get("origin_px"), pw)
    pattern: dict[str, Any] = {"kind": kind}
    inner: ChessboardTarget | CharucoTarget | TagTarget
    if kind == "charuco":
        cols, rows = (count_field(p, key, 2, pw, " (squares)") for key in ("cols", "rows"))
        square = length_field(p, "square_px", pw, "screen pixels")
        marker = finite(p.get("marker_px"))
        if marker is None or not 0 < marker < square:
            raise DatasetError(f"{pw}: marker_px must be a number > 0 and below square_px, got {short(p.get('marker_px'))}")
        name, dict_id = tag_dictionary(p.get("dictionary"), f"{pw}: dictionary")
        _enough_ids(dict_id, cols * rows // 2, name, pw, f"a {cols} x {rows} board ({cols * rows // 2} markers)")
        inner = CharucoTarget(cols, rows, square, marker, name, dict_id)
        pattern.update(cols=cols, rows=rows, square_px=square, marker_px=marker, dictionary=name)
        offset, y_sign = origin, 1.0
    elif kind == "chessboard":
        cols, rows = (count_field(p, key, 3, pw, " (inner corners)") for key in ("cols", "rows"))
        square = length_field(p, "square_px", pw, "screen pixels")
        if (cols + rows) % 2 == 0:
            raise DatasetError(f"{pw}: cols + rows must be odd ({cols} + {rows}): a board that looks the same turned "
                               "half a turn cannot tell which corner is C00")
        inner = ChessboardTarget(cols, rows, square)
        pattern.update(cols=cols, rows=rows, square_px=square)
        offset, y_sign = origin + square, 1.0
    else:
        name, dict_id = tag_dictionary(p.get("dictionary"), f"{pw}: dictionary")
        cols, rows = (count_field(p, key, 1, pw) for key in ("cols", "rows"))
        size = length_field(p, "tag_px", pw, "screen pixels, edge of the black square")
        spacing = length_field(p, "spacing_px", pw, "screen pixels, centre to centre")
        if spacing < size:
            raise DatasetError(f"{pw}: spacing_px ({spacing:g}) is below tag_px ({size:g}): the tags would overlap")
        first = p.get("first_id", 0)
        if not is_int(first) or first < 0:
            raise DatasetError(f"{pw}: first_id must be a non-negative integer, got {short(first)}")
        _enough_ids(dict_id, first + cols * rows, name, pw, f"tags {first}-{first + cols * rows - 1}")
        tags = {first + r * cols + c: (np.eye(3), np.array([c * spacing, -r * spacing, 0.0]))
                for r in range(rows) for c in range(cols)}
        inner = TagTarget(name, dict_id, size, tags, frame="target")
        pattern.update(dictionary=name, tag_px=size, spacing_px=spacing, cols=cols, rows=rows, first_id=int(first))
        offset, y_sign = origin + size / 2.0, -1.0  # the tag frame's y is up on the screen
    pattern["origin_px"] = [float(origin[0]), float(origin[1])]
    screen = ScreenTarget(width_px, height_px, width_mm, height_mm, pattern, inner,
                          (float(offset[0]), float(offset[1])), y_sign)
    _check_fits(screen, pw)
    return screen


def check_screen_mm(value: float, where: str) -> None:
    """Refuse a screen side (millimetres) outside :data:`MIN_SCREEN_MM` .. :data:`MAX_SCREEN_MM`: below it
    the size was most likely typed in metres (``0.6`` for 600 mm), above it in micrometres or by mistake."""
    if value < MIN_SCREEN_MM:
        metres = (f" ({value:g} m = {value * 1000:g} mm)" if value * 1000 >= MIN_SCREEN_MM else "")
        raise DatasetError(f"{where}: {value:g} mm is not a plausible screen side (at least {MIN_SCREEN_MM:g} mm); "
                           f"screen sizes are in millimetres{metres}")
    if value > MAX_SCREEN_MM:
        raise DatasetError(f"{where}: {value:g} mm is not a plausible screen side (at most {MAX_SCREEN_MM:g} mm, "
                           f"{MAX_SCREEN_MM / 1000:g} m); screen sizes are in millimetres")


def _origin(value: Any, where: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 2 or any(finite(x) is None for x in value):
        raise DatasetError(f"{where}: origin_px must be [u, v], pixel-edge coordinates on the screen, got {short(value)}")
    return np.array([float(x) for x in value])


def _enough_ids(dict_id: int, needed: int, name: str, where: str, what: str) -> None:
    import cv2

    available = int(cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0])
    if needed > available:
        raise DatasetError(f"{where}: {what} needs {needed} ids; dictionary {name} has only {available}")


def _check_fits(screen: ScreenTarget, where: str) -> None:
    """Every square or tag of the pattern lies on the screen's pixels."""
    p = screen.pattern
    origin = np.asarray(p["origin_px"])
    if p["kind"] == "charuco":
        extent = np.array([p["cols"], p["rows"]]) * p["square_px"]
    elif p["kind"] == "chessboard":
        extent = (np.array([p["cols"], p["rows"]]) + 1) * p["square_px"]
    else:
        extent = (np.array([p["cols"], p["rows"]]) - 1) * p["spacing_px"] + p["tag_px"]
    low, high = origin, origin + extent
    if np.any(low < 0) or high[0] > screen.width_px or high[1] > screen.height_px:
        raise DatasetError(
            f"{where}: covers pixels [{low[0]:g}, {high[0]:g}) x [{low[1]:g}, {high[1]:g}), which do not fit on the "
            f"{screen.width_px} x {screen.height_px} screen"
        )
