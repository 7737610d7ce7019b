"""capture@1's robot fields (docs/formats.md, "Robot arms: joint states and mounts"): ``robot`` and
``mounts`` as in dataset@1 (checked when the detected dataset is), and ``joints: {file: joints.csv, max_dt}``,
a CSV (``io/joint_table.py``) with a header of joint names and an ``image`` column naming each image's file
(an image given by its pixels without a file: its ``id``) or a ``time`` column (seconds) matched to each
image's ``time`` within ``max_dt`` seconds (default 0.02; a video's frame ``k`` is at ``k / fps`` seconds
from its first frame); each detected image takes its row's joint values (radians, metres for a prismatic joint).
"""
from __future__ import annotations

import csv
import math
import os
from collections.abc import Mapping
from typing import Any

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import check_keys, short, type_name
from mirror_fg.io.joint_table import DEFAULT_MAX_DT, JointTable, parse_header, parse_row

__all__ = ["capture_robot_fields", "add_robot_fields", "read_joint_table", "video_fps"]


def capture_robot_fields(d: Mapping[str, Any], source: str, base_dir: str, read: bool = True) -> dict[str, Any] | None:
    """``{"robot", "mounts", "table", "rows": {image file name: {joint: value}}, "file", "path", "max_dt",
    "times"}`` of a capture, or None without ``robot``. The URDF path is made absolute (relative to the capture
    file). ``read=False``: the CSV is not read (a live session reads it as it grows; ``table`` None)."""
    robot, mounts, joints = d.get("robot"), d.get("mounts"), d.get("joints")
    if robot is None:
        for key, value in (("mounts", mounts), ("joints", joints)):
            if value is not None:
                raise DatasetError(f"{source}: {key} needs a robot (robot: {{urdf, base_link}})")
        return None
    if not isinstance(robot, Mapping):
        raise DatasetError(f"{source}: robot: expected an object {{urdf, base_link, joint_offsets}}, got {type_name(robot)}")
    robot = dict(robot)
    if isinstance(robot.get("urdf"), str) and not os.path.isabs(robot["urdf"]):
        robot["urdf"] = os.path.join(base_dir, robot["urdf"])
    if not isinstance(joints, Mapping):
        raise DatasetError(f"{source}: joints: expected {{file: joints.csv}} (the joint states of every image), "
                           f"got {short(joints) if joints is not None else 'nothing'}")
    check_keys(joints, ("file", "max_dt"), f"{source}: joints")
    name = joints.get("file")
    if not isinstance(name, str) or not name:
        raise DatasetError(f"{source}: joints.file must be a CSV file's name, got {short(name)}")
    max_dt = joints.get("max_dt", DEFAULT_MAX_DT)
    if isinstance(max_dt, bool) or not isinstance(max_dt, (int, float)) or not math.isfinite(max_dt) or max_dt <= 0:
        raise DatasetError(f"{source}: joints.max_dt must be a number of seconds > 0, got {short(max_dt)}")
    path = name if os.path.isabs(name) else os.path.join(base_dir, name)
    table = read_joint_table(path, name, source) if read else None
    return {"robot": robot, "mounts": mounts, "table": table, "rows": table.by_image if table else {}, "file": name,
            "path": path,
            "max_dt": float(max_dt), "times": _image_times(d.get("images"), source)}


def read_joint_table(path: str, name: str, source: str) -> JointTable:
    """The whole joint-state CSV at ``path`` (``name`` as the user wrote it in ``source``, for messages)."""
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            key, joints = parse_header(list(reader.fieldnames or []), name)
            table = JointTable(name, key, joints)
            for k, row in enumerate(reader, start=2):  # line numbers: the header is line 1
                table.add(*parse_row(row, key, joints, name, k), k)
    except OSError as error:
        raise DatasetError(f"{source}: joints.file {name}: {error.strerror or error}") from None
    return table


def _image_times(images: Any, source: str) -> list[float | None]:
    """Each listed image's ``time`` (seconds) by its position in ``images``, None where it gives none."""
    times: list[float | None] = []
    for index, entry in enumerate(images if isinstance(images, list) else []):
        t = entry.get("time") if isinstance(entry, Mapping) else None
        if t is not None and (isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t)):
            raise DatasetError(f"{source}: images[{index}]: time must be a number of seconds, got {short(t)}")
        times.append(None if t is None else float(t))
    return times


def add_robot_fields(data: dict[str, Any], capture) -> None:
    """Give the detected dataset@1 dictionary ``data`` the capture's robot, mounts and each image's joints:
    matched by the image file's name (an ``image`` column), or by its ``time`` (a ``time`` column; a video's
    frame ``k`` is at ``k / fps`` seconds from its first frame) within ``max_dt``. An image without its row,
    without a time, or between two equally near rows is refused by name."""
    fields = getattr(capture, "robot", None)
    if not fields:
        return
    table: JointTable = fields["table"]
    data["robot"] = fields["robot"]
    if fields["mounts"] is not None:
        data["mounts"] = fields["mounts"]
    if table.key == "time":
        times = _dataset_times(capture, fields["times"])
        for image in data["images"]:
            t = times.get(image["id"])
            if t is None:
                raise DatasetError(f"{capture.source}: image {image['id']!r}: no time (seconds) to match in "
                                   f"{fields['file']}'s time column: give the image a time, or the CSV an image column")
            try:
                image["joints"] = dict(table.nearest(t, fields["max_dt"], image["id"]))
            except DatasetError as error:
                raise DatasetError(f"{capture.source}: {error}") from None
        return
    if capture.images is None:
        raise DatasetError(f"{capture.source}: joints: {fields['file']} has an image column; a video's frames are "
                           "matched by a time column (seconds from the first frame)")
    files = {entry.id: os.path.basename(entry.file) for entry in capture.images if entry.file is not None}
    for image in data["images"]:
        name = files.get(image["id"], image["id"])
        if name not in fields["rows"]:
            raise DatasetError(f"{capture.source}: image {image['id']!r}: {fields['file']} has no row for {name!r}")
        image["joints"] = fields["rows"][name]


def _dataset_times(capture, listed: list[float | None]) -> dict[str, float]:
    """``{dataset image id: time (seconds)}``: a listed image's (and its views') ``time``; a video's frame
    ``k`` at ``k / fps``."""
    if capture.images is not None:
        out: dict[str, float] = {}
        for entry, t in zip(capture.images, listed):
            if t is None:
                continue
            out[entry.id] = t
            for view in entry.views or []:
                out[view.id] = t
        return out
    video = capture.video
    fps = video_fps(video.file, f"{capture.source}: video")
    return {f"{video.stem}:{k}": k / fps for s in video.segments for k in s.output_frames()}


def video_fps(path: str, where: str) -> float:
    """The frame rate a video's container reports (DatasetError where it reports none)."""
    import cv2

    from mirror_fg.io.fileio import open_video

    vc = open_video(path, where)
    try:
        fps = float(vc.get(cv2.CAP_PROP_FPS))
    finally:
        vc.release()
    if not math.isfinite(fps) or fps <= 0:
        raise DatasetError(f"{where}: the video reports no frame rate, so its frames have no time to match joint states")
    return fps
