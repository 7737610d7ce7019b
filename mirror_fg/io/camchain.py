"""Kalibr's ``camchain.yaml`` of a multi-camera ``mirror-fg/result@1``, and its standard deviations beside it.

Kalibr's reader (``kalibr_common/ConfigReader.py``, ``CameraChainParameters``) counts the cameras as the
top-level keys (``numCameras() = len(data)``) and reads ``cam0``, ``cam1``, ... by name, each with
``camera_model`` (``pinhole``), ``intrinsics`` ``[fu, fv, pu, pv]`` (floats), ``distortion_model``
(``radtan``: 4 coefficients ``k1, k2, p1, p2``; ``equidistant``: ``k1..k4``, OpenCV's fisheye model),
``distortion_coeffs``, ``resolution`` ``[w, h]`` (ints), ``rostopic``, ``cam_overlaps`` and, for every camera
after the first, ``T_cn_cnm1``: the 4x4 transform from camera n-1 into camera n (``x_n = T x_nm1``; its
exporters compute it as ``T_cn_i T_cnm1_i^-1``), which is result@1's ``rig`` entry. A top-level key of our
own would be counted as a camera, so the standard deviations (which Kalibr leaves out) go to a second file,
``<stem>.camchain-sigma.yaml``: per camera, 1-sigma and 3-sigma of ``T_cn_cnm1`` (degrees about camera n's
axes, millimetres, docs/formats.md's convention) and its 6x6 covariance, and the estimated intrinsics'
standard deviations in Kalibr's order.
"""
from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.transform import Transform, _clean
from mirror_fg.io.result import validate_result

__all__ = ["camchain", "camchain_sigma", "camchain_paths", "camchain_texts", "camchain_topic", "KALIBR_INTRINSICS"]

#: Kalibr's pinhole ``intrinsics`` order and the result@1 camera keys they are.
KALIBR_INTRINSICS = ("fx", "fy", "cx", "cy")
#: Kalibr's distortion coefficients (4) of each camera model, as result@1 names them.
_KALIBR_DISTORTION = {"pinhole": ("radtan", ("k1", "k2", "p1", "p2")), "fisheye": ("equidistant", ("k1", "k2", "k3", "k4"))}
_TOPIC_CHARACTER = re.compile(r"[^A-Za-z0-9_]")


def camchain_topic(name: str) -> str:
    """``/<name>/image_raw``, characters a ROS name does not take replaced by ``_``."""
    clean = _TOPIC_CHARACTER.sub("_", name)
    if clean[:1].isdigit():
        clean = "cam_" + clean
    return f"/{clean}/image_raw"


def _cameras(result: Mapping[str, Any], source: str) -> dict[str, Any]:
    cameras = result.get("cameras")
    if not cameras:
        raise DatasetError(f"{source}: a camchain needs a result with cameras (a dataset with several cameras)")
    for name, entry in cameras.items():
        if entry.get("camera") is None:
            raise DatasetError(f"{source}: camera {name!r} has no intrinsics in the result (a camchain needs each "
                               "camera's pixels model)")
    return cameras


def _distortion(camera: Mapping[str, Any]) -> tuple[str, list[float], list[float]]:
    """Kalibr's distortion model, its 4 coefficients, and the OpenCV terms it cannot hold (non-zero)."""
    model = camera.get("model", "pinhole")
    kalibr_model, _ = _KALIBR_DISTORTION[model]
    dist = [float(x) for x in camera.get("dist") or []] + [0.0] * 4
    return kalibr_model, dist[:4], [x for x in dist[4:] if x != 0.0]


def camchain(result: Mapping[str, Any], source: str = "result") -> dict[str, dict[str, Any]]:
    """The camchain dictionary (``cam0``, ``cam1``, ... in the result's ``cameras`` order). ``result`` is
    validated first; DatasetError naming ``source`` when it has no cameras or a camera lacks intrinsics."""
    result = validate_result(result, source)
    cameras = _cameras(result, source)
    out: dict[str, dict[str, Any]] = {}
    for n, (name, entry) in enumerate(cameras.items()):
        camera = entry["camera"]
        distortion_model, coefficients, _ = _distortion(camera)
        cam: dict[str, Any] = {
            "camera_model": "pinhole",
            "intrinsics": [float(camera[k]) for k in KALIBR_INTRINSICS],
            "distortion_model": distortion_model,
            "distortion_coeffs": coefficients,
            "resolution": [int(camera["width"]), int(camera["height"])],
            "rostopic": camchain_topic(name),
            "cam_overlaps": [],
        }
        if n > 0:
            rig = result["rig"][n - 1]  # validated: from camera n-1 to camera n
            T = Transform(np.array(rig["T"]["R"]), np.array(rig["T"]["t"])).matrix()
            cam["T_cn_cnm1"] = [[_clean(float(x)) for x in row] for row in T]
        out[f"cam{n}"] = cam
    return out


def _sd(covariance: Any) -> dict[str, list[float]] | None:
    if covariance is None:
        return None
    sd = np.sqrt(np.clip(np.diag(np.asarray(covariance, dtype=float)), 0.0, None))
    return {"rotation_deg": np.rad2deg(sd[:3]).tolist(), "position_mm": (1e3 * sd[3:]).tolist()}


def camchain_sigma(result: Mapping[str, Any], source: str = "result") -> dict[str, Any]:
    """The standard deviations of :func:`camchain`'s values, per ``camN``: the camera's name, ``T_cn_cnm1``'s
    1-sigma and 3-sigma and 6x6 covariance (where the result has one), and ``intrinsics_sigma`` /
    ``distortion_sigma`` (1-sigma in Kalibr's order; null for a value kept, not estimated)."""
    result = validate_result(result, source)
    cameras = _cameras(result, source)
    out: dict[str, Any] = {}
    for n, (name, entry) in enumerate(cameras.items()):
        camera = entry["camera"]
        estimated = list(camera.get("estimated") or [])
        P = camera.get("covariance")
        def sd(key: str) -> float | None:
            if key not in estimated or P is None:
                return None
            i = estimated.index(key)
            return float(np.sqrt(max(P[i][i], 0.0)))
        _, names = _KALIBR_DISTORTION[camera.get("model", "pinhole")]
        cam: dict[str, Any] = {"name": name, "intrinsics_sigma": [sd(k) for k in KALIBR_INTRINSICS],
                               "distortion_sigma": [sd(k) for k in names]}
        dropped = _distortion(camera)[2]
        if dropped:
            cam["distortion_dropped"] = dropped
        if n > 0:
            rig = result["rig"][n - 1]
            cam["T_cn_cnm1_from"] = rig["from"]
            cam["T_cn_cnm1_sigma"] = _sd(rig.get("covariance"))
            cam["T_cn_cnm1_sigma3"] = rig.get("sigma3")
            cam["T_cn_cnm1_covariance"] = rig.get("covariance")
        out[f"cam{n}"] = cam
    return out


def camchain_paths(result_path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``(<stem>.camchain.yaml, <stem>.camchain-sigma.yaml)`` beside ``result_path``."""
    p = Path(result_path)
    return p.with_name(f"{p.stem}.camchain.yaml"), p.with_name(f"{p.stem}.camchain-sigma.yaml")


def _dump(content: Mapping[str, Any]) -> str:
    return yaml.safe_dump(dict(content), default_flow_style=None, sort_keys=False, width=1 << 16, allow_unicode=True)


def camchain_texts(result: Mapping[str, Any], result_path: str | os.PathLike[str]) -> dict[str, str]:
    """``{path: text}`` of the camchain and its sigma file (nothing written: the caller commits all its
    outputs together). DatasetError naming ``result_path`` (see :func:`camchain`)."""
    source = os.fspath(result_path)
    chain, sigma = camchain(result, source), camchain_sigma(result, source)
    name = " ".join(Path(result_path).name.split())
    names = ", ".join(f"cam{n} = {entry['name']}" for n, entry in enumerate(sigma.values()))
    notes = "".join(f"# {cam}: OpenCV distortion terms beyond Kalibr's four left out: {entry['distortion_dropped']}\n"
                    for cam, entry in sigma.items() if entry.get("distortion_dropped"))
    header = (f"# Kalibr camchain written by mirror-fg from {name} ({names}).\n"
              "# T_cn_cnm1 maps points of camera n-1 into camera n (metres); the standard deviations are in\n"
              f"# {camchain_paths(result_path)[1].name}.\n" + notes)
    sigma_header = (f"# Standard deviations of the mirror-fg camchain of {name} (Kalibr writes none).\n"
                    "# T_cn_cnm1_sigma: 1-sigma, _sigma3: 3-sigma; rotation_deg about camera n's axes (R_true = Exp(dtheta) R),\n"
                    "# position_mm along them (t_true = t + dt); covariance [dtheta rad, dt m]. intrinsics_sigma: fu, fv, pu, pv\n"
                    "# in pixels, null where kept.\n")
    chain_path, sigma_path = camchain_paths(result_path)
    return {os.fspath(chain_path): header + _dump(chain), os.fspath(sigma_path): sigma_header + _dump(sigma)}
