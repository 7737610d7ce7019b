"""Targets of a capture@1: what is detected (chessboard, AprilTag/ArUco tags) or measured by hand (points).

``target`` (docs/formats.md, and :mod:`mirror_fg.io.capture` for the whole file):

* ``kind: chessboard`` with ``cols``, ``rows`` (inner corners) and ``square`` (metres). Inner corner
  (col, row) is fiducial ``C{row*cols+col:02d}`` at ``(col*square, row*square, 0)`` in the board
  frame. Corner C00: look at the printed face with the rows (``cols + 1`` squares each) horizontal
  and turn the board so that its top-left corner square is black; C00 is the inner corner of that
  square, C01, C02, ... run to the right along the top row, row 1 is the next row down. The board
  frame has x to the right, y down and z into the board. When ``cols + rows`` is odd (one count
  odd, the other even) the square colours tell the board's two half-turn orientations apart, and
  the detector enforces this order in every image (handedness from the number of mirrors, the half
  turn from the colour of the squares) or refuses the image with the reason.

  A *symmetric* board (``cols + rows`` even) looks the same turned half a turn, and a square one
  (``cols == rows``, even) also a quarter turn (an odd square board's colours still tell the quarter
  turns apart): no single image can tell which corner is C00. Each image is then labelled by
  consistency across the images (:mod:`mirror_fg.solver.screen.labelling`): the labelling, among the
  board's symmetric ones (:meth:`ChessboardTarget.symmetries`), under which every image fits one
  ``T_cam_base``. An image no labelling clearly fits better than another is left out with that
  reason. The images cannot tell the whole capture apart from its twin turned with the board (the
  same board, seen the same way), so one convention settles that: C00's row is the board's top row
  as it appears in most images (upright: the rows from C00's to the last run down the image), and
  ``T_base_target`` must put C00 at that physical corner. Hold or show a symmetric board upright.
* ``kind: apriltag`` (or ``aruco``) with ``dictionary`` (``tag36h11``, ``tag25h9``, ``tag16h5``,
  ``tag36h10`` or an OpenCV ArUco name such as ``DICT_4X4_50``), ``tag_size`` (metres, edge of the
  black square) and either ``tags: {id: {R, t}}``, each tag's frame in the base frame
  (``Bp = R @ p_tag + t``), or ``grid: {cols, rows, spacing, first_id}``: tag ``first_id +
  row*cols + col`` at ``(col*spacing, -row*spacing, 0)`` in the target frame, whose axes are those
  of every tag (``spacing`` is centre to centre, metres; tag ``first_id`` is top left). The tag
  frame is OpenCV's ArUco marker frame (origin at the centre of the black square, x right and y up
  on the printed face, z out of it). Fiducial ``T{id}_{k}`` is corner k in cv2.aruco's order, at
  ``(-s/2, s/2, 0)``, ``(s/2, s/2, 0)``, ``(s/2, -s/2, 0)``, ``(-s/2, -s/2, 0)`` in the tag frame.
  Tags not listed are ignored. Optional ``corner_refinement``: ``subpix`` (default: markers found
  by ``cv2.aruco``, corners refined by ``cv2.cornerSubPix``), ``contour``, ``apriltag`` or ``none``
  (OpenCV's own ``CORNER_REFINE_*``); optional ``image_gamma``: ``srgb`` (default; images encoded
  like a camera's JPEG/PNG, linearized before ``subpix`` refinement, which otherwise pulls corners
  about 0.5 px into the black square) or ``linear``.
* ``kind: charuco`` with ``cols``, ``rows`` (squares, both >= 2), ``square`` and ``marker`` (metres,
  edges of a chessboard square and of a marker's black square, ``marker < square``), ``dictionary``
  (an OpenCV ArUco name such as ``DICT_5X5_100``, or an AprilTag family) and optional
  ``legacy_pattern`` (``true`` for boards made by OpenCV before 4.6 whose row count is even).
  The board is OpenCV's ``cv2.aruco.CharucoBoard``: its top-left square is black, markers in the
  white squares. ChArUco corner ``id`` (OpenCV's numbering: row by row over the inner corners,
  ``id = row*(cols-1) + col``) is fiducial ``C{id:02d}`` at ``((col+1)*square, (row+1)*square, 0)``
  in the board frame (OpenCV's: origin at the board's top-left outer corner, x right along the top
  row, y down, z into the board). The marker ids tell every corner apart, so the names are the same
  in every image, whatever the view; an image shows any subset of them.
* ``kind: points`` with ``fiducials: {name: [x, y, z]}`` (metres, target frame); each image then
  gives its pixels under ``observations`` instead of detection.
* ``kind: screen``: a pattern shown full screen on a monitor (``mirror-fg pattern``); the base frame is
  the screen's (:mod:`mirror_fg.io.screen_target`).

A pose (a tag's, or ``T_base_target``) is ``{R: 3x3, t: [3]}`` or ``{q_xyzw: [4], t: [3]}``:
``Bp = R @ p + t``, metres. Pixels measured by hand (an image's ``observations``, required with a points
target) are ``{name: [u, v]}`` inline or a file: JSON/YAML of that shape, or text with one ``name u v``
or ``u v`` per line, the latter in the order of the target's fiducials (:func:`observations_from`).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.transform import quaternion_xyzw_to_rotation
from mirror_fg.core.values import (
    MAX_FEATURE_SIZE_M,
    check_extent,
    check_keys,
    check_size,
    finite,
    is_int,
    named_vectors,
    short,
    type_name,
    vector,
)
from mirror_fg.io.screen_target import screen_target_from_dict
from mirror_fg.io.target_kinds import (  # noqa: F401 (the kinds: public here too)
    ROTATION_TOL,
    CharucoTarget,
    ChessboardTarget,
    PointsTarget,
    Symmetry,
    TagTarget,
    Target,
    count_field,
    length_field,
    tag_dictionary,
    target_symmetries,
)

_CORNER_REFINEMENTS = ("subpix", "contour", "apriltag", "none")
_IMAGE_GAMMAS = ("srgb", "linear")

__all__ = [
    "ChessboardTarget",
    "Symmetry",
    "target_symmetries",
    "CharucoTarget",
    "TagTarget",
    "PointsTarget",
    "Target",
    "target_from_dict",
    "tag_dictionary",
    "pose_from_dict",
    "ROTATION_TOL",
]

def target_from_dict(t: Any, source: str) -> Target:
    """The ``target`` of a capture@1; DatasetError naming ``source`` on any problem, also on sizes in mm."""
    target, where = _target_from_dict(t, source), f"{source}: target"
    for key, noun in (("square", "square"), ("marker", "marker"), ("tag_size", "tag")):  # over 1 m, or 5 m across
        if hasattr(target, key):
            check_size(getattr(target, key), MAX_FEATURE_SIZE_M, where, key, f"{target.kind} {noun}")
    check_extent(target.target_points().values(), where, f"{target.kind} target")
    return target


def _target_from_dict(t: Any, source: str) -> Target:
    where = f"{source}: target"
    if not isinstance(t, Mapping):
        raise DatasetError(f"{where}: expected a mapping with 'kind', got {type_name(t)}")
    kind = t.get("kind")
    if kind == "chessboard":
        check_keys(t, ("kind", "cols", "rows", "square"), where)
        cols, rows = (count_field(t, key, 3, where, " (inner corners)") for key in ("cols", "rows"))
        square = length_field(t, "square", where)
        return ChessboardTarget(cols, rows, square)
    if kind == "charuco":
        return _charuco(t, where)
    if kind in ("apriltag", "aruco"):
        check_keys(t, ("kind", "dictionary", "tag_size", "tags", "grid", "corner_refinement", "image_gamma"), where)
        name, dict_id = tag_dictionary(t.get("dictionary"), f"{where}: dictionary")
        import cv2

        num_ids = int(cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0])
        size = length_field(t, "tag_size", where, "metres, edge of the black square")
        refine = t.get("corner_refinement", "subpix")
        if refine not in _CORNER_REFINEMENTS:
            raise DatasetError(f"{where}: corner_refinement must be one of {', '.join(_CORNER_REFINEMENTS)}, got {short(refine)}")
        gamma = t.get("image_gamma", "srgb")
        if gamma not in _IMAGE_GAMMAS:
            raise DatasetError(f"{where}: image_gamma must be one of {', '.join(_IMAGE_GAMMAS)}, got {short(gamma)}")
        if (t.get("tags") is None) == (t.get("grid") is None):
            raise DatasetError(f"{where}: give exactly one of 'tags' (each tag's pose) and 'grid'")
        if t.get("tags") is not None:
            tags_in = t["tags"]
            if not isinstance(tags_in, Mapping) or not tags_in:
                raise DatasetError(f"{where}: tags must be a non-empty mapping {{id: {{R, t}}}}, got {short(tags_in)}")
            tags: dict[int, tuple[np.ndarray, np.ndarray]] = {}
            for key, pose in tags_in.items():
                tag_id = _tag_id(key, num_ids, name, f"{where}: tags")
                if tag_id in tags:
                    raise DatasetError(f"{where}: tags: tag {tag_id} is listed twice")
                tags[tag_id] = pose_from_dict(pose, f"{where}: tags[{tag_id}]")
            frame = "base"
        else:
            tags = _grid(t["grid"], num_ids, name, f"{where}: grid")
            frame = "target"
        return TagTarget(name, dict_id, size, tags, frame=frame, corner_refinement=refine, image_gamma=gamma)
    if kind == "points":
        check_keys(t, ("kind", "fiducials"), where)
        fids = t.get("fiducials")
        if not isinstance(fids, Mapping) or not fids:
            raise DatasetError(f"{where}: fiducials must be a non-empty mapping {{name: [x, y, z]}} (metres)")
        out = named_vectors(fids, 3, where, "fiducial")
        if len(out) < 3:
            raise DatasetError(f"{where}: needs at least 3 fiducials, got {len(out)}")
        return PointsTarget(out)
    if kind == "screen":  # a pattern shown on a monitor: its own module
        return screen_target_from_dict(t, where)  # type: ignore[return-value]
    raise DatasetError(f"{where}: kind must be one of chessboard, charuco, apriltag, aruco, points, screen, got {short(kind)}")


def _charuco(t: Mapping[str, Any], where: str) -> CharucoTarget:
    check_keys(t, ("kind", "cols", "rows", "square", "marker", "dictionary", "legacy_pattern"), where)
    cols, rows = (count_field(t, key, 2, where, " (squares)") for key in ("cols", "rows"))
    square = length_field(t, "square", where)
    marker = finite(t.get("marker"))
    if marker is None or not 0 < marker < square:
        raise DatasetError(
            f"{where}: marker must be a number > 0 and below square (metres), got {short(t.get('marker'))}"
        )
    legacy = t.get("legacy_pattern", False)
    if not isinstance(legacy, bool):
        raise DatasetError(f"{where}: legacy_pattern must be true or false, got {short(legacy)}")
    name, dict_id = tag_dictionary(t.get("dictionary"), f"{where}: dictionary")
    import cv2

    num_ids = int(cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0])
    markers = cols * rows // 2
    if markers > num_ids:
        raise DatasetError(
            f"{where}: a {cols} x {rows} board has {markers} markers; dictionary {name} has only {num_ids}"
        )
    return CharucoTarget(cols, rows, square, marker, name, dict_id, legacy)


def _tag_id(key: Any, num_ids: int, dict_name: str, where: str) -> int:
    if isinstance(key, str) and key.strip().isdigit():
        key = int(key)
    if not is_int(key) or key < 0:
        raise DatasetError(f"{where}: tag id must be a non-negative integer, got {short(key)}")
    if key >= num_ids:
        raise DatasetError(f"{where}: tag id {key} is not in dictionary {dict_name} (ids 0-{num_ids - 1})")
    return int(key)


def _grid(g: Any, num_ids: int, dict_name: str, where: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    if not isinstance(g, Mapping):
        raise DatasetError(f"{where}: expected {{cols, rows, spacing, first_id}}, got {type_name(g)}")
    check_keys(g, ("cols", "rows", "spacing", "first_id"), where)
    cols, rows = (count_field(g, key, 1, where) for key in ("cols", "rows"))
    spacing = length_field(g, "spacing", where, "metres, centre to centre")
    first = g.get("first_id", 0)
    if not is_int(first) or first < 0:
        raise DatasetError(f"{where}: first_id must be a non-negative integer, got {short(first)}")
    last = first + cols * rows - 1
    if last >= num_ids:
        raise DatasetError(f"{where}: tag ids {first}-{last} are not all in dictionary {dict_name} (ids 0-{num_ids - 1})")
    return {
        first + r * cols + c: (np.eye(3), np.array([c * spacing, -r * spacing, 0.0]))
        for r in range(rows)
        for c in range(cols)
    }


def pose_from_dict(value: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` from ``{R: 3x3, t: [3]}`` or ``{q_xyzw: [4], t: [3]}``; R must be a rotation."""
    if not isinstance(value, Mapping):
        raise DatasetError(f"{where}: expected {{R: 3x3, t: [x, y, z]}}, got {type_name(value)}")
    check_keys(value, ("R", "t", "q_xyzw"), where)
    if "t" not in value:
        raise DatasetError(f"{where}: missing 't' (metres)")
    t = vector(value["t"], 3, f"{where}: t")
    if ("R" in value) == ("q_xyzw" in value):
        raise DatasetError(f"{where}: give exactly one of 'R' (3x3) and 'q_xyzw'")
    if "q_xyzw" in value:
        q = vector(value["q_xyzw"], 4, f"{where}: q_xyzw")
        n = float(np.linalg.norm(q))
        if abs(n - 1.0) > 1e-3:
            raise DatasetError(f"{where}: q_xyzw must be a unit quaternion, has norm {n:.6g}")
        return quaternion_xyzw_to_rotation(q), t
    rows = value["R"]
    if not isinstance(rows, (list, tuple)) or len(rows) != 3:
        raise DatasetError(f"{where}: R must be 3 rows of 3 numbers, got {short(rows)}")
    R = np.array([vector(r, 3, f"{where}: R row {i}") for i, r in enumerate(rows)])
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > ROTATION_TOL or np.linalg.det(R) < 0:
        raise DatasetError(f"{where}: R is not a rotation matrix (|R^T R - I| = {err:.2g}, det = {np.linalg.det(R):.4g})")
    u, _, vt = np.linalg.svd(R)
    return u @ vt, t
