"""What a calibration must satisfy before it is written (:func:`require_converged`); the
:class:`~mirror_fg.data.Calibration` value itself is :mod:`mirror_fg.data.calibration`'s.
"""
from __future__ import annotations

import numpy as np

from mirror_fg.core.errors import DatasetError, SolveError
from mirror_fg.data.calibration import POOR_FIT_RATIO, Calibration

__all__ = ["require_converged", "POOR_FIT_RATIO", "MAX_BASE_DISTANCE_M"]

#: A camera-to-base distance above this (metres) is refused: no robot is that large, the target's
#: sizes were most likely given in millimetres (docs/formats.md).
MAX_BASE_DISTANCE_M = 20.0


def require_converged(
    calibration: Calibration, source: str, solver: str = "Levenberg-Marquardt", accept_poor_fit: bool = False
) -> Calibration:
    """``calibration`` if it can be written: one rule for batch and incremental runs (``mirror-fg
    calibrate`` and ``calibrate-many``).

    SolveError when its solver did not converge, or when the fit is poor (:attr:`Calibration.fit_ratio`
    above :data:`POOR_FIT_RATIO`) unless ``accept_poor_fit``: the message names the likely cause (the
    images it found inconsistent, else wrong labels, pixel_sigma, distortion, a moved camera).
    DatasetError when ``T_cam_base`` puts the base more than :data:`MAX_BASE_DISTANCE_M` from the camera
    or a mirror or point is as far (sizes in millimetres where metres are expected); SolveError when an
    estimate or bound is NaN or infinite (``result_guard``).
    """
    from mirror_fg.solver.result.guard import check_finite, check_within_reach

    if not calibration.converged:
        raise SolveError(f"{source}: {solver} did not converge in {calibration.iterations} iterations "
                         "(stalled); the result was not written")
    check_finite(calibration, source)
    distance = float(np.linalg.norm(calibration.t_cam_base))
    if distance > MAX_BASE_DISTANCE_M:
        raise DatasetError(f"{source}: T_cam_base puts the base {distance:.3g} m from the camera: are the target's "
                           f"sizes in metres? (more than {MAX_BASE_DISTANCE_M:g} m is refused)")
    check_within_reach(calibration, source)
    ratio = calibration.fit_ratio
    if not accept_poor_fit and ratio > POOR_FIT_RATIO:
        cause = (calibration.inconsistency.message if calibration.inconsistency is not None else
                 "likely causes: wrong mirror_configs labels (two images given one placement), a pixel_sigma far "
                 "too small, unmodelled lens distortion, or a camera that moved")
        rms = float(np.sqrt(np.mean(calibration.residual_norms ** 2))) if len(calibration.residuals) else float("nan")
        raise SolveError(f"{source}: the fit is {ratio:.3g} times worse than the noise model allows (RMS "
                         f"{rms:.4g} {calibration.residual_units}; more than {POOR_FIT_RATIO:g}x is refused): {cause}; "
                         "the result was not written (--accept-poor-fit writes it anyway)")
    return calibration
