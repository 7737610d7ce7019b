"""capture@1's robot fields (docs/formats.md, "Robot arms: joint states and mounts"): ``robot`` and
``mounts`` as in dataset@1 (checked when the detected dataset is), and ``joints: {file: joints.csv}``, a
CSV with a header of joint names and an ``image`` column naming each image's file (an image given by its
pixels without a file: its ``id``); each detected image takes its row's joint values (radians, metres for a prismatic joint).
"""
from __future__ import annotations

import csv
import math
import os
from collections.abc import Mapping
from typing import Any

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import check_keys, short, type_name

__all__ = ["capture_robot_fields", "add_robot_fields"]


def capture_robot_fields(d: Mapping[str, Any], source: str, base_dir: str) -> dict[str, Any] | None:
    """``{"robot", "mounts", "rows": {image file name: {joint: value}}, "file"}`` of a capture, or None
    without ``robot``. The URDF path is made absolute (relative to the capture file)."""
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
    check_keys(joints, ("file",), f"{source}: joints")
    name = joints.get("file")
    if not isinstance(name, str) or not name:
        raise DatasetError(f"{source}: joints.file must be a CSV file's name, got {short(name)}")
    path = name if os.path.isabs(name) else os.path.join(base_dir, name)
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            header = list(reader.fieldnames or [])
            table = list(reader)
    except OSError as error:
        raise DatasetError(f"{source}: joints.file {name}: {error.strerror or error}") from None
    if "image" not in header:
        where = "a time column is not supported yet: give an image column" if "time" in header else "no image column"
        raise DatasetError(f"{name}: {where} (the image file's name on each row)")
    rows: dict[str, dict[str, float]] = {}
    for k, row in enumerate(table, start=2):  # line numbers: the header is line 1
        image = (row.get("image") or "").strip()
        if not image:
            raise DatasetError(f"{name}: line {k}: empty image name")
        if image in rows:
            raise DatasetError(f"{name}: line {k}: image {image!r} has two rows")
        values: dict[str, float] = {}
        for joint in header:
            if joint == "image":
                continue
            text = row.get(joint)
            try:
                values[joint] = float(text)  # type: ignore[arg-type]
            except (TypeError, ValueError):
                raise DatasetError(f"{name}: line {k}: image {image!r}: joint {joint!r} is {short(text)}, not a number") from None
            if not math.isfinite(values[joint]):
                raise DatasetError(f"{name}: line {k}: image {image!r}: joint {joint!r} is {text} (not a finite number)")
        rows[image] = values
    return {"robot": robot, "mounts": mounts, "rows": rows, "file": name}


def add_robot_fields(data: dict[str, Any], capture) -> None:
    """Give the detected dataset@1 dictionary ``data`` the capture's robot, mounts and each image's joints
    (matched by the image file's name); a detected image without a row is refused by name."""
    fields = getattr(capture, "robot", None)
    if not fields:
        return
    if capture.images is None:
        raise DatasetError(f"{capture.source}: joints: a video's frames are not matched to joint states yet; "
                           "give the frames as images")
    files = {entry.id: os.path.basename(entry.file) for entry in capture.images if entry.file is not None}
    data["robot"] = fields["robot"]
    if fields["mounts"] is not None:
        data["mounts"] = fields["mounts"]
    for image in data["images"]:
        name = files.get(image["id"], image["id"])
        if name not in fields["rows"]:
            raise DatasetError(f"{capture.source}: image {image['id']!r}: {fields['file']} has no row for {name!r}")
        image["joints"] = fields["rows"][name]
