"""The files of one calibration: the result@1 file and its ROS side files (and, for several cameras, the
Kalibr camchain and its standard deviations), planned and written together.

:func:`plan_calibration_outputs` checks every path before any work (io.output.OutputPlan: never over
an input, side files only over files mirror-fg wrote, no side files beside a device);
:func:`write_calibration_outputs` writes them all-or-nothing. Used by ``mirror-fg calibrate`` and by
``tools.many`` (one calibration per input).
"""
from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.gaze_error import DEFAULT_VIEWING_DISTANCE_M
from mirror_fg.io.camchain import camchain_paths, camchain_texts
from mirror_fg.io.output import OutputPlan
from mirror_fg.io.result import estimated_camera, result_text
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

__all__ = ["CalibrationOutputs", "plan_calibration_outputs"]

#: What the side files mirror-fg writes carry in their first lines (so a stranger's file is never replaced).
SIDE_FILE_MARKER = b"mirror-fg"


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
        if self.ros:
            texts.update(ros_output_texts(result, self.result_path, self.base_frame, self.camera_frame))
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
        return self.plan.commit(texts)


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
    return CalibrationOutputs(plan, target, ros, base_frame, camera_frame, side_files=not plan.is_device(target))
