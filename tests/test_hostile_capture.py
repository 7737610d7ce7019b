"""Hostile input to captures and detection: every bad file ends in one DatasetError line or a
refused image, never an internal exception, a native library's stderr line, or gigabytes of memory."""
from __future__ import annotations

import json
import struct
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from mirror_fg.io.capture import capture_from_dict, load_capture
from mirror_fg.io.fileio import MAX_IMAGE_PIXELS
from mirror_fg.core.errors import DatasetError
from mirror_fg.vision.detectors import FOUND, REFUSED
from mirror_fg.vision.detect import _too_large, detect_capture

SQUARE_PX = 20
COLS, ROWS = 5, 4  # inner corners; cols + rows odd


def board_png(path: Path) -> tuple[int, int]:
    """A front view of a COLS x ROWS board (top-left square black); returns (width, height)."""
    h, w = (ROWS + 1) * SQUARE_PX + 2 * SQUARE_PX, (COLS + 1) * SQUARE_PX + 2 * SQUARE_PX
    img = np.full((h, w), 230, np.uint8)
    for r in range(ROWS + 1):
        for c in range(COLS + 1):
            if (r + c) % 2 == 0:
                y, x = (r + 1) * SQUARE_PX, (c + 1) * SQUARE_PX
                img[y : y + SQUARE_PX, x : x + SQUARE_PX] = 25
    cv2.imwrite(str(path), img)
    return w, h


def bilevel_png(path: Path, width: int, height: int) -> None:
    """A 1-bit black PNG written row by row: a 20000 x 20000 one is ~1 MB on disk and costs no memory here."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    row = b"\x00" * (1 + (width + 7) // 8)  # filter byte + packed bits
    z = zlib.compressobj(9)
    idat = b"".join(z.compress(row) for _ in range(height)) + z.flush()
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0))
                     + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


def capture_dict(camera, images, num_mirrors: int = 2) -> dict:
    return {
        "format": "mirror-fg/capture@1", "num_mirrors": num_mirrors, "camera": camera,
        "target": {"kind": "chessboard", "cols": COLS, "rows": ROWS, "square": 0.03},
        "images": [{"file": f, "mirror_configs": [0, "each"]} for f in images],
    }


def write_capture(tmp_path: Path, capture: dict) -> Path:
    path = tmp_path / "capture.yaml"
    path.write_text(yaml.safe_dump(capture, sort_keys=False))
    return path


def camera_of(width: int, height: int) -> dict:
    return {"model": "pinhole", "width": width, "height": height, "fx": 300.0, "fy": 300.0,
            "cx": width / 2, "cy": height / 2}


def truncated_files(tmp_path: Path) -> list[str]:
    """A truncated PNG, a truncated JPEG, random bytes and an empty file, named as images."""
    noise = (np.random.default_rng(0).random((120, 160)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "full.png"), noise)
    cv2.imwrite(str(tmp_path / "full.jpg"), noise)
    png, jpg = (tmp_path / "full.png").read_bytes(), (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cutpng.png").write_bytes(png[: len(png) // 2])
    (tmp_path / "cutjpg.jpg").write_bytes(jpg[: len(jpg) // 2])
    (tmp_path / "noise.png").write_bytes(np.random.default_rng(1).bytes(3000))
    (tmp_path / "empty.jpg").write_bytes(b"")
    return ["cutpng.png", "cutjpg.jpg", "noise.png", "empty.jpg"]


# --------------------------------------------------------------------------------------------------
# 1. Corrupt camera calibration files
# --------------------------------------------------------------------------------------------------

FS_HEAD = "%YAML:1.0\n---\n"


def fs_matrix(name: str, rows, cols, data: str, dt: str = "d") -> str:
    return f"{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: {dt}\n   data: [ {data} ]\n"


K9 = "500., 0., 319.5, 0., 500., 239.5, 0., 0., 1."
FS_GOOD_K = fs_matrix("camera_matrix", 3, 3, K9)
BIG = "1" + "0" * 400


def ros(**changes) -> str:
    d = {"image_width": 640, "image_height": 480,
         "camera_matrix": {"rows": 3, "cols": 3, "data": [500.0, 0, 319.5, 0, 500.0, 239.5, 0, 0, 1]},
         "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5}}
    d.update(changes)
    return yaml.safe_dump(d)


def kalibr(**changes) -> str:
    cam = {"camera_model": "pinhole", "intrinsics": [400.0, 401.0, 320.0, 240.0], "distortion_model": "radtan",
           "distortion_coeffs": [0.01, 0.02, 0.003, 0.004], "resolution": [640, 480]}
    cam.update(changes)
    return yaml.safe_dump({"cam0": cam})


def xml(body: str) -> str:
    return f'<?xml version="1.0"?>\n<opencv_storage>\n{body}\n</opencv_storage>\n'


XML_K = '<camera_matrix type_id="opencv-matrix"><rows>{r}</rows><cols>3</cols><dt>d</dt><data>{d}</data></camera_matrix>'

CAMERA_FILES = {
    # OpenCV FileStorage YAML
    "fs_K_8_numbers.yaml": FS_HEAD + fs_matrix("camera_matrix", 3, 3, "1, 2, 3, 4, 5, 6, 7, 8"),
    "fs_K_rows_mismatch.yaml": FS_HEAD + fs_matrix("camera_matrix", 2, 4, "1, 2, 3, 4, 5, 6, 7, 8, 9"),
    "fs_K_string_entry.yaml": FS_HEAD + fs_matrix("camera_matrix", 3, 3, "500, 0, abc, 0, 500, 239.5, 0, 0, 1"),
    "fs_K_scalar.yaml": FS_HEAD + "camera_matrix: 5\n",
    "fs_K_nested_garbage.yaml": FS_HEAD + "camera_matrix: [1, [2, {a: 3}], 4]\n",
    "fs_K_nan.yaml": FS_HEAD + fs_matrix("camera_matrix", 3, 3, ".nan, 0, 319.5, 0, 500, 239.5, 0, 0, 1"),
    "fs_K_huge_rows.yaml": FS_HEAD + fs_matrix("camera_matrix", 3000000, 3000000, K9),
    "fs_dist_3.yaml": FS_HEAD + FS_GOOD_K + fs_matrix("distortion_coefficients", 1, 3, "0.1, 0.2, 0.3"),
    "fs_dist_7.yaml": FS_HEAD + FS_GOOD_K + fs_matrix("distortion_coefficients", 1, 7, "0, 0, 0, 0, 0, 0, 0"),
    "fs_width_huge.yaml": FS_HEAD + FS_GOOD_K + f"image_width: {BIG}\nimage_height: 480\n",
    "fs_width_string.yaml": FS_HEAD + FS_GOOD_K + "image_width: wide\nimage_height: 480\n",
    "fs_width_inf.yaml": FS_HEAD + FS_GOOD_K + "image_width: .inf\nimage_height: 480\n",
    "fs_width_nan.yaml": FS_HEAD + FS_GOOD_K + "image_width: .nan\nimage_height: 480\n",
    "fs_width_fraction.yaml": FS_HEAD + FS_GOOD_K + "image_width: 640.5\nimage_height: 480\n",
    "fs_width_zero.yaml": FS_HEAD + FS_GOOD_K + "image_width: 0\nimage_height: 480\n",
    "fs_height_missing.yaml": FS_HEAD + FS_GOOD_K + "image_width: 640\n",
    "fs_truncated.yaml": FS_HEAD + "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1, 2,",
    "fs_no_K.yaml": FS_HEAD + "image_width: 640\n",
    "fs_header_only.yaml": "%YAML:1.0\n",
    # OpenCV FileStorage XML
    "xml_rows_word.xml": xml(XML_K.format(r="three", d="1 0 0 0 1 0 0 0 1")),
    "xml_rows_huge.xml": xml(XML_K.format(r="99999999", d="1 0 0 0 1 0 0 0 1")),
    "xml_data_words.xml": xml(XML_K.format(r="3", d="a b c d e f g h i")),
    "xml_width_element.xml": xml(XML_K.format(r="3", d="500 0 320 0 500 240 0 0 1")
                                 + "<image_width><_>1</_><_>2</_></image_width><image_height>480</image_height>"),
    "xml_truncated.xml": xml(XML_K.format(r="3", d="1 0 0 0 1 0 0 0 1"))[:70],
    # ROS camera_info YAML
    "ros_K_8.yaml": ros(camera_matrix={"rows": 3, "cols": 3, "data": [1, 2, 3, 4, 5, 6, 7, 8]}),
    "ros_K_strings.yaml": ros(camera_matrix={"rows": 3, "cols": 3, "data": ["500", 0, 319.5, 0, 500, 239.5, 0, 0, 1]}),
    "ros_K_bools.yaml": ros(camera_matrix={"rows": 3, "cols": 3, "data": [True, 0, 319.5, 0, 500, 239.5, 0, 0, True]}),
    "ros_K_null.yaml": ros(camera_matrix={"rows": 3, "cols": 3, "data": None}),
    "ros_K_nested.yaml": ros(camera_matrix={"rows": 3, "cols": 3, "data": [[1, [2]], {"a": 1}]}),
    "ros_K_rows_string.yaml": ros(camera_matrix={"rows": "3", "cols": "3", "data": [500, 0, 319.5, 0, 500, 239.5, 0, 0, 1]}),
    "ros_dist_3.yaml": ros(distortion_coefficients={"rows": 1, "cols": 3, "data": [0, 0, 0]}),
    "ros_dist_7.yaml": ros(distortion_coefficients=[0] * 7),
    "ros_dist_string.yaml": ros(distortion_coefficients={"rows": 1, "cols": 5, "data": [0, 0, "x", 0, 0]}),
    "ros_width_float.yaml": ros(image_width=640.5),
    "ros_width_bool.yaml": ros(image_width=True),
    "ros_width_missing.yaml": ros(image_width=None),
    "ros_K_null_value.yaml": ros(camera_matrix=None),
    # Kalibr camchain
    "kalibr_intrinsics_string.yaml": kalibr(intrinsics=[400.0, 401.0, 320.0, "240"]),
    "kalibr_intrinsics_3.yaml": kalibr(intrinsics=[400.0, 401.0, 320.0]),
    "kalibr_coeffs_strings.yaml": kalibr(distortion_coeffs=["a", "b", "c", "d"]),
    "kalibr_coeffs_bools.yaml": kalibr(distortion_coeffs=[True, False, True, False]),
    "kalibr_coeffs_null.yaml": kalibr(distortion_coeffs=[None, 0, 0, 0]),
    "kalibr_resolution_zero.yaml": kalibr(resolution=[0, 480]),
    "kalibr_resolution_strings.yaml": kalibr(resolution=["640", "480"]),
    "kalibr_resolution_giant.yaml": kalibr(resolution=[10**6, 10**6]),
    "kalibr_cam_null.yaml": "cam0: null\ncam1: {camera_model: pinhole}\n",
    # anything
    "empty.yaml": "",
    "empty.xml": "",
    "scalar.yaml": "42\n",
}
#: YAML texts with numbers PyYAML would not write (400 digits, .nan)
CAMERA_FILES["ros_K_huge_int.yaml"] = ros().replace("500.0", BIG, 1)
CAMERA_FILES["kalibr_intrinsics_huge_int.yaml"] = kalibr().replace("400.0", BIG, 1)
CAMERA_FILES["kalibr_intrinsics_nan.yaml"] = kalibr().replace("400.0", ".nan", 1)
CAMERA_FILES["kalibr_coeffs_huge_int.yaml"] = kalibr().replace("0.01", BIG, 1)


@pytest.mark.parametrize("name", sorted(CAMERA_FILES))
def test_corrupt_camera_file_is_one_line_naming_it(tmp_path, name):
    (tmp_path / name).write_text(CAMERA_FILES[name])
    board_png(tmp_path / "a.png")
    path = write_capture(tmp_path, capture_dict(name, ["a.png"]))
    with pytest.raises(DatasetError) as info:
        load_capture(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{path}: camera ({name})"), message
    assert len(message) < len(str(path)) + 250 and BIG not in message, message


def test_camera_file_name_is_checked_and_good_files_still_read(tmp_path):
    (tmp_path / "chain.yaml").write_text(kalibr())
    board_png(tmp_path / "a.png")
    with pytest.raises(DatasetError, match="name must be a camera name"):
        load_capture(write_capture(tmp_path, capture_dict({"file": "chain.yaml", "name": ["cam0"]}, ["a.png"])))
    cap = load_capture(write_capture(tmp_path, capture_dict({"file": "chain.yaml", "name": "cam0"}, ["a.png"])))
    assert cap.camera["width"] == 640 and cap.camera["dist"] == [0.01, 0.02, 0.003, 0.004]
    (tmp_path / "fs.xml").write_text(xml(XML_K.format(r="3", d="500 0 320 0 501 240 0 0 1")
                                         + "<image_width>640</image_width><image_height>480</image_height>"))
    cap = load_capture(write_capture(tmp_path, capture_dict("fs.xml", ["a.png"])))
    assert (cap.camera["fy"], cap.camera["height"], cap.camera["dist"]) == (501.0, 480, [0.0] * 5)
    (tmp_path / "size.yaml").write_text(FS_HEAD + FS_GOOD_K + "image_size: [ 640, 480 ]\n")
    assert load_capture(write_capture(tmp_path, capture_dict("size.yaml", ["a.png"]))).camera["width"] == 640


# --------------------------------------------------------------------------------------------------
# 2. Decompression bombs, huge frames, files that are not images
# --------------------------------------------------------------------------------------------------

CHILD_PRELUDE = textwrap.dedent("""
    import resource, sys
    from mirror_fg.io.capture import load_capture
    from mirror_fg.io.dataset import DatasetError
    from mirror_fg.vision.detect import detect_capture, format_reports
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    try:
        _, reports = detect_capture(load_capture(sys.argv[1]), progress=False)
        print(format_reports(reports))
    except DatasetError as exc:
        print("DatasetError:", exc)
    print("grew_kb", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before)
""")


def run_detect_child(capture: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", CHILD_PRELUDE, str(capture)], capture_output=True, text=True, timeout=120)


def test_decompression_bomb_is_refused_from_its_header(tmp_path):
    bilevel_png(tmp_path / "bomb.png", 20000, 20000)  # 400 Mpx: 400 MB as 8-bit gray
    assert (tmp_path / "bomb.png").stat().st_size < 3_000_000
    w, h = board_png(tmp_path / "a.png")
    child = run_detect_child(write_capture(tmp_path, capture_dict(camera_of(w, h), ["a.png", "bomb.png"])))
    assert child.returncode == 0, child.stderr
    lines = child.stdout.splitlines()
    assert lines[0].startswith("a: found"), child.stdout
    assert lines[1].startswith("bomb: refused: images[1] (bomb.png): image is above the limit"), child.stdout
    grew_kb = int(lines[-1].split()[1])
    assert grew_kb < 150_000, f"detection grew by {grew_kb} kB"


def test_image_size_limit_keeps_big_photographs(tmp_path):
    bilevel_png(tmp_path / "photo.png", 8000, 6000)  # 48 Mpx
    bilevel_png(tmp_path / "wide.png", 12000, 9000)  # 108 Mpx: Pillow only warns; our limit refuses
    assert MAX_IMAGE_PIXELS >= 8000 * 6000
    assert _too_large(str(tmp_path / "photo.png")) == ""
    assert "12000 x 9000 pixels, above the limit" in _too_large(str(tmp_path / "wide.png"))


def test_files_that_are_not_images_are_refused_with_a_reason(tmp_path):
    w, h = board_png(tmp_path / "a.png")
    bad = truncated_files(tmp_path)
    cap = load_capture(write_capture(tmp_path, capture_dict(camera_of(w, h), ["a.png", *bad])))
    _, reports = detect_capture(cap, progress=False)
    assert [r.status for r in reports] == [FOUND] + [REFUSED] * len(bad)
    for report, name in zip(reports[1:], bad):
        assert f"({name}): " in report.reason and ("cannot decode" in report.reason or "damaged" in report.reason)
        assert "\n" not in report.reason and len(report.reason) < 220, report.reason
    assert "Premature end of JPEG file" in reports[2].reason  # the decoder's own words, kept short


def test_video_with_frames_above_the_limit_is_refused_before_decoding(tmp_path):
    # YUV4MPEG2: a text header gives the frame size; one 12000 x 12000 frame would be 216 MB, the file is 1 kB
    (tmp_path / "big.y4m").write_bytes(b"YUV4MPEG2 W12000 H12000 F25:1 Ip A1:1 C420jpeg\nFRAME\n" + bytes(1000))
    capture = capture_dict(camera_of(64, 48), [])
    del capture["images"]
    capture["video"] = {"file": "big.y4m", "segments": [{"frames": [0, 0], "mirror_configs": [0, 0]}]}
    with pytest.raises(DatasetError) as info:
        load_capture(write_capture(tmp_path, capture))
    message = str(info.value)
    assert "video (big.y4m): frames of 12000 x 12000 pixels are above the limit" in message, message


# --------------------------------------------------------------------------------------------------
# 3. Native libraries' stderr
# --------------------------------------------------------------------------------------------------


def test_native_decoder_lines_do_not_reach_stderr(tmp_path):
    w, h = board_png(tmp_path / "a.png")
    bad = truncated_files(tmp_path)
    child = run_detect_child(write_capture(tmp_path, capture_dict(camera_of(w, h), ["a.png", *bad])))
    for word in ("libpng", "JPEG", "IDAT", "Premature"):
        assert word not in child.stderr, child.stderr
    assert child.returncode == 0 and "a: found" in child.stdout, child.stdout + child.stderr
    assert "libpng error" in child.stdout  # kept, shortened, in the image's reason instead
    # a video FFmpeg refuses to open: its own "[IMGUTILS @ ...]" line is not printed either
    (tmp_path / "huge.y4m").write_bytes(b"YUV4MPEG2 W40000 H40000 F25:1 Ip A1:1 C420jpeg\nFRAME\n" + bytes(100))
    capture = capture_dict(camera_of(w, h), [])
    del capture["images"]
    capture["video"] = {"file": "huge.y4m", "segments": [{"frames": [0, 0], "mirror_configs": [0, 0]}]}
    child = run_detect_child(write_capture(tmp_path, capture))
    assert "DatasetError: " in child.stdout and "cannot open the video" in child.stdout, child.stdout
    assert child.stderr == "", child.stderr


# --------------------------------------------------------------------------------------------------
# 4. Capture.input_files
# --------------------------------------------------------------------------------------------------


def test_input_files_lists_every_file_read(tmp_path):
    w, h = board_png(tmp_path / "a.png")
    board_png(tmp_path / "b.png")
    (tmp_path / "cam.yaml").write_text(kalibr(resolution=[w, h]))
    (tmp_path / "obs.json").write_text(json.dumps({"P0": [10.0, 20.0]}))
    capture = capture_dict("cam.yaml", ["a.png", "b.png"])
    capture["images"][1]["observations"] = "obs.json"
    path = write_capture(tmp_path, capture)
    expected = [str(tmp_path / n) for n in ("capture.yaml", "cam.yaml", "a.png", "b.png", "obs.json")]
    assert load_capture(path).input_files() == expected
    capture["camera"] = camera_of(w, h)
    capture["images"].append({"file": "a.png", "id": "again", "mirror_configs": [1, 1]})  # listed twice, named once
    assert capture_from_dict(capture, base_dir=str(tmp_path)).input_files() == expected[2:]
    writer = cv2.VideoWriter(str(tmp_path / "v.avi"), cv2.VideoWriter_fourcc(*"FFV1"), 10, (w, h), isColor=False)
    writer.write(np.zeros((h, w), np.uint8))
    writer.release()
    del capture["images"]
    capture["video"] = {"file": "v.avi", "segments": [{"frames": [0, 0], "mirror_configs": [0, 0]}]}
    assert load_capture(write_capture(tmp_path, capture)).input_files() == [str(path), str(tmp_path / "v.avi")]


# --------------------------------------------------------------------------------------------------
# 5. Messages quote little of the user's data
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("where", ["top", "image file", "camera file", "observations file", "point name"])
def test_messages_quote_at_most_80_characters_of_user_data(tmp_path, where):
    long = "x" * 500
    board_png(tmp_path / "a.png")
    capture = capture_dict(camera_of(10, 10), ["a.png"])
    if where == "top":
        capture[long] = 1
    elif where == "image file":
        capture["images"][0]["file"] = long + ".png"
    elif where == "camera file":
        capture["camera"] = long + ".yaml"
    elif where == "observations file":
        capture["images"][0]["observations"] = long + ".txt"
    else:
        capture["images"][0]["observations"] = {long: [1, 2, 3]}
    path = write_capture(tmp_path, capture)
    with pytest.raises(DatasetError) as info:
        load_capture(path)
    message = str(info.value)
    assert "\n" not in message and "x" * 81 not in message, message
