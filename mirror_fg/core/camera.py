"""The camera: OpenCV's pinhole model with distortion or its fisheye model, and the one check of a camera object.

:class:`Camera` turns pixels into normalized image coordinates and back: ``model`` ``"pinhole"``
(``cv2.undistortPoints`` / ``cv2.projectPoints``, ``dist`` = ``k1, k2, p1, p2[, k3, ...]``) or
``"fisheye"`` (OpenCV's equidistant fisheye model, Kalibr's ``equidistant``: ``cv2.fisheye.undistortPoints``
/ ``cv2.fisheye.distortPoints``, ``dist`` = ``k1, k2, k3, k4``); focal lengths and centre in pixels,
pixels in OpenCV's convention (the centre of the top-left pixel is (0, 0)). :func:`check_camera` is
the one validator of a camera object (the ``camera`` of dataset@1 and capture@1, and what the
camera-file readers of :mod:`mirror_fg.io.camera_files` extract), with one line naming the key on any problem;
:func:`camera_from_dict` / :func:`camera_to_dict` convert between it and :class:`Camera`.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import check_keys, check_name, finite, is_int, short, type_name

__all__ = [
    "Camera",
    "check_camera",
    "camera_from_dict",
    "camera_to_dict",
    "DIST_LENGTHS",
    "MODELS",
    "INTRINSIC_NAMES",
    "CAMERA_KEYS",
    "PIXEL_MARGIN_FRACTION",
    "initial_intrinsics",
]

#: Lengths of OpenCV distortion vectors ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]])``.
DIST_LENGTHS = (4, 5, 8, 12, 14)
#: Camera models: OpenCV's pinhole model with its distortion, and OpenCV's fisheye (equidistant) model.
MODELS = ("pinhole", "fisheye")
#: Length of a fisheye distortion vector ``(k1, k2, k3, k4)``: theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8).
FISHEYE_DIST_LENGTH = 4
#: Intrinsics that ``camera.estimate`` may name (OpenCV's pinhole model; p1, p2 are not fisheye terms), in
#: the order of the pixel factors' ``K(0)`` vector (``factors/intrinsics.py``), which holds the estimated ones.
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: Keys of a camera object (docs/formats.md); any other is refused with the key probably meant.
CAMERA_KEYS = ("model", "width", "height", "fx", "fy", "cx", "cy", "dist", "estimate", "prior_sigma")
#: Pixel observations may lie this fraction of the image size outside it (detections at the border).
PIXEL_MARGIN_FRACTION = 0.02
# cv2.undistortPoints stops after 5 fixed-point iterations by default (errors ~1e-5 on a wide-angle
# lens); iterate until the reprojection error is below 1e-12 px (at most 100 times) instead.
_UNDISTORT_CRITERIA = (100, 1e-12)  # (max iterations, epsilon in pixels)
# cv2.fisheye.undistortPoints's mark for a point it could not undistort, and the largest round-trip
# error (pixels) of a point it did undistort: above it the point is beyond the model's valid range.
_FISHEYE_FAILED = -1e5
_FISHEYE_ROUND_TRIP_PX = 1e-3


@dataclass(frozen=True)
class Camera:
    """OpenCV camera; focal lengths and centre in pixels.

    ``model``: ``"pinhole"`` with ``dist`` = OpenCV's ``(k1, k2, p1, p2[, k3, ...])``, or ``"fisheye"``
    (equidistant) with ``dist`` = ``(k1, k2, k3, k4)``. Last among the fields, so that positional
    construction of a pinhole camera is unchanged.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    #: Intrinsics to estimate through the mirrors (``camera.estimate``), and their prior sigmas.
    estimate: tuple[str, ...] = ()
    prior_sigma: tuple[tuple[str, float], ...] = ()
    model: str = "pinhole"

    def contains(self, pixels: np.ndarray) -> np.ndarray:
        """Whether each pixel (N, 2) lies in the image, extended by PIXEL_MARGIN_FRACTION of its size."""
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        margin = PIXEL_MARGIN_FRACTION * np.array([self.width, self.height])
        low, high = -0.5 - margin, np.array([self.width, self.height]) - 0.5 + margin
        return np.all((pixels >= low) & (pixels <= high), axis=1)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def normalize(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates (N, 2) of pixel coordinates (N, 2).

        ``cv2.undistortPoints`` (pinhole) or ``cv2.fisheye.undistortPoints`` (fisheye). A pixel the
        fisheye model cannot undistort (its ray would be at or beyond 90 degrees from the axis) gives NaN.
        """
        import cv2

        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if pixels.shape[0] == 0:
            return np.zeros((0, 2))
        dist = np.asarray(self.dist, dtype=np.float64)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, *_UNDISTORT_CRITERIA)
        if self.model == "fisheye":
            out = cv2.fisheye.undistortPoints(pixels, self.K, dist, criteria=criteria).reshape(-1, 2)
            # OpenCV marks a point whose iteration did not converge with -1e6 (4.x) or leaves it non-finite.
            failed = ~np.all(np.isfinite(out), axis=1) | np.all(out <= _FISHEYE_FAILED, axis=1)
            back = self.distort(np.where(failed[:, None], 0.0, out))
            failed |= np.linalg.norm(back - pixels.reshape(-1, 2), axis=1) > _FISHEYE_ROUND_TRIP_PX
            out[failed] = np.nan
            return out
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x spelling; 5.x takes criteria directly
            out = cv2.undistortPointsIter(pixels, self.K, dist, None, None, criteria)
        else:
            out = cv2.undistortPoints(pixels, self.K, dist, criteria=criteria)
        return out.reshape(-1, 2)

    def distort(self, normalized: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of normalized coordinates (N, 2) through the distortion.

        ``cv2.projectPoints`` (pinhole) or ``cv2.fisheye.distortPoints`` (fisheye, no skew).
        """
        import cv2

        normalized = np.asarray(normalized, dtype=np.float64).reshape(-1, 2)
        if normalized.shape[0] == 0:
            return np.zeros((0, 2))
        if self.model == "fisheye":
            dist = np.asarray(self.dist, dtype=np.float64)
            return np.asarray(cv2.fisheye.distortPoints(normalized.reshape(-1, 1, 2), self.K, dist)).reshape(-1, 2)
        rays = np.hstack([normalized, np.ones((len(normalized), 1))])
        pixels, _ = cv2.projectPoints(
            rays, np.zeros(3), np.zeros(3), self.K, np.asarray(self.dist, dtype=np.float64)
        )
        return pixels.reshape(-1, 2)


# --------------------------------------------------------------------------------------------------
# The camera object (dataset@1 and capture@1 ``camera``)
# --------------------------------------------------------------------------------------------------


def check_camera(
    camera: Mapping[str, Any], where: str, *, need_size: bool = True, max_pixels: int | None = None,
    allow_unstarted: bool = False,
) -> dict[str, Any]:
    """Check a camera object and return it as plain values; DatasetError (one line starting ``where``).

    Returns ``{"model", "width", "height", "fx", "fy", "cx", "cy", "dist"}`` (``model`` ``pinhole``
    when absent, or ``fisheye``; ints, floats in pixels; ``dist`` a list: OpenCV's ``k1, k2, p1, p2[,
    k3, ...]``, five zeros when absent, or with ``fisheye`` exactly ``k1, k2, k3, k4``, four zeros
    when absent), and
    ``estimate`` (list) and ``prior_sigma`` (dict) where given. ``need_size``: False where the image
    size may be missing (a calibration file without it; ``width`` and ``height`` are then None, both
    or neither). ``max_pixels``: refuse an image size above it (images will be decoded).
    ``allow_unstarted``: fx, fy, cx, cy may be absent where ``estimate`` names them (their value is
    then None: the caller starts them from the photographs, :func:`initial_intrinsics`).
    """
    if not isinstance(camera, Mapping):
        raise DatasetError(f"{where}: expected an object, got {type_name(camera)}")
    check_keys(camera, CAMERA_KEYS, where)
    estimate, prior_sigma = _estimated_intrinsics(camera, where)
    model = camera.get("model", "pinhole")
    if model not in MODELS:
        raise DatasetError(f"{where}: unsupported model {short(model)} ('pinhole' or 'fisheye')")
    if model == "fisheye" and {"p1", "p2"} & set(estimate):
        raise DatasetError(f"{where}: estimate: p1 and p2 are not terms of the fisheye model (k1..k4)")
    required = ("width", "height", "fx", "fy", "cx", "cy") if need_size else ("fx", "fy", "cx", "cy")
    missing = [k for k in required if camera.get(k) is None]  # absent or null (a checked camera's unstarted)
    unstarted = [k for k in missing if k in estimate and k in ("fx", "fy", "cx", "cy")]
    if unstarted and not allow_unstarted:
        raise DatasetError(f"{where}: {', '.join(unstarted)} absent: starting intrinsics from the photographs "
                           "is not possible here; give a starting value")
    without_prior = [k for k in unstarted if k in dict(prior_sigma)]
    if without_prior:
        raise DatasetError(f"{where}: prior_sigma {without_prior[0]}: a prior needs a given value, and "
                           f"{without_prior[0]} is absent")
    missing = [k for k in missing if k not in unstarted]
    if missing:
        raise DatasetError(f"{where}: missing {', '.join(repr(k) for k in missing)}")
    out: dict[str, Any] = {"model": model}
    if not need_size and (camera.get("width") is None) != (camera.get("height") is None):
        raise DatasetError(f"{where}: gives only one of the image width and height")
    for key in ("width", "height"):
        value = camera.get(key)
        if value is None and not need_size:
            out[key] = None
            continue
        if not is_int(value) or value < 1:
            raise DatasetError(f"{where}: {key} must be a positive integer (pixels), got {short(value)}")
        out[key] = int(value)
    if max_pixels is not None and out["width"] is not None and out["width"] * out["height"] > max_pixels:
        raise DatasetError(
            f"{where}: image size {short(out['width'])} x {short(out['height'])} is above the limit of "
            f"{max_pixels} pixels"
        )
    for key in ("fx", "fy", "cx", "cy"):
        if key in unstarted:
            out[key] = None  # started from the photographs by the caller
            continue
        value = finite(camera[key])
        if value is None:
            raise DatasetError(f"{where}: {key} must be a finite number (pixels), got {short(camera[key])}")
        if key in ("fx", "fy") and value <= 0:
            raise DatasetError(f"{where}: {key} must be > 0, got {short(camera[key])}")
        out[key] = value
    fisheye = model == "fisheye"
    dist = camera.get("dist", [0.0] * (FISHEYE_DIST_LENGTH if fisheye else 5))
    if isinstance(dist, np.ndarray):
        dist = dist.ravel().tolist()
    values = [finite(x) for x in dist] if isinstance(dist, (list, tuple)) else [None]
    if fisheye and (len(values) != FISHEYE_DIST_LENGTH or None in values):
        raise DatasetError(
            f"{where}: dist of a fisheye camera must be 4 finite numbers (k1, k2, k3, k4), got {short(dist)}"
        )
    if not fisheye and (len(values) not in DIST_LENGTHS or None in values):
        raise DatasetError(
            f"{where}: dist must be 4, 5, 8, 12 or 14 finite numbers (OpenCV k1, k2, p1, p2[, k3, ...]), "
            f"got {short(dist)}"
        )
    out["dist"] = values
    if estimate:
        out["estimate"] = list(estimate)
    if prior_sigma:
        out["prior_sigma"] = dict(prior_sigma)
    return out


def camera_from_dict(camera: Mapping[str, Any], where: str) -> Camera:
    """A :class:`Camera` from a camera object with its image size (:func:`check_camera`)."""
    c = check_camera(camera, where)
    return Camera(
        width=c["width"],
        height=c["height"],
        fx=c["fx"],
        fy=c["fy"],
        cx=c["cx"],
        cy=c["cy"],
        dist=tuple(c["dist"]),
        estimate=tuple(c.get("estimate", ())),
        prior_sigma=tuple(c.get("prior_sigma", {}).items()),
        model=c["model"],
    )


def camera_to_dict(c: Camera) -> dict[str, Any]:
    """The camera object of ``c`` (plain ints, floats and lists; ``estimate``/``prior_sigma`` where set)."""
    camera: dict[str, Any] = {
        "model": c.model,
        "width": int(c.width),
        "height": int(c.height),
        "fx": float(c.fx),
        "fy": float(c.fy),
        "cx": float(c.cx),
        "cy": float(c.cy),
        "dist": [float(x) for x in c.dist],
    }
    if c.estimate:
        camera["estimate"] = list(c.estimate)
    if c.prior_sigma:
        camera["prior_sigma"] = dict(c.prior_sigma)
    return camera


def _estimated_intrinsics(camera: Mapping[str, Any], where: str) -> tuple[tuple[str, ...], tuple[tuple[str, float], ...]]:
    """``camera.estimate`` (names of intrinsics) and ``camera.prior_sigma`` ({name: sigma > 0}), checked."""
    estimate = camera.get("estimate", [])
    if not isinstance(estimate, list) or not all(isinstance(n, str) for n in estimate):
        raise DatasetError(f"{where}: estimate must be a list of intrinsic names, got {short(estimate)}")
    for name in estimate:
        check_name(name, INTRINSIC_NAMES, f"{where}: estimate", "intrinsic")
    if len(set(estimate)) != len(estimate):
        raise DatasetError(f"{where}: estimate names an intrinsic twice: {short(estimate)}")
    prior = camera.get("prior_sigma", {})
    if not isinstance(prior, Mapping):
        raise DatasetError(f"{where}: prior_sigma must be an object {{name: sigma}}, got {type_name(prior)}")
    for name, sigma in prior.items():
        check_name(name, INTRINSIC_NAMES, f"{where}: prior_sigma", "intrinsic")
        if finite(sigma) is None or sigma <= 0:
            raise DatasetError(f"{where}: prior_sigma {name}: must be a finite number > 0, got {short(sigma)}")
    return tuple(estimate), tuple((str(n), float(s)) for n, s in prior.items())


#: Fiducials are coplanar when their third singular value is below this fraction of the first.
PLANAR_TOL = 1e-6
#: A photograph gives a plane-to-image homography with this many fiducials or more.
MIN_BOARD_POINTS = 4


def initial_intrinsics(
    width: int,
    height: int,
    fiducials: Mapping[str, np.ndarray],
    views: list[Mapping[str, np.ndarray]],
    mirrored: bool,
    given: Mapping[str, float | None],
    dist: tuple[float, ...],
    where: str,
    free_k1: bool = False,
) -> dict[str, float]:
    """Start values of fx, fy, cx, cy (pixels) from the photographs of a planar target.

    ``views``: per photograph, pixel observations by name; those of ``fiducials`` (base frame,
    metres) are a planar board seen in a (virtual) camera: ``cv2.initCameraMatrix2D`` then
    ``cv2.calibrateCamera`` with the distortion fixed at ``dist`` and the ``given`` values (None:
    absent) fixed where both of a pair are given. ``mirrored``: the photographs are seen through an odd
    number of mirrors, so the board is mirror-imaged: its second in-plane axis is negated, which makes
    the virtual view an ordinary (right-handed) one. (For a planar board this changes no intrinsic: a
    mirror image of a plane is the plane seen from behind, and Zhang's constraints are unchanged when
    a homography's second column changes sign; measured on the real photographs, identical starts.
    It keeps the per-view poses proper.) DatasetError (one line starting ``where``) when
    the fiducials are not coplanar or fewer than two photographs show 4 or more of them.
    ``free_k1``: let ``calibrateCamera`` fit k1 too (k1 is estimated later): on the five real
    photographs of shared/data/takahashi2012 (k1 about -0.24) this puts the start's cx 21 px from the
    final estimate instead of 445 px, and the joint LM then converges in a fraction of the iterations.
    Only fx, fy, cx, cy are returned: k1 starts at its given value.
    """
    import cv2

    names = list(fiducials)
    points = np.array([fiducials[n] for n in names], dtype=float).reshape(-1, 3)
    centre = points.mean(axis=0)
    _, singular, axes = np.linalg.svd(points - centre)
    if singular[2] > PLANAR_TOL * singular[0]:
        raise DatasetError(f"{where}: fx, fy, cx, cy absent: starting them from the photographs needs coplanar "
                           "fiducials (a board), and these are not coplanar; give starting values")
    plane = (points - centre) @ axes[:2].T  # (N, 2) in-plane coordinates, metres
    if mirrored:
        plane[:, 1] *= -1.0  # eq. (3): a reflection flips the board's handedness
    board = {n: np.array([plane[i, 0], plane[i, 1], 0.0], dtype=np.float32) for i, n in enumerate(names)}
    object_points, image_points = [], []
    for view in views:
        seen = [n for n in view if n in board]
        if len(seen) >= MIN_BOARD_POINTS:
            object_points.append(np.array([board[n] for n in seen], dtype=np.float32).reshape(-1, 1, 3))
            image_points.append(np.array([view[n] for n in seen], dtype=np.float32).reshape(-1, 1, 2))
    if len(object_points) < 2:
        raise DatasetError(f"{where}: fx, fy, cx, cy absent: starting them from the photographs needs at least 2 "
                           f"images with {MIN_BOARD_POINTS} or more fiducials each, got {len(object_points)}; "
                           "give starting values")
    size = (int(width), int(height))
    K = cv2.initCameraMatrix2D(object_points, image_points, size)
    for key, (row, col) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        if given.get(key) is not None:
            K[row, col] = float(given[key])  # type: ignore[arg-type]
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_TANGENT_DIST
             | (0 if free_k1 else cv2.CALIB_FIX_K1))
    if given.get("fx") is not None and given.get("fy") is not None:
        flags |= cv2.CALIB_FIX_FOCAL_LENGTH
    if given.get("cx") is not None and given.get("cy") is not None:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    coefficients = np.zeros((1, 5))
    coefficients[0, : min(5, len(dist))] = dist[:5]
    try:
        _, K, _, _, _ = cv2.calibrateCamera(object_points, image_points, size, K, coefficients, flags=flags)
    except cv2.error as error:
        raise DatasetError(f"{where}: fx, fy, cx, cy absent: cv2.calibrateCamera could not start them from the "
                           f"photographs ({str(error).strip().splitlines()[-1]}); give starting values") from None
    start = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}
    if not all(np.isfinite(v) for v in start.values()) or start["fx"] <= 0 or start["fy"] <= 0:
        raise DatasetError(f"{where}: fx, fy, cx, cy absent: the start from the photographs failed "
                           f"({', '.join(f'{k}={v:.4g}' for k, v in start.items())}); give starting values")
    return {k: (float(given[k]) if given.get(k) is not None else v) for k, v in start.items()}  # type: ignore[arg-type]
