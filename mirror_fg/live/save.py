"""The files of a live session (``mirror-fg live``): its outputs checked before the first frame, the JSON
lines it streams, and the ``--save DIR`` folder written as the session goes (docs/formats.md, "Live sessions").

:func:`plan_live_outputs` checks every output against every input (the capture, the ``--source`` video
or folder, the files the capture names) and against each other (``-o`` and its ROS files,
``--json-lines``, the folder's ``capture.yaml`` and frames) before anything is written; each problem is
one line (DatasetError, exit 2).

:class:`SessionFolder` writes each frame the session uses as it is added (``frameNNNNNN.png``, grey),
then ``capture.yaml`` again, each file replaced whole (io.output.atomic_write). Until :meth:`finish`
the capture carries ``incomplete`` (a sentence saying so): a session ended by SIGKILL leaves a folder
that ``detect`` and ``calibrate`` refuse in one line rather than read half; ``finish`` (at the end, on
Ctrl-C, SIGTERM or SIGHUP) writes it without, a capture@1 that repeats the session offline.
"""
from __future__ import annotations

import os
import re
import stat
import sys
from dataclasses import dataclass, field
from typing import IO, Any

import cv2
import numpy as np

from mirror_fg.core.errors import DatasetError, OutputError
from mirror_fg.io.output import OutputPlan, atomic_write, same_file

__all__ = ["LiveOutputs", "SessionFolder", "plan_live_outputs", "SAVED_CAPTURE", "SAVED_JOINTS", "FRAME_NAME"]

#: The capture@1 a saved session writes in its folder.
SAVED_CAPTURE = "capture.yaml"
#: The joint states of a robot arm's saved frames (an ``image`` column naming each frame, then the joints).
SAVED_JOINTS = "joints.csv"
#: The name of a saved frame: the index of the frame in the source.
FRAME_NAME = re.compile(r"frame[0-9]{6,}\.png")
_HEADER = "# Written by mirror-fg live: the frames it used, one placement each.\n"


def _kind(path: str) -> str | None:
    """What exists at ``path``: "directory", "file", another kind in words, or None."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISDIR(mode):
        return "directory"
    if stat.S_ISREG(mode):
        return "file"
    return "character device" if stat.S_ISCHR(mode) else "special file"


def _inside(path: str, folder: str) -> bool:
    """Whether ``path`` is ``folder`` or lies under it (links resolved as far as they exist)."""
    real, top = os.path.realpath(path), os.path.realpath(folder)
    return real == top or real.startswith(top.rstrip(os.sep) + os.sep)


class SessionFolder:
    """``--save DIR``: the frames used, each written as it is added, and the capture@1 that repeats them."""

    def __init__(self, folder: str, capture_data: dict[str, Any], camera: dict[str, Any],
                 robot: dict[str, Any] | None = None):
        self.folder = folder
        self.capture = {key: value for key, value in capture_data.items() if key not in ("images", "video", "track")}
        self.camera = camera  # the session's camera dictionary (its size is known once the first frame is read)
        #: A robot arm's capture fields (``io.robot_capture.capture_robot_fields``: its URDF's absolute path):
        #: each frame's joint states are kept in ``joints.csv`` beside it, matched by the frame's file name.
        self.robot = robot
        self.joints: list[dict[str, float]] = []
        self.images: list[dict[str, Any]] = []
        self.written: list[str] = []
        self.finished = False

    @staticmethod
    def check(folder: str) -> None:
        """Refuse a ``--save`` that is not a new or empty folder (one line)."""
        kind = _kind(folder)
        if kind is None:
            parent = os.path.dirname(os.path.abspath(folder))
            while parent and not os.path.lexists(parent):
                parent = os.path.dirname(parent)
            if parent and not os.path.isdir(parent):
                raise DatasetError(f"--save {folder}: cannot make the folder: {parent} is a file, not a folder")
            return
        if kind != "directory":
            raise DatasetError(f"--save {folder}: is a {kind}, not a folder; give a new or empty folder")
        try:
            if os.listdir(folder):
                raise DatasetError(f"--save {folder}: the folder exists and is not empty (nothing is written over)")
        except OSError as error:
            raise DatasetError(f"--save {folder}: cannot read the folder: {error.strerror or error}") from None

    def add(self, frame: int, gray: np.ndarray, image: dict[str, Any] | None = None) -> None:
        """Write one used frame, then the capture naming every frame so far (still ``incomplete``). ``image``:
        the frame's ``mirror_configs`` (default: a placement of its own) and, of an arm, its ``joints``."""
        if not self.images:
            try:
                os.makedirs(self.folder, exist_ok=True)
            except OSError as error:
                raise OutputError(f"--save {self.folder}: cannot make the folder: {error.strerror or error}") from None
        name = f"frame{frame:06d}.png"
        encoded, png = cv2.imencode(".png", gray)
        if not encoded:
            raise OutputError(f"--save {self.folder}: cannot encode {name}")
        path = os.path.join(self.folder, name)
        atomic_write(path, png.tobytes())
        self.written.append(path)
        image = image or {}
        self.images.append({"file": name, "mirror_configs": list(image.get("mirror_configs", [len(self.images)]))})
        if self.robot is not None:
            self.joints.append(dict(image["joints"]))
        self._write_capture(incomplete=True)

    def finish(self) -> list[str]:
        """The capture without ``incomplete`` (nothing when no frame was used); the paths written."""
        if self.images and not self.finished:
            self._write_capture(incomplete=False)
            self.finished = True
            self.written.append(os.path.join(self.folder, SAVED_CAPTURE))
        return list(self.written)

    def _write_capture(self, incomplete: bool) -> None:
        import yaml

        data = dict(self.capture)
        if incomplete:  # docs/formats.md#live-sessions-mirror-fg-live: refused by every command until finished
            data = {"format": data.get("format"),
                    "incomplete": (f"written by a `mirror-fg live --save` session that has not finished (still running, "
                                   f"or killed): {len(self.images)} frame(s) so far; delete this line to use them"),
                    **data}
        data["camera"] = self.camera
        data["images"] = self.images
        if self.robot is not None:  # an arm: the frames' joint states, then the capture naming them
            self._write_joints()
            urdf = os.path.relpath(self.robot["robot"]["urdf"], os.path.abspath(self.folder))
            data["robot"] = {**data.get("robot", {}), "urdf": urdf}
            data["joints"] = {"file": SAVED_JOINTS}
        atomic_write(os.path.join(self.folder, SAVED_CAPTURE), _HEADER + yaml.safe_dump(data, sort_keys=False))

    def _write_joints(self) -> None:
        """``joints.csv``: an ``image`` column (each saved frame's file name) and the joints, every value as
        Python writes it exactly (``repr``), so that the folder calibrates again to the same answer."""
        import csv
        import io

        names = list(self.joints[0])
        text = io.StringIO()
        rows = csv.writer(text, lineterminator="\n")
        rows.writerow(["image", *names])
        for image, joints in zip(self.images, self.joints):
            rows.writerow([image["file"], *(repr(float(joints[n])) for n in names)])
        atomic_write(os.path.join(self.folder, SAVED_JOINTS), text.getvalue().encode("utf-8"))


@dataclass
class LiveOutputs:
    """The checked outputs of one session: the result's (``calibration``, or None), the JSON lines, the folder."""

    calibration: Any = None  # io.calibration_files.CalibrationOutputs
    json_lines: str | None = None
    save: str | None = None
    stream: IO[str] | None = field(default=None, repr=False)

    def open_lines(self) -> None:
        """Open the JSON lines (replacing the file) once every check has passed."""
        if self.json_lines is None:
            return
        if self.json_lines == "-":
            self.stream = sys.stdout
            return
        try:
            self.stream = open(self.json_lines, "w", encoding="utf-8")
        except OSError as error:
            raise OutputError(f"--json-lines {self.json_lines}: cannot write: {error.strerror or error}") from None

    def write_line(self, text: str) -> None:
        assert self.stream is not None
        try:
            self.stream.write(text + "\n")
            self.stream.flush()
        except OSError as error:
            raise OutputError(f"--json-lines {self.json_lines}: cannot write: {error.strerror or error}") from None

    def close_lines(self) -> None:
        if self.stream is not None and self.stream is not sys.stdout:
            try:
                self.stream.close()
            except OSError:
                pass  # its write already failed and said so
            self.stream = None


def plan_live_outputs(capture: str, source: str, inputs: list[str], output: str | None, json_lines: str | None,
                      save: str | None, ros: bool = True) -> LiveOutputs:
    """Check every output of ``live`` against every input (``capture``, the ``source`` video or folder and
    ``inputs``, the files the capture names) and each other, before anything is written."""
    from mirror_fg.io.calibration_files import plan_calibration_outputs

    files = [capture, *inputs]
    source_kind = _kind(source)
    if source_kind == "file":
        files.append(source)
    outputs = LiveOutputs(json_lines=json_lines, save=save)
    if output is not None:
        outputs.calibration = plan_calibration_outputs(files, output, ros=ros)
        plan = outputs.calibration.plan
    else:
        plan = OutputPlan(inputs=files)
    if json_lines is not None and json_lines != "-":
        plan.add(json_lines, "JSON lines")  # never an input, the result or its ROS files
    if save is not None:
        SessionFolder.check(save)
        if source_kind == "directory" and same_file(source, save):
            raise DatasetError(f"--save {save}: is the --source folder; the saved frames would be read as new ones")
        for path, role in plan.outputs.items():
            if _inside(save, path) and not same_file(save, path):
                raise DatasetError(f"--save {save}: lies under the {role} {path}")
            if same_file(path, save) or (_inside(path, save) and (os.path.basename(path) in (SAVED_CAPTURE, SAVED_JOINTS)
                                                                   or FRAME_NAME.fullmatch(os.path.basename(path)))):
                raise DatasetError(f"{path}: the {role} would be written over by --save {save} (its "
                                   f"{SAVED_CAPTURE}, {SAVED_JOINTS} and frameNNNNNN.png); choose another name")
        for path in files:
            if _inside(path, save):
                raise DatasetError(f"--save {save}: holds the input {path}; give a new or empty folder")
    if json_lines is not None and json_lines != "-" and _kind(json_lines) is None:
        parent = os.path.dirname(json_lines)
        if not os.path.isdir(parent or "."):  # streamed from the first frame: its folder must exist
            raise DatasetError(f"--json-lines {json_lines}: no such folder {parent}")
    return outputs
