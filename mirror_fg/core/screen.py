"""A calibrated screen in the camera frame: what gaze code needs (pixel <-> 3-D point, gaze ray -> pixel).

Frames (docs/formats.md, "Screens"): the screen frame {S} has its origin at the top-left corner of the
active area, x to the right along the pixel rows, y down, z into the screen, metres. Pixel (i, j) covers
[i, i + 1) x [j, j + 1) of the pixel-edge coordinates ``e = (e_u, e_v)``, which lie at
``s = (e_u * mx, e_v * my, 0)`` with ``mx = width_mm / width_px / 1000`` (metres per pixel), likewise
``my``; the centre of pixel (i, j) is ``e = (i + 0.5, j + 0.5)``. ``T_cam_screen = (R, t)`` is the
result's ``T_cam_base``: ``Cp = R s + t``.

Uncertainty: first-order propagation of the pose covariance ``P`` (6 x 6, ``[dtheta, dt]`` with
``R_true = Exp(dtheta) R``, ``t_true = t + dt``, camera axes: the docs/formats.md convention). A point on the
screen moves by ``dp = -[R s]x dtheta + dt``; a ray's hit by the Jacobian in :meth:`Screen.pixel_of_ray`.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mirror_fg.core.transform import Transform

__all__ = ["Screen", "ScreenHit"]


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass(frozen=True)
class ScreenHit:
    """Where a ray meets the screen: ``pixel`` (2,) pixel-edge coordinates (the pixel is ``floor(pixel)``),
    ``covariance_px`` (2, 2) or None, ``point_cam`` (3,) metres, ``distance`` along the ray (units of its
    direction: metres for a unit direction)."""

    pixel: np.ndarray
    covariance_px: np.ndarray | None
    point_cam: np.ndarray
    distance: float

    @property
    def sigma3_px(self) -> np.ndarray | None:
        """3-sigma bounds (2,) of the pixel along the screen's x and y, pixels."""
        return None if self.covariance_px is None else 3.0 * np.sqrt(np.diag(self.covariance_px))


@dataclass(frozen=True)
class Screen:
    """A screen of ``width_px`` x ``height_px`` pixels, ``width_mm`` x ``height_mm`` active area, at
    ``T_cam_screen`` (camera <- screen), with the pose's ``covariance`` (6 x 6, docs/formats.md convention) or None."""

    width_px: int
    height_px: int
    width_mm: float
    height_mm: float
    T_cam_screen: Transform
    covariance: np.ndarray | None = None

    @classmethod
    def from_result(cls, result: Mapping[str, Any] | str | os.PathLike[str]) -> Screen:
        """From a result@1 of a screen capture (its ``screen`` block and ``T_cam_base``): its dictionary, or
        the path of its file (read and validated by ``mirror_fg.io.result.load_result``). TypeError for
        anything else, ValueError (DatasetError for a file) for a result without a screen."""
        if isinstance(result, (str, os.PathLike)):
            from mirror_fg.io.result import load_result  # the format's one reader; core needs no io otherwise

            result = load_result(result)
        if not isinstance(result, Mapping):
            raise TypeError(f"Screen.from_result takes a result@1 dictionary or the path of its file, got "
                            f"{type(result).__name__}")
        block = result.get("screen")
        if not isinstance(block, Mapping):
            raise ValueError("the result has no 'screen' block (it is not from a capture with a screen target)")
        T = result["T_cam_base"]
        cov = result.get("covariance_cam_base")
        return cls(int(block["width_px"]), int(block["height_px"]), float(block["width_mm"]), float(block["height_mm"]),
                   Transform(np.array(T["R"], dtype=float), np.array(T["t"], dtype=float)),
                   None if cov is None else np.array(cov, dtype=float))

    @property
    def metres_per_px(self) -> np.ndarray:
        """(2,) metres per pixel along the screen's x and y."""
        return np.array([self.width_mm / self.width_px, self.height_mm / self.height_px]) / 1000.0

    def screen_point(self, edge_px: Any) -> np.ndarray:
        """Screen-frame points (..., 3), metres, of pixel-edge coordinates (..., 2)."""
        xy = np.asarray(edge_px, dtype=float) * self.metres_per_px
        return np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1)

    def camera_point(self, edge_px: Any) -> np.ndarray:
        """Camera-frame points (..., 3), metres, of pixel-edge coordinates (..., 2) on the screen."""
        return self.T_cam_screen.apply(self.screen_point(edge_px))

    def camera_point_covariance(self, edge_px: Any) -> np.ndarray | None:
        """Covariance (3, 3), m^2, of :meth:`camera_point` of one pixel-edge point (2,), or None."""
        if self.covariance is None:
            return None
        Rs = self.T_cam_screen.R @ self.screen_point(edge_px)
        J = np.hstack([-_skew(Rs), np.eye(3)])  # dp = -[R s]x dtheta + dt
        return J @ self.covariance @ J.T

    @property
    def corners_cam(self) -> np.ndarray:
        """(4, 3) top-left, top-right, bottom-right, bottom-left corners of the active area, camera frame."""
        w, h = self.width_px, self.height_px
        return self.camera_point(np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]))

    @property
    def normal_cam(self) -> np.ndarray:
        """Unit normal out of the screen towards the viewer (-z of the screen frame), camera frame."""
        return -self.T_cam_screen.R[:, 2]

    def pixel_of_point(self, point_cam: Any) -> np.ndarray:
        """Pixel-edge coordinates (..., 2) of camera-frame points (..., 3) projected along the normal onto the screen."""
        s = self.T_cam_screen.inverse().apply(np.asarray(point_cam, dtype=float))
        return s[..., :2] / self.metres_per_px

    def pixel_of_ray(self, origin: Any, direction: Any, inside: bool = True) -> ScreenHit | None:
        """Where the ray ``origin + lambda * direction`` (camera frame, metres; ``lambda > 0``) meets the
        screen, or None: parallel to it, behind the origin, or (``inside``) off the active area."""
        o = np.asarray(origin, dtype=float).reshape(3)
        d = np.asarray(direction, dtype=float).reshape(3)
        R, t = self.T_cam_screen.R, self.T_cam_screen.t
        o_s, d_s = R.T @ (o - t), R.T @ d  # the ray in the screen frame
        if abs(d_s[2]) < 1e-12 * max(float(np.linalg.norm(d_s)), 1e-300):
            return None
        lam = -o_s[2] / d_s[2]
        if not lam > 0:
            return None
        q = o_s + lam * d_s
        pixel = q[:2] / self.metres_per_px
        if inside and not (0.0 <= pixel[0] < self.width_px and 0.0 <= pixel[1] < self.height_px):
            return None
        cov = None
        if self.covariance is not None:
            # R' = Exp(dtheta) R, t' = t + dt: d(o_s) = R^T [o - t]x dtheta - R^T dt, d(d_s) = R^T [d]x dtheta.
            G = np.hstack([R.T @ _skew(o - t) + lam * (R.T @ _skew(d)), -R.T])  # d(o_s + lam d_s), lam held
            J_q = (np.eye(3) - np.outer(d_s, [0.0, 0.0, 1.0]) / d_s[2]) @ G  # lam moves to keep q_z = 0
            J = J_q[:2] / self.metres_per_px[:, None]
            cov = J @ self.covariance @ J.T
        return ScreenHit(pixel, cov, R @ q + t, float(lam))

    def to_dict(self) -> dict[str, Any]:
        """The result@1 ``screen`` block (docs/formats.md), with extras: ``mm_per_px`` and, with a covariance,
        each corner's 3-sigma bounds (camera axes, mm)."""
        block: dict[str, Any] = {
            "width_px": int(self.width_px), "height_px": int(self.height_px),
            "width_mm": float(self.width_mm), "height_mm": float(self.height_mm),
            "corners_cam": self.corners_cam.tolist(), "normal_cam": self.normal_cam.tolist(),
            "mm_per_px": (1000.0 * self.metres_per_px).tolist(),
        }
        if self.covariance is not None:
            w, h = self.width_px, self.height_px
            block["corners_sigma3_mm"] = [
                (3000.0 * np.sqrt(np.diag(self.camera_point_covariance(e)))).tolist()  # type: ignore[arg-type]
                for e in ([0.0, 0.0], [w, 0.0], [w, h], [0.0, h])
            ]
        return block
