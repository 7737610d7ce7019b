"""A capture@1 with several screens, and its result (docs/formats.md, "The answer in the user's units":
several screens).

``screens: {name: screen target}`` instead of ``target`` (each as ``mirror-fg pattern`` writes it), and
every image names its screen: ``{file, mirror_configs, screen: name}``. A photograph that shows two
screens in one mirror is listed once per screen, with the same ``mirror_configs``: the same placement.
One camera (``camera``, not ``cameras``); no ``T_base_target``, ``video`` or ``track``.

:func:`split_screens_capture` turns it into one ordinary capture@1 per screen (each detected as a screen
capture is); :func:`screens_result` writes result@1 with the first screen's pose at the top level (its
``screen`` block too, so single-screen readers keep working) and, in one graph
(:mod:`mirror_fg.solver.batch.screens`):

* ``screens: {name: {...the screen block..., "T_cam_screen": {R, t, q_xyzw}, "covariance": [[6 x 6]],
  "sigma3": {rotation_deg, position_mm}}}`` (each screen's pose, camera <- screen, metres, the joint
  estimate's marginal in the uncertainty convention, camera axes);
* ``screen_pairs: [{"from", "to", "T": {R, t, q_xyzw}, "covariance", "sigma3"}]``: each screen after the
  first relative to the one before it; ``T`` maps points of screen ``from`` into screen ``to``'s frame
  (``x_to = R x_from + t``), its covariance ``[dtheta, dt]`` about ``to``'s axes;
* ``screens_joint_covariance``: the (6S, 6S) covariance of every ``T_cam_screen``, in ``screens`` order.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import short, type_name
from mirror_fg.io.result_poses import sigma3_pose, transform_entry
from mirror_fg.io.screen_target import ScreenTarget, screen_target_from_dict

__all__ = ["is_screens_capture", "split_screens_capture", "screens_result"]

_REFUSED_WITH_SCREENS = {
    "target": "give either target or screens",
    "cameras": "several screens are calibrated with one camera: give camera",
    "T_base_target": "each screen's frame is its own (origin at the top-left corner of its active area)",
    "video": "give images, each naming its screen",
    "track": "several screens follow no points",
}


def is_screens_capture(data: Any) -> bool:
    """The parsed file is a capture@1 with ``screens``."""
    return isinstance(data, Mapping) and data.get("format") == "mirror-fg/capture@1" and "screens" in data


def split_screens_capture(data: Mapping[str, Any], source: str) -> tuple[dict[str, ScreenTarget], dict[str, dict[str, Any]]]:
    """``(targets, captures)``: each screen's target and its own capture@1 dictionary (the images that name
    it, without ``screen``), in the order of ``screens``. DatasetError (one line naming the key or image)."""
    for key, why in _REFUSED_WITH_SCREENS.items():
        if key in data:
            raise DatasetError(f"{source}: {key}: not with screens ({why})")
    screens = data["screens"]
    if not isinstance(screens, Mapping) or len(screens) < 2:
        raise DatasetError(f"{source}: screens: expected a mapping of two or more {{name: screen target}} "
                           f"(one screen is target: {{kind: screen, ...}}), got {short(screens)}")
    targets: dict[str, ScreenTarget] = {}
    for name, block in screens.items():
        where = f"{source}: screens: {name}"
        if not isinstance(name, str) or not name or "/" in name:
            raise DatasetError(f"{source}: screens: a screen's name must be a non-empty string without '/', got {short(name)}")
        if not isinstance(block, Mapping) or block.get("kind") != "screen":
            raise DatasetError(f"{where}: expected a screen target {{kind: screen, width_px, ...}} (as mirror-fg pattern "
                               f"writes it), got {short(block)}")
        targets[name] = screen_target_from_dict(block, where)
    images = data.get("images")
    if not isinstance(images, list) or not images:
        raise DatasetError(f"{source}: images must be a non-empty list of {{file, mirror_configs, screen}}")
    per_screen: dict[str, list[Any]] = {name: [] for name in targets}
    for index, entry in enumerate(images):
        where = f"{source}: images[{index}]"
        if not isinstance(entry, Mapping):
            raise DatasetError(f"{where}: expected {{file, mirror_configs, screen}}, got {type_name(entry)}")
        name = entry.get("screen")
        if name not in targets:
            raise DatasetError(f"{where}: screen must name one of the screens ({', '.join(targets)}), got {short(name)}")
        per_screen[name].append({k: v for k, v in entry.items() if k != "screen"})
    for name, entries in per_screen.items():
        if not entries:
            raise DatasetError(f"{source}: screens: {name}: no image names it")
    common = {k: v for k, v in data.items() if k not in ("screens", "images")}
    captures = {name: {**common, "target": targets[name].to_dict(), "images": per_screen[name]} for name in targets}
    return targets, captures


def screens_result(calibration: Any, targets: Mapping[str, ScreenTarget], viewing_distance_m: float) -> dict[str, Any]:
    """result@1 of a :class:`~mirror_fg.solver.batch.screens.ScreensCalibration` (module docstring)."""
    from mirror_fg.core.gaze_error import gaze_block
    from mirror_fg.io.screen_result import screen_of

    result = calibration.first_calibration().to_dict()
    blocks = {}
    for name in calibration.names:
        T, covariance = calibration.poses[name], calibration.covariance(name)
        pose = {"T_cam_base": {"R": T.R.tolist(), "t": T.t.tolist()}, "covariance_cam_base": covariance.tolist()}
        screen = screen_of(targets[name], pose)
        blocks[name] = {**screen.to_dict(), **gaze_block(screen, viewing_distance_m),
                        "T_cam_screen": transform_entry(T.R, T.t), "covariance": covariance.tolist(),
                        "sigma3": sigma3_pose(covariance)}
    first = calibration.names[0]
    result["screen"] = {k: v for k, v in blocks[first].items() if k not in ("T_cam_screen", "covariance", "sigma3")}
    result["screens"] = blocks
    pairs = []
    for before, name in zip(calibration.names, calibration.names[1:]):
        T, covariance = calibration.relative(name, before)
        pairs.append({"from": before, "to": name, "T": transform_entry(T.R, T.t), "covariance": covariance.tolist(),
                      "sigma3": sigma3_pose(covariance)})
    result["screen_pairs"] = pairs
    result["screens_joint_covariance"] = np.asarray(calibration.joint_covariance).tolist()
    return result
