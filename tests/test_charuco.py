"""ChArUco boards as a capture@1 target: rendered through one and two mirrors, detected, calibrated.

The images are synthesised here: the board image of ``cv2.aruco.CharucoBoard.generateImage`` is the
texture of the base plane, and each image is that plane seen through the mirrors, warped by its exact
planar homography (eqs. 5-9: base (x, y, 1) -> pixel), box-averaged from 4 x 4 supersamples in linear
intensity, blurred (optics), sRGB-encoded like a camera's PNG and given sensor noise. Through one
mirror the image is mirror-imaged, as a photograph would be.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from conftest import load_script, pose_difference
from mirror_fg import calibrate
from mirror_fg.core.errors import DatasetError
from mirror_fg.core.geometry import nested_transform
from mirror_fg.io.capture import capture_from_dict, load_capture
from mirror_fg.io.target import CharucoTarget, target_from_dict
from mirror_fg.vision.detect import detect_capture
from mirror_fg.vision.detectors import FOUND, NOT_FOUND, detect_charuco

SIZE = (1024, 768)
CAMERA = {"model": "pinhole", "width": SIZE[0], "height": SIZE[1], "fx": 800.0, "fy": 800.0, "cx": 511.5, "cy": 383.5}
COLS, ROWS, SQUARE = 7, 5, 0.05  # squares, metres
BOARD = {"kind": "charuco", "cols": COLS, "rows": ROWS, "square": SQUARE, "marker": 0.037, "dictionary": "DICT_4X4_50"}
TEXELS_PER_SQUARE = 120
QUIET_TEXELS = 60  # white margin around the board in the texture
SUPERSAMPLE = 4
BLUR_PX = 0.6  # Gaussian sigma of the optics, pixels
NOISE_GREY = 0.5  # sensor noise, grey levels
BLACK, WHITE, BACKGROUND = 0.04, 0.85, 0.3  # linear reflectances
PIXEL_SIGMA = 0.1  # pixels: about twice the corners' measured error (0.045 px RMS per coordinate)


def rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def reflect(d: np.ndarray, n: np.ndarray) -> np.ndarray:
    return d - 2 * (d @ n) * n


def tilted(n: np.ndarray, deg: float, phi: float) -> np.ndarray:
    """``n`` turned by ``deg`` towards the direction at angle ``phi`` around it."""
    u = unit(np.cross(n, [0.0, 1.0, 0.0]))
    w = np.cross(n, u)
    return unit(n + np.tan(np.radians(deg)) * (np.cos(phi) * u + np.sin(phi) * w))


def scene(num_mirrors: int) -> tuple[np.ndarray, np.ndarray, list[tuple[list[int], list[np.ndarray]]]]:
    """``R_cam_base``, ``t_cam_base`` (base = board frame) and per image (mirror_configs, mirror vectors).

    The camera looks into the last mirror 0.4 m ahead; each mirror turns the view by about 70 degrees;
    the board faces the mirror it is seen in. Placements tilt each nominal mirror by 4-5 degrees about
    its hit point, around a cone (1 mirror: 5 placements; 2 mirrors: 3 of mirror 1, each with 3 of
    mirror 2).
    """
    hit = np.array([0.0, 0.0, 0.4])  # where the optical axis meets the last mirror
    d = np.array([0.0, 0.0, 1.0])
    hits, normals = [], []
    first_normal = unit([np.sin(np.radians(35)), 0.0, np.cos(np.radians(35))])
    for k in range(num_mirrors):  # from the camera outwards: mirror Nv first
        n = first_normal if k == 0 else unit(d - unit([0.35, -0.85, 0.4]))  # then up and back
        hits.append(hit)
        normals.append(n)
        d = reflect(d, n)
        hit = hit + 0.3 * d
    X = hit + 0.1 * d  # the board's centre, 0.4 m past the last mirror hit
    z_b = d  # into the board: its printed face looks back along the path
    y_b = unit(np.array([0.0, 1.0, 0.0]) - (np.array([0.0, 1.0, 0.0]) @ z_b) * z_b)
    R = np.column_stack([np.cross(y_b, z_b), y_b, z_b]) @ rot("z", 20) @ rot("x", 12) @ rot("y", -10)
    centre = np.array([COLS * SQUARE / 2, ROWS * SQUARE / 2, 0.0])
    t = X - R @ centre
    hits, normals = hits[::-1], normals[::-1]  # mirror 1 (met first by the light) first

    def vector(l: int, deg: float, phi: float) -> np.ndarray:
        n = tilted(normals[l], deg, phi)
        return float(n @ hits[l]) * n

    images = []
    if num_mirrors == 1:
        for m in range(8):
            images.append(([m], [vector(0, 7.0, 2 * np.pi * m / 8)]))
    else:
        for m1 in range(3):
            v1 = vector(0, 8.0, 2 * np.pi * m1 / 3)
            for k in range(3):
                images.append(([m1, 3 * m1 + k], [v1, vector(1, 8.0, 2 * np.pi * k / 3 + 0.5 + m1)]))
    return R, t, images


def texture(target: CharucoTarget) -> np.ndarray:
    """Linear reflectance of the board (and its white margin), texel u centred at board x = (u + 0.5 - margin) * size."""
    w = target.cols * TEXELS_PER_SQUARE + 2 * QUIET_TEXELS
    h = target.rows * TEXELS_PER_SQUARE + 2 * QUIET_TEXELS
    img = target.board().generateImage((w, h), marginSize=QUIET_TEXELS, borderBits=1)
    return np.where(img > 127, WHITE, BLACK).astype(np.float32)


def render(tex: np.ndarray, H: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """8-bit sRGB image of the base plane whose homography (board (x, y, 1) metres -> pixel) is ``H``."""
    s, texel = SUPERSAMPLE, SQUARE / TEXELS_PER_SQUARE
    fine_to_pixel = np.array([[1 / s, 0, 0.5 / s - 0.5], [0, 1 / s, 0.5 / s - 0.5], [0, 0, 1]])
    board_to_texel = np.array([[1 / texel, 0, QUIET_TEXELS - 0.5], [0, 1 / texel, QUIET_TEXELS - 0.5], [0, 0, 1]])
    M = board_to_texel @ np.linalg.inv(H) @ fine_to_pixel
    fine = cv2.warpPerspective(tex, M, (SIZE[0] * s, SIZE[1] * s), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=BACKGROUND)
    linear = cv2.GaussianBlur(cv2.resize(fine, SIZE, interpolation=cv2.INTER_AREA), (0, 0), BLUR_PX)
    encoded = load_script("render_scene").srgb_encode(linear) + rng.normal(0.0, NOISE_GREY, linear.shape)
    return np.clip(np.round(encoded), 0, 255).astype(np.uint8)


def synthesise(tmp_path: Path, num_mirrors: int) -> tuple[Path, dict]:
    """The capture file and its truth: ``T_cam_base`` and every corner's true pixel per image."""
    target = target_from_dict(BOARD, "test")
    assert isinstance(target, CharucoTarget)
    R, t, images = scene(num_mirrors)
    K = np.array([[CAMERA["fx"], 0, CAMERA["cx"]], [0, CAMERA["fy"], CAMERA["cy"]], [0, 0, 1.0]])
    corners = target.target_points()
    tex, rng = texture(target), np.random.default_rng(num_mirrors)
    entries, truth_pixels = [], []
    for k, (configs, vectors) in enumerate(images):
        A, b = nested_transform(R, t, vectors)
        H = K @ np.column_stack([A[:, 0], A[:, 1], b])
        uvw = (H @ np.array([[p[0], p[1], 1.0] for p in corners.values()]).T).T
        pixels = {n: q[:2] / q[2] for n, q in zip(corners, uvw)}
        inside = all(20 < p[0] < SIZE[0] - 20 and 20 < p[1] < SIZE[1] - 20 for p in pixels.values())
        assert inside, f"image {k}: the board leaves the view"
        cv2.imwrite(str(tmp_path / f"img{k}.png"), render(tex, H, rng))
        entries.append({"file": f"img{k}.png", "mirror_configs": configs})
        truth_pixels.append(pixels)
    capture = {"format": "mirror-fg/capture@1", "num_mirrors": num_mirrors, "camera": CAMERA,
               "pixel_sigma": PIXEL_SIGMA, "target": BOARD, "images": entries}
    path = tmp_path / "capture.yaml"
    path.write_text(yaml.safe_dump(capture, sort_keys=False))
    return path, {"R": R, "t": t, "pixels": truth_pixels}


@pytest.fixture(scope="module", params=[1, 2], ids=["one mirror", "two mirrors"])
def detected(request, tmp_path_factory):
    path, truth = synthesise(tmp_path_factory.mktemp(f"charuco{request.param}"), request.param)
    ds, reports = detect_capture(load_capture(path), progress=False)
    return request.param, path, truth, ds, reports


def test_charuco_corners_detected_sub_pixel_through_mirrors(detected):
    num_mirrors, _, truth, ds, reports = detected
    assert [r.status for r in reports] == [FOUND] * len(truth["pixels"])
    errors = []
    for image, expected in zip(ds.images, truth["pixels"]):
        assert len(image.observations) == len(expected) == 24  # every corner, by its id
        errors += [np.linalg.norm(image.observations[n] - expected[n]) for n in image.observations]
    errors = np.array(errors)
    print(f"{num_mirrors} mirror(s): corner error median {np.median(errors):.3f} px, max {errors.max():.3f} px, "
          f"RMS per coordinate {np.sqrt(np.mean(errors**2) / 2):.3f} px")
    assert np.median(errors) < 0.15 and errors.max() < 0.5, (np.median(errors), errors.max())


def test_charuco_capture_calibrates_to_the_truth_within_3_sigma(detected):
    num_mirrors, _, truth, ds, _ = detected
    cal = calibrate(ds)
    error = pose_difference(cal.R_cam_base, cal.t_cam_base, truth["R"], truth["t"])
    bound = 3 * np.sqrt(np.diag(cal.covariance))
    print(f"{num_mirrors} mirror(s): error / sigma {np.round(3 * error / bound, 2)}; "
          f"3-sigma {np.degrees(bound[:3]).round(3)} deg, {(1000 * bound[3:]).round(2)} mm")
    assert np.all(np.abs(error) <= bound), (error, bound)
    assert np.all(bound[:3] < np.radians(2)) and np.all(bound[3:] < 0.02)  # the scene constrains it


def test_charuco_needs_the_flip_through_an_odd_number_of_mirrors(detected):
    num_mirrors, path, truth, _, _ = detected
    gray = cv2.imread(str(path.parent / "img0.png"), cv2.IMREAD_GRAYSCALE)
    target = load_capture(path).target
    assert detect_charuco(gray, target, mirrored=num_mirrors % 2 == 0).status == NOT_FOUND  # the wrong parity
    turned = cv2.rotate(gray, cv2.ROTATE_180)  # names follow the ids, whatever the view
    det = detect_charuco(turned, target, mirrored=num_mirrors % 2 == 1, camera=CAMERA)
    assert det.status == FOUND
    for name, p in det.points.items():
        expected = np.array([SIZE[0] - 1, SIZE[1] - 1]) - truth["pixels"][0][name]
        assert np.linalg.norm(p - expected) < 0.5


@pytest.mark.parametrize(
    "change, words",
    [
        ({"cols": 1}, "cols"),
        ({"marker": 0.06}, "marker"),
        ({"dictionary": "DICT_9X9_1"}, "unknown dictionary"),
        ({"cols": 20, "rows": 20}, "has only 50"),
        ({"legacy_pattern": "yes"}, "legacy_pattern"),
        ({"markers": 0.03}, "markers"),
    ],
)
def test_charuco_target_refused_with_the_reason(change, words):
    with pytest.raises(DatasetError) as exc:
        target_from_dict({**BOARD, **change}, "cap.yaml")
    assert words in str(exc.value) and str(exc.value).startswith("cap.yaml: target")


def test_charuco_fiducials_are_opencv_board_corners(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((SIZE[1], SIZE[0]), np.uint8))
    cap = capture_from_dict({"format": "mirror-fg/capture@1", "num_mirrors": 1, "camera": CAMERA, "target": BOARD,
                             "T_base_target": {"R": np.eye(3).tolist(), "t": [0.1, 0.0, 0.0]},
                             "images": [{"file": "a.png", "mirror_configs": [0]}]}, base_dir=str(tmp_path))
    assert isinstance(cap.target, CharucoTarget)
    points = cap.target.target_points()
    opencv = cap.target.board().getChessboardCorners()
    assert list(points) == [f"C{i:02d}" for i in range(len(opencv))]
    np.testing.assert_allclose(np.array(list(points.values())), opencv, atol=1e-7)
    np.testing.assert_allclose(cap.fiducials()["C00"], [0.15, 0.05, 0.0])


def test_detection_is_logged_per_image_for_applications(detected, caplog):
    """Library messages go to the ``mirror_fg`` logger: the capture loaded, each image found (DEBUG) or
    left out with its reason (INFO), the closing count (INFO)."""
    import logging

    num_mirrors, path, _, _, _ = detected
    capture = yaml.safe_load(path.read_text())
    cv2.imwrite(str(path.parent / "blank.png"), np.full((SIZE[1], SIZE[0]), 128, np.uint8))
    capture["images"].append({"file": "blank.png", "mirror_configs": capture["images"][0]["mirror_configs"]})
    logged = path.parent / "logged.yaml"
    logged.write_text(yaml.safe_dump(capture, sort_keys=False))
    with caplog.at_level(logging.DEBUG, logger="mirror_fg"):
        detect_capture(load_capture(logged), progress=False)
    records = [(r.name, r.levelno, r.getMessage()) for r in caplog.records if r.name.startswith("mirror_fg")]
    assert any(level == logging.INFO and "capture loaded" in text and "charuco target" in text
               for _, level, text in records), records
    assert any(level == logging.DEBUG and text.startswith("img0: found, 24 points") for _, level, text in records)
    assert any(level == logging.INFO and text.startswith("blank: not found: ChArUco board: 0 corners")
               for _, level, text in records), records
    n = len(capture["images"])
    assert any(level == logging.INFO and f"{n} images: {n - 1} found, 1 not found" in text for _, level, text in records)
