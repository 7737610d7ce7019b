"""The files of one calibration: the result@1 file and its ROS side files (and, for several cameras, the
Kalibr camchain and its standard deviations), planned and written together.

:func:`plan_calibration_outputs` checks every path before any work (io.output.OutputPlan: never over
an input, side files only over files mirror-fg wrote, no side files beside a device);
:func:`write_calibration_outputs` writes them all-or-nothing. Used by ``mirror-fg calibrate`` and by
``analysis.many`` (one calibration per input).
"""
from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.gaze_error import DEFAULT_VIEWING_DISTANCE_M
from mirror_fg.io.camchain import camchain_paths, camchain_texts
from mirror_fg.io.fileio import load_structured
from mirror_fg.io.output import OutputPlan, file_head, same_file
from mirror_fg.io.result import RESULT_FORMAT, estimated_camera, result_text
from mirror_fg.io.screen_result import screen_block, screen_xml_path, screen_xml_text
from mirror_fg.io.ros import (
    DEFAULT_BASE_FRAME,
    DEFAULT_CAMERA_FRAME,
    check_camera_frame_name,
    check_frame_name,
    camera_info_path,
    rig_camera_info_path,
    camera_info_text,
    ros_output_paths,
    ros_output_texts,
)

__all__ = ["CalibrationOutputs", "plan_calibration_outputs", "base_is_camera"]

#: What the side files mirror-fg writes carry in their first lines (so a stranger's file is never replaced).
SIDE_FILE_MARKER = b"mirror-fg"


def base_is_camera(result: Mapping[str, Any]) -> bool:
    """Whether the result is of data without a known target (``fiducials: {}``, docs/formats.md): the base
    frame is then the (first) camera's own frame, its ``T_cam_base`` exactly the identity with an exactly
    zero covariance (not estimated), so there is no camera-to-base calibration to publish for it."""
    cov, T = result.get("covariance_cam_base"), result["T_cam_base"]
    return bool(cov is not None and not np.any(np.asarray(cov, dtype=float))
                and np.array_equal(np.asarray(T["R"], dtype=float), np.eye(3))
                and not np.any(np.asarray(T["t"], dtype=float)))


class CalibrationOutputs:
    """A checked plan for ``result_path`` and (``ros``) its side files; :meth:`write` commits them."""

    def __init__(self, plan: OutputPlan, result_path: str, ros: bool, base_frame: str, camera_frame: str,
                 side_files: bool = True):
        self.plan, self.result_path, self.ros, self.side_files = plan, result_path, ros, side_files
        self.base_frame, self.camera_frame = base_frame, camera_frame
        self.camera_info: Path | None = None
        self.screen: Any = None  # the ScreenTarget of a screen capture: the result gets its screen block
        self.screen_xml: str | None = None
        self.viewing_distance_m = DEFAULT_VIEWING_DISTANCE_M  # the eye of the screen block's gaze error
        self.camchain: tuple[str, str] | None = None
        #: What :meth:`write` left out or removed, one line each for the user.
        self.notes: list[str] = []
        #: Side files an earlier run may have written under this name (:func:`_earlier_side_files`).
        self.earlier_side_files: list[Path] = []

    def expect_cameras(self) -> None:
        """The dataset has several cameras: plan (check now, before the solve) ``<stem>.camchain.yaml`` and
        ``<stem>.camchain-sigma.yaml`` (:mod:`mirror_fg.io.camchain`), written with the result. Without this
        call, :meth:`write` plans them when the result has ``cameras`` (checked then, still before any write)."""
        if self.side_files and self.camchain is None:
            chain, sigma = camchain_paths(self.result_path)
            self.camchain = (self.plan.add(chain, "Kalibr camchain", marker=SIDE_FILE_MARKER),
                             self.plan.add(sigma, "camchain standard deviations", marker=SIDE_FILE_MARKER))

    def expect_camera(self) -> None:
        """The intrinsics will be estimated: plan (check now, before the solve) ``<stem>.camera_info.yaml``,
        the estimated camera as a ROS ``camera_info`` file, written beside the ROS outputs."""
        if self.ros and self.camera_info is None:
            self.camera_info = Path(self.plan.add(camera_info_path(self.result_path), "camera_info YAML",
                                                  marker=SIDE_FILE_MARKER))

    def use_capture(self, capture: Any) -> None:
        """The input is this capture@1: a screen target's result gets its ``screen`` block, and (planned
        now, before detection) ``<stem>.screen.xml`` beside it (:mod:`mirror_fg.io.screen_result`)."""
        if capture.target.kind != "screen":
            return
        self.screen = capture.target
        if self.screen_xml is None and not self.plan.is_device(self.result_path):
            self.screen_xml = self.plan.add(screen_xml_path(self.result_path), "screen XML", marker=SIDE_FILE_MARKER)

    def write(self, result: Mapping[str, Any]) -> list[Path]:
        """Write the result@1 dictionary and its ROS outputs, all-or-nothing; the paths written. The result
        of a screen capture is written with its ``screen`` block, and ``<stem>.screen.xml`` beside it; a result
        with ``cameras`` (each with its intrinsics) gets the Kalibr camchain and its standard deviations."""
        texts = {}
        if self.screen is not None:
            result = {**result, "screen": screen_block(self.screen, result, self.viewing_distance_m)}
            if self.screen_xml is not None:
                texts[self.screen_xml] = screen_xml_text(result)
        texts = {self.result_path: result_text(result, self.result_path), **texts}
        if self.side_files and result.get("cameras") and all(e.get("camera") for e in result["cameras"].values()):
            self.expect_cameras()
            texts.update(camchain_texts(result, self.result_path))
        if self.ros and base_is_camera(result) and len(result.get("cameras") or {}) < 2:
            self.notes.append("note: no ROS/URDF files: without a known target the base frame is the camera's own "
                              "frame, so there is no camera-to-base transform to publish (the identity is no calibration)")
        elif self.ros:
            texts.update(ros_output_texts(result, self.result_path, self.base_frame, self.camera_frame))
            if base_is_camera(result):  # a rig without a known target: the others are relative to the first
                first = next(iter(result["cameras"]))
                self.notes.append(f"note: without a known target the base frame is camera {first}'s own frame: its "
                                  "entries in the ROS/URDF files are the identity by definition (no calibration); the "
                                  "other cameras' are their poses relative to it")
            for name, entry in (result.get("cameras") or {}).items():  # each rig camera that estimated
                block = entry.get("camera") or {}
                if block.get("estimated"):
                    path = self.plan.add(rig_camera_info_path(self.result_path, name), f"camera_info YAML of {name}",
                                         marker=SIDE_FILE_MARKER)
                    texts[path] = camera_info_text(estimated_camera({"camera": block}, os.fspath(self.result_path)),
                                                   f"{name}_optical_frame", block.get("sigma3"))
            camera = result.get("camera")
            if camera is not None and self.camera_info is not None and not result.get("cameras"):
                texts[os.fspath(self.camera_info)] = camera_info_text(
                    estimated_camera(result, os.fspath(self.result_path)), self.camera_frame, camera.get("sigma3"))
        written = self.plan.commit(texts)
        if self.side_files:
            self._remove_stale(texts)
        return written

    def _remove_stale(self, texts: Mapping[str, Any]) -> None:
        """Remove the side files an earlier mirror-fg run wrote under this result's name that this run did not
        write (they would contradict the new result: a rig's camchain beside a one-camera result, the
        camera_info of intrinsics no longer estimated); a file there that mirror-fg did not write is left, with
        a warning naming it. Inputs of this run are never touched."""
        written = {os.path.realpath(p) for p in texts}
        for path in dict.fromkeys(os.fspath(p) for p in self.earlier_side_files):
            if os.path.realpath(path) in written or not os.path.lexists(path):
                continue
            if any(same_file(path, source) for source in self.plan.inputs):
                continue
            if os.path.islink(path) or not os.path.isfile(path) or SIDE_FILE_MARKER not in file_head(path):
                self.notes.append(f"warning: {path} is not from this run (it was not written by mirror-fg, or is not "
                                  "a regular file): left as it is; it does not belong to the new result")
                continue
            try:
                os.remove(path)
            except OSError as error:
                self.notes.append(f"warning: {path} is from an earlier run under this name and contradicts the new "
                                  f"result, but could not be removed: {error.strerror or error}")
                continue
            self.notes.append(f"removed {path}: an earlier run's side file under this name that the new result "
                              "does not have")


def _earlier_side_files(result_path: str) -> list[Path]:
    """The side files a mirror-fg run may have written beside ``result_path``: the fixed names (ROS YAML,
    URDF, camera_info, camchain and its standard deviations, screen XML) and, where the result there now
    names its cameras, each rig camera's camera_info (read before this run replaces the result)."""
    paths = [*ros_output_paths(result_path), camera_info_path(result_path), *camchain_paths(result_path),
             Path(screen_xml_path(result_path))]
    if os.path.isfile(result_path) and os.path.getsize(result_path) <= _EARLIER_RESULT_BYTES:
        try:
            earlier = load_structured(result_path)
        except DatasetError:
            earlier = None
        cameras = earlier.get("cameras") if isinstance(earlier, Mapping) and earlier.get("format") == RESULT_FORMAT else None
        if isinstance(cameras, Mapping):
            for name in cameras:
                if isinstance(name, str) and name:
                    paths.append(rig_camera_info_path(result_path, name))
    return paths


#: An earlier result larger than this is not read for its cameras' names (a result of a rig is kilobytes).
_EARLIER_RESULT_BYTES = 64 * 1024 * 1024


def plan_calibration_outputs(
    inputs: Iterable[str | os.PathLike[str]],
    result_path: str | os.PathLike[str],
    *,
    ros: bool = True,
    base_frame: str = DEFAULT_BASE_FRAME,
    camera_frame: str = DEFAULT_CAMERA_FRAME,
) -> CalibrationOutputs:
    """Check the outputs of a calibration before any work; DatasetError (one line) if one must not be
    written. A result that goes to a character device (``/dev/null``) gets no side files."""
    plan = OutputPlan(inputs=[os.fspath(p) for p in inputs])
    target = plan.add(result_path, "result")
    ros = ros and not plan.is_device(target)
    if ros:
        try:
            check_frame_name(base_frame, "--base-frame")
            check_camera_frame_name(camera_frame, "--camera-frame")
        except ValueError as error:
            raise DatasetError(str(error)) from None
        yaml_path, urdf_path = ros_output_paths(target)
        plan.add(yaml_path, "ROS YAML", marker=SIDE_FILE_MARKER)
        plan.add(urdf_path, "URDF", marker=SIDE_FILE_MARKER)
    outputs = CalibrationOutputs(plan, target, ros, base_frame, camera_frame, side_files=not plan.is_device(target))
    if outputs.side_files:
        outputs.earlier_side_files = _earlier_side_files(target)
    return outputs
