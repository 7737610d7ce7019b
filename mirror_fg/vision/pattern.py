"""``mirror-fg pattern``: a full-screen calibration pattern for a monitor seen by its webcam in a hand-held mirror.

:func:`design_pattern` chooses the layout for a screen of ``width_px`` x ``height_px`` pixels and
``width_mm`` x ``height_mm`` active area and returns it as a
:class:`~mirror_fg.io.screen_target.ScreenTarget` (the capture@1 ``target`` block that describes it);
:func:`draw_pattern` draws exactly those pixels; :func:`pattern_files` gives the PNG, the
``.target.yaml`` and the ``.html`` page that shows it at one image pixel per device pixel.

Design (docs/gaze_guide.md): the webcam sees the screen through a mirror held 0.2-0.6 m in front of
it, so along a path of 0.4-1.2 m; only a part of the screen is in the mirror, and the view is
mirror-imaged. Hence by default a ChArUco board (every corner named by its marker, any subset of
them usable, decoded on the flipped image), squares of about :data:`SQUARE_MM` (at most a sixth of the
screen's height, :data:`FILL_SQUARES`, so that a laptop's corners still span it; at 1.2 m a 640-pixel
webcam with a 60 degree field of view, fx ~ 550 px, sees 40 mm as 18 px: ~3 px per bit of a 4x4
marker, which decodes), markers of 4x4 bits (the largest bits for a given square), and a white quiet
border of at least half a square between the board and the monitor's dark bezel.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.io.screen_target import (
    MAX_SCREEN_PX, PATTERN_KINDS, ScreenTarget, check_screen_mm, screen_target_from_dict,
)

__all__ = ["SQUARE_MM", "PatternFiles", "design_pattern", "draw_pattern", "screen_mm_from_diagonal",
           "pattern_files", "pattern_texts", "html_page", "write_pattern", "pattern_summary"]

#: Edge of a square (ChArUco, chessboard) or the tag spacing, millimetres on the screen (see the module).
SQUARE_MM = 40.0
#: The default square is at most 1/FILL_SQUARES of the screen's height (corners that span the screen
#: constrain its pose: on a 15.6-inch laptop 32 mm squares give 3x smaller Cramer-Rao bounds than 40 mm).
FILL_SQUARES = 6
#: White margin around the board, at least this fraction of a square (the bezel is dark).
QUIET_FRACTION = 0.5
#: Marker (ChArUco) or tag (AprilTag) edge as a fraction of the square / tag spacing, at most.
MARKER_FRACTION = 0.75
#: Fewest screen pixels per bit of a marker: below it the pattern itself cannot be drawn sharply.
MIN_BIT_PX = 2
#: Fewest squares (ChArUco: squares; chessboard: squares, i.e. inner corners + 1; AprilTag: tags) per axis.
MIN_COUNT = {"charuco": (4, 3), "chessboard": (5, 4), "apriltag": (2, 2)}
#: Dictionaries: 4x4-bit ArUco markers for ChArUco (largest bits; 250 ids), tag36h11 for AprilTag grids.
CHARUCO_DICTIONARY, APRILTAG_DICTIONARY = "DICT_4X4_250", "tag36h11"
#: A board with more markers than this takes its ids from the larger 4x4 dictionary (less error correction).
LARGE_BOARD_MARKERS, LARGE_CHARUCO_DICTIONARY = 250, "DICT_4X4_1000"
#: First line of the side files, so that a later run may replace them (io.output's marker check).
MARKER_LINE = "written by mirror-fg pattern"


def screen_mm_from_diagonal(width_px: int, height_px: int, diagonal_in: float) -> tuple[float, float]:
    """Active area (width_mm, height_mm) of a screen of ``diagonal_in`` inches whose pixels are square."""
    diagonal_mm = 25.4 * diagonal_in
    hypot = math.hypot(width_px, height_px)
    return diagonal_mm * width_px / hypot, diagonal_mm * height_px / hypot


def design_pattern(width_px: int, height_px: int, width_mm: float, height_mm: float, kind: str = "charuco",
                   square_mm: float | None = None) -> ScreenTarget:
    """The pattern for this screen (module docstring), as its ``screen`` target. DatasetError (one line)
    for a screen of no size or a pattern that does not fit."""
    if kind not in PATTERN_KINDS:
        raise DatasetError(f"pattern: kind must be one of {', '.join(PATTERN_KINDS)}, got {kind!r}")
    _check_screen_px(width_px, height_px)
    for what, mm in (("width", width_mm), ("height", height_mm)):
        if not (math.isfinite(mm) and mm > 0):
            raise DatasetError(f"pattern: the screen's {what} must be more than 0 mm, got {mm:g} mm")
        check_screen_mm(mm, f"pattern: the screen's {what}")
    # default: SQUARE_MM, smaller on a small screen so that the corners still span it (a laptop's)
    want_mm = min(SQUARE_MM, min(width_mm, height_mm) / FILL_SQUARES) if square_mm is None else square_mm
    if not (math.isfinite(want_mm) and want_mm > 0):
        raise DatasetError(f"pattern: the square must be more than 0 mm, got {want_mm:g} mm")
    if square_mm is not None and not square_mm <= min(width_mm, height_mm):
        raise DatasetError(f"pattern: --square-mm {square_mm:.6g} is larger than the screen ({width_mm:.6g} x "
                           f"{height_mm:.6g} mm): the square is in millimetres on the screen")
    px_per_mm = min(width_px / width_mm, height_px / height_mm)
    import cv2

    name = APRILTAG_DICTIONARY if kind == "apriltag" else CHARUCO_DICTIONARY
    from mirror_fg.io.target import tag_dictionary

    name, dict_id = tag_dictionary(name)
    bits = int(cv2.aruco.getPredefinedDictionary(dict_id).markerSize) + 2  # data bits + black border
    square = 2 * max(1, int(round(want_mm * px_per_mm / 2)))  # even: the marker sits centred on whole pixels
    min_cols, min_rows = MIN_COUNT[kind]
    cols, rows, extent = _layout(width_px, height_px, kind, square, bits)
    while square_mm is None and (cols < min_cols or rows < min_rows) and square > 2:
        square -= 2  # the default square shrinks on a small screen until the fewest squares fit
        cols, rows, extent = _layout(width_px, height_px, kind, square, bits)
    marker = _marker_px(square, bits)
    what = "tags" if kind == "apriltag" else "squares"
    if marker < bits * MIN_BIT_PX or cols < min_cols or rows < min_rows:
        too_small = marker < bits * MIN_BIT_PX
        raise DatasetError(
            f"pattern: a {kind} pattern of at least {min_cols} x {min_rows} {what} does not fit on the {width_px} x "
            f"{height_px} screen with its quiet border "
            + (f"(its markers would have less than {MIN_BIT_PX} px per bit)" if too_small
               else f"(squares of {_describe(square, px_per_mm)} give {max(cols, 0)} x {max(rows, 0)}; choose smaller squares)")
        )
    origin = [float((width_px - extent[0]) // 2), float((height_px - extent[1]) // 2)]
    if kind == "charuco" and cols * rows // 2 > LARGE_BOARD_MARKERS:  # small squares on a large screen
        name, dict_id = tag_dictionary(LARGE_CHARUCO_DICTIONARY)
    ids = cols * rows // 2 if kind == "charuco" else cols * rows if kind == "apriltag" else 0
    available = int(cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0])
    if ids > available:
        raise DatasetError(f"pattern: {cols} x {rows} {what} of {_describe(square, px_per_mm)} need {ids} marker ids, more "
                           f"than {name} has ({available}); choose larger squares")
    if kind == "charuco":
        pattern: dict[str, Any] = {"kind": kind, "cols": cols, "rows": rows, "square_px": square, "marker_px": marker,
                                   "dictionary": name, "origin_px": origin}
    elif kind == "chessboard":
        pattern = {"kind": kind, "cols": cols - 1, "rows": rows - 1, "square_px": square, "origin_px": origin}
    else:
        pattern = {"kind": kind, "dictionary": name, "tag_px": marker, "spacing_px": square, "cols": cols,
                   "rows": rows, "first_id": 0, "origin_px": origin}
    block = {"kind": "screen", "width_px": width_px, "height_px": height_px, "width_mm": float(width_mm),
             "height_mm": float(height_mm), "pattern": pattern}
    return screen_target_from_dict(block, "pattern")


def _marker_px(square: int, bits: int) -> int:
    """Edge of a marker or tag (pixels): a whole number of pixels per bit, at most MARKER_FRACTION of a square."""
    return bits * int(MARKER_FRACTION * square // bits)


def _layout(width_px: int, height_px: int, kind: str, square: int, bits: int) -> tuple[int, int, tuple[int, int]]:
    """(cols, rows, extent (w, h) pixels) of the pattern with squares (tag spacing) of ``square`` pixels
    inside the quiet border; cols, rows count squares (ChArUco, chessboard) or tags."""
    border = int(math.ceil(QUIET_FRACTION * square))
    if kind == "apriltag":  # tags `square` apart, each `marker` wide
        marker = _marker_px(square, bits)
        cols = (width_px - 2 * border - marker) // square + 1
        rows = (height_px - 2 * border - marker) // square + 1
        return cols, rows, ((cols - 1) * square + marker, (rows - 1) * square + marker)
    cols, rows = (width_px - 2 * border) // square, (height_px - 2 * border) // square
    if kind == "chessboard" and (cols + rows) % 2 == 0:
        cols -= 1  # inner corners (cols - 1) + (rows - 1) odd: the colours tell the half turn apart
    return cols, rows, (cols * square, rows * square)


def _describe(square_px: int, px_per_mm: float) -> str:
    return f"{square_px} px = {square_px / px_per_mm:.0f} mm"


def draw_pattern(screen: ScreenTarget) -> np.ndarray:
    """The pattern as an 8-bit grey image of exactly ``height_px`` x ``width_px`` (white background)."""
    import cv2

    p = screen.pattern
    image = np.full((screen.height_px, screen.width_px), 255, np.uint8)
    u0, v0 = (int(round(x)) for x in p["origin_px"])
    if p["kind"] == "charuco":
        target = screen.pattern_target
        size = (p["cols"] * int(p["square_px"]), p["rows"] * int(p["square_px"]))
        board = target.board().generateImage(size, marginSize=0, borderBits=1)  # type: ignore[union-attr]
        image[v0:v0 + size[1], u0:u0 + size[0]] = board
    elif p["kind"] == "chessboard":
        square = int(p["square_px"])
        for r in range(p["rows"] + 1):
            for c in range(p["cols"] + 1):
                if (r + c) % 2 == 0:  # the top-left square is black
                    image[v0 + r * square:v0 + (r + 1) * square, u0 + c * square:u0 + (c + 1) * square] = 0
    else:
        dictionary = cv2.aruco.getPredefinedDictionary(screen.pattern_target.dictionary_id)  # type: ignore[union-attr]
        tag_px, spacing = int(p["tag_px"]), int(p["spacing_px"])
        for r in range(p["rows"]):
            for c in range(p["cols"]):
                tag = cv2.aruco.generateImageMarker(dictionary, p["first_id"] + r * p["cols"] + c, tag_px, borderBits=1)
                image[v0 + r * spacing:v0 + r * spacing + tag_px, u0 + c * spacing:u0 + c * spacing + tag_px] = tag
    return image


@dataclass(frozen=True)
class PatternFiles:
    """The three files of one pattern: the PNG, its capture@1 target block, the page that shows it."""

    png: str
    target_yaml: str
    html: str


def pattern_files(png_path: str | os.PathLike[str]) -> PatternFiles:
    """``pattern.png`` -> ``pattern.png``, ``pattern.target.yaml``, ``pattern.html`` (same folder)."""
    path = Path(png_path)
    if path.suffix.lower() != ".png":
        raise DatasetError(f"{path}: the pattern is written as PNG (lossless): give a name ending in .png")
    stem = path.with_suffix("")
    return PatternFiles(os.fspath(path), f"{stem}.target.yaml", f"{stem}.html")


def pattern_texts(screen: ScreenTarget, files: PatternFiles) -> dict[str, bytes | str]:
    """``{path: content}`` of the three files."""
    import cv2
    import yaml

    ok, png = cv2.imencode(".png", draw_pattern(screen))
    if not ok:  # pragma: no cover - OpenCV always encodes an 8-bit grey image
        raise DatasetError(f"{files.png}: OpenCV could not encode the pattern")
    p = screen.pattern
    header = (
        f"# {MARKER_LINE}: the capture@1 target of {os.path.basename(files.png)} ({screen.width_px} x "
        f"{screen.height_px} px, {screen.width_mm:g} x {screen.height_mm:g} mm)\n"
        "# paste under 'target:' in a capture@1, or: target: {kind: screen, ...} as below. Screen frame: origin at\n"
        "# the top-left corner of the active area, x right, y down, z into the screen, metres.\n"
        f"# {p['kind']} pattern in screen pixels (pixel-edge coordinates).\n"
    )
    body = yaml.safe_dump(screen.to_dict(), default_flow_style=None, sort_keys=False)
    return {files.png: png.tobytes(), files.target_yaml: header + body,
            files.html: html_page(screen, os.path.basename(files.png))}


def write_pattern(png_path: str | os.PathLike[str], screen_px: tuple[int, int], screen_mm: tuple[float, float] | None,
                  diagonal_in: float | None, kind: str = "charuco", square_mm: float | None = None,
                  ) -> tuple[ScreenTarget, PatternFiles]:
    """Design and write the pattern of a screen of ``screen_px`` pixels whose active area is ``screen_mm``
    (or, from ``diagonal_in`` inches and the aspect ratio, :func:`screen_mm_from_diagonal`): the PNG, its
    ``.target.yaml`` and ``.html`` (checked before any work, written all-or-nothing; the side files only
    over files this command wrote). DatasetError (one line) on impossible sizes."""
    from mirror_fg.io.output import OutputPlan

    width_px, height_px = screen_px
    _check_screen_px(width_px, height_px)  # before anything is allocated: an image of these pixels is drawn
    if screen_mm is None:
        if diagonal_in is None:
            raise DatasetError("pattern: give the screen's size in mm or its diagonal in inches")
        screen_mm = screen_mm_from_diagonal(width_px, height_px, diagonal_in)
        for what, mm in (("width", screen_mm[0]), ("height", screen_mm[1])):
            check_screen_mm(mm, f"pattern: --diagonal {diagonal_in:g} in gives the screen's {what}")
    files = pattern_files(png_path)
    plan = OutputPlan()
    plan.add(files.png, "pattern PNG")
    plan.add(files.target_yaml, "target YAML", marker=MARKER_LINE.encode())
    plan.add(files.html, "HTML page", marker=MARKER_LINE.encode())
    screen = design_pattern(width_px, height_px, screen_mm[0], screen_mm[1], kind, square_mm)
    plan.commit(pattern_texts(screen, files))
    return screen, files


def _check_screen_px(width_px: int, height_px: int) -> None:
    """Refuse a screen of no pixels or more than :data:`MAX_SCREEN_PX` a side (a typing mistake: drawing
    100000 x 100000 pixels would take 10 GB)."""
    if not (width_px >= 1 and height_px >= 1):
        raise DatasetError(f"pattern: the screen must have at least 1 x 1 pixels, got {width_px} x {height_px}")
    if width_px > MAX_SCREEN_PX or height_px > MAX_SCREEN_PX:
        raise DatasetError(f"pattern: --screen {width_px}x{height_px} is not a plausible screen (at most {MAX_SCREEN_PX} "
                           "pixels a side): give its native resolution, e.g. 1920x1080")


def pattern_summary(screen: ScreenTarget, files: PatternFiles) -> list[str]:
    """What ``mirror-fg pattern`` prints: the layout, the files, how to show it unscaled."""
    p = screen.pattern
    mm = screen.metres_per_px * 1000.0
    grid = f"{p['cols']} x {p['rows']} " + {"apriltag": "tags", "charuco": "squares", "chessboard": "inner corners"}[p["kind"]]
    square = p.get("square_px", p.get("spacing_px"))
    return [
        f"{p['kind']} pattern {screen.width_px} x {screen.height_px} px on {screen.width_mm:.1f} x {screen.height_mm:.1f} "
        f"mm ({mm[0]:.4f} x {mm[1]:.4f} mm per pixel): {grid}, {square:g} px = {square * mm[0]:.1f} mm, "
        f"{len(screen.target_points())} corners",
        f"wrote {files.png}, {files.target_yaml}, {files.html}",
        f"show it full screen without scaling: open {os.path.basename(files.html)} in a browser and press F11 (it "
        f"undoes OS display scaling), or `feh -F --zoom 100 {os.path.basename(files.png)}`; --screen must be the "
        "native resolution",
    ]


def html_page(screen: ScreenTarget, png_name: str) -> str:
    """A page that shows ``png_name`` at one image pixel per device pixel, whatever the OS display scaling
    (CSS size = pixels / devicePixelRatio), and says when the screen has other pixels than the pattern."""
    import html
    import json

    w, h = screen.width_px, screen.height_px
    src = html.escape(png_name, quote=True)
    return f"""<!DOCTYPE html>
<!-- {MARKER_LINE}: shows {src} at one image pixel per device pixel -->
<html><head><meta charset="utf-8"><title>mirror-fg pattern {w} x {h}</title>
<style>
html, body {{ margin: 0; padding: 0; background: #fff; overflow: hidden; }}
img {{ display: block; image-rendering: pixelated; image-rendering: crisp-edges; }}
#note {{ position: fixed; left: 50%; top: 50%; transform: translate(-50%, -50%); max-width: 36em; padding: 1em;
         font: 16px sans-serif; background: #fff; border: 3px solid #c00; }}
</style></head>
<body>
<img id="pattern" src="{src}" width="{w}" height="{h}" alt="calibration pattern">
<div id="note"></div>
<script>
const W = {json.dumps(w)}, H = {json.dumps(h)};
const img = document.getElementById("pattern"), note = document.getElementById("note");
function fit() {{
  const ratio = window.devicePixelRatio || 1;  // OS display scaling x browser zoom
  img.style.width = (W / ratio) + "px"; img.style.height = (H / ratio) + "px";
  const sw = Math.round(screen.width * ratio), sh = Math.round(screen.height * ratio);
  const lines = [];
  if (sw !== W || sh !== H)
    lines.push("This screen has " + sw + " x " + sh + " device pixels; the pattern was made for " + W + " x " + H +
               ". Make it again with --screen " + sw + "x" + sh + " (the native resolution), or the target file is wrong.");
  if (!document.fullscreenElement && (window.innerWidth * ratio < W - 1 || window.innerHeight * ratio < H - 1))
    lines.push("Click here or press F11 for full screen (display scaling " + Math.round(100 * ratio) + "%, compensated).");
  note.textContent = lines.join(" ");
  note.style.display = lines.length ? "block" : "none";
}}
note.onclick = () => document.documentElement.requestFullscreen && document.documentElement.requestFullscreen();
window.addEventListener("resize", fit);
fit();
</script>
</body></html>
"""
