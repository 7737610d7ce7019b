"""What a solved :class:`~mirror_fg.solver.result.calibration.Calibration` must satisfy before it is written:
every estimate and bound a finite number, and every mirror and point within reach of the camera.

Frames and units as docs/formats.md: mirror vectors in the frame of the camera that saw them (metres,
their length is the mirror's distance from that camera), points in the base frame (metres), mapped into
the first camera's frame by ``T_cam_base`` (``Cp = R Bp + t``).

Both rules catch answers that look like successes but are not: lengths typed in millimetres or
centimetres scale a target-free solution by 1000 or 100 (mirrors 100 m away, points a kilometre away,
residuals as good as with metres: the scale cannot be seen in the images), and a degenerate solve
leaves NaN in the covariance (every bound ``nan``).
"""
from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError

__all__ = ["check_finite", "check_within_reach", "MAX_SCENE_DISTANCE_M"]

#: A mirror or reconstruction point farther than this (metres) from the camera is refused: no
#: calibration set-up is that large (the same bound as the camera-to-base distance, ``calibration``'s
#: ``MAX_BASE_DISTANCE_M``), the lengths were most likely given in millimetres or centimetres.
MAX_SCENE_DISTANCE_M = 20.0


def _arrays(calibration: Any) -> Iterator[tuple[str, Any]]:
    """``(what, array or None)`` for every estimate and covariance a result carries."""
    yield "T_cam_base", calibration.R_cam_base
    yield "T_cam_base", calibration.t_cam_base
    yield "the covariance of T_cam_base", calibration.covariance
    for (l, m), v in calibration.mirror_vectors.items():
        yield f"mirror {l} placement {m}", v
    for (l, m), c in calibration.mirror_covariances.items():
        yield f"the bounds of mirror {l} placement {m}", c
    for name, p in calibration.points.items():
        yield f"point {name}", p
    for name, c in calibration.point_covariances.items():
        yield f"the bounds of point {name}", c
    if calibration.camera is not None:
        yield "the estimated intrinsics", np.asarray(calibration.camera.camera.K)
        yield "the bounds of the estimated intrinsics", calibration.camera.covariance
    for name, pose in (calibration.cameras or {}).items():
        yield f"camera {name}'s T_cam_base", pose.R_cam_base
        yield f"camera {name}'s T_cam_base", pose.t_cam_base
        yield f"the covariance of camera {name}'s T_cam_base", pose.covariance
    yield "the joint covariance of the cameras", calibration.camera_pose_covariance


def check_finite(calibration: Any, source: str) -> None:
    """SolveError (exit 3) naming the first estimate or bound that is NaN or infinite: the data did not
    determine it (a degenerate scale or geometry), and a ``nan`` bound is no answer."""
    for what, value in _arrays(calibration):
        if value is not None and not np.all(np.isfinite(np.asarray(value, dtype=float))):
            raise SolveError(f"{source}: the solve left {what} undetermined (NaN or infinite): the data do not fix "
                             "it (check the scale, the target's sizes and the views); the result was not written")
    if not np.isfinite(calibration.final_error):
        raise SolveError(f"{source}: the final cost is not a finite number; the result was not written")


def check_within_reach(calibration: Any, source: str) -> None:
    """DatasetError (exit 2) for a mirror or point more than :data:`MAX_SCENE_DISTANCE_M` from the camera:
    the lengths the user typed (a scale distance, target sizes, fiducials) were most likely not metres."""
    for (l, m), v in calibration.mirror_vectors.items():
        distance = float(np.linalg.norm(v))
        if distance > MAX_SCENE_DISTANCE_M:
            _refuse(source, f"mirror {l} placement {m}", distance)
    R, t = np.asarray(calibration.R_cam_base), np.asarray(calibration.t_cam_base)
    for name, p in calibration.points.items():
        distance = float(np.linalg.norm(R @ np.asarray(p) + t))
        if distance > MAX_SCENE_DISTANCE_M:
            _refuse(source, f"point {name}", distance)


def _refuse(source: str, what: str, distance: float) -> None:
    raise DatasetError(f"{source}: the solution puts {what} {distance:.3g} m from the camera: are the lengths "
                       "(scale distance, target sizes, fiducials) in metres, not millimetres or centimetres? "
                       f"(more than {MAX_SCENE_DISTANCE_M:g} m is refused; the result was not written)")
