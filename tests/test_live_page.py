"""The live page (tools/live_page.html) in headless Chromium, fed by the real server with a stub state:
what a user sees once done with only ``--target-mm``, and the labels against the target lines."""
import os
import re
import shutil
import signal
import subprocess
from dataclasses import dataclass, field

import cv2
import numpy as np
import pytest

from mirror_fg.live.server import LiveServer

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars", "--disable-breakpad", "--disable-crash-reporter"]


def chromium(*args: str, timeout: float = 240) -> str:
    """Run headless Chromium in a process group of its own; its standard output. Every process of the group
    (renderers, zygotes, crash handlers) is killed when it returns or times out: none outlives the test to
    keep polling a page or loading the machine under the tests that follow."""
    proc = subprocess.Popen([CHROMIUM, *CHROMIUM_FLAGS, *args], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout)
        return out
    except subprocess.TimeoutExpired:
        return ""
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium not installed (apt-get install chromium)")

WORDS = "tilt it 20 deg towards the upper right of the image, keep it ~0.50 m away"


def status(done: bool, position_mm: list[float]) -> dict:
    return {"frame": 40, "t": 12.0, "status": "added", "reason": "", "placements": 6,
            "sigma3_base_cam": {"rotation_deg": [0.8, 1.1, 0.5], "position_mm": position_mm},
            "next": {"mirror": 1, "tilt_deg": 20.0, "azimuth_deg": 45.0, "distance_m": 0.5},
            "done": done, "targets": {"mm": 40.0, "deg": None},
            "placements_tilt": [[10.0, 20.0], [15.0, 200.0], [22.0, 100.0]], "current_tilt": None,
            "counts": {"added": 6}, "next_words": WORDS}


@dataclass
class StubState:
    status: dict
    seq: int = 3
    jpeg: bytes = field(default_factory=lambda: cv2.imencode(".jpg", np.full((240, 320), 128, np.uint8))[1].tobytes())


def page(tmp_path, state: StubState) -> tuple[str, np.ndarray]:
    """The page's DOM and screenshot (RGB) once it has shown ``state``."""
    from PIL import Image

    server = LiveServer(0, lambda: state)
    server.start()
    try:
        # a profile of its own per run: the first run's group is killed when it returns, and a second run
        # on its profile can wait out its timeout on the lock the killed one left
        common = ["--virtual-time-budget=1500", "--window-size=1280,900"]
        dom = chromium(f"--user-data-dir={tmp_path / 'profile-dom'}", *common, "--dump-dom", server.url)
        shot = tmp_path / "page.png"
        chromium(f"--user-data-dir={tmp_path / 'profile-shot'}", *common, f"--screenshot={shot}", server.url)
        return dom, np.asarray(Image.open(shot).convert("RGB")).astype(int)
    finally:
        server.stop()


def polar(dom: str) -> str:
    """The polar plot as drawn (the page's script, also in the DOM, names its classes too)."""
    return re.search(r'<svg id="polar".*?</svg>', dom, re.S).group(0)


def red(picture: np.ndarray) -> np.ndarray:  # the bars' "above target" (#d9534f)
    r, g, b = picture[..., 0], picture[..., 1], picture[..., 2]
    return (r > 190) & (g > 60) & (g < 110) & (b > 55) & (b < 110)


def green(picture: np.ndarray) -> np.ndarray:  # "met" and the Done banner (#2e9d46)
    r, g, b = picture[..., 0], picture[..., 1], picture[..., 2]
    return (r < 80) & (g > 130) & (g < 175) & (b > 50) & (b < 100)


def target_line(picture: np.ndarray) -> np.ndarray:  # the target marker (#7b2cbf)
    r, g, b = picture[..., 0], picture[..., 1], picture[..., 2]
    return (abs(r - 0x7b) < 25) & (abs(g - 0x2c) < 25) & (abs(b - 0xbf) < 25)


def text(picture: np.ndarray) -> np.ndarray:  # dark glyphs (#222)
    return picture.max(axis=-1) < 90


def test_done_with_only_a_position_target_shows_no_red_and_no_next_placement(tmp_path):
    dom, picture = page(tmp_path, StubState(status(True, [12.0, 15.0, 20.0])))
    assert 'id="stop" class="shown"' in dom  # the green Done
    assert "rot x: 0.80 deg (no target)" in dom
    assert WORDS not in dom and 'class="suggested"' not in polar(dom)  # nothing left to suggest
    assert "none needed" in dom
    assert red(picture).sum() < 100, red(picture).sum()  # the polar plot's "now" legend only
    assert green(picture).sum() > 2000  # the banner and the three position bars


def test_labels_never_cross_the_target_line(tmp_path):
    dom, picture = page(tmp_path, StubState(status(False, [52.0, 35.0, 61.0])))
    assert WORDS in dom and 'class="suggested"' in polar(dom) and 'id="stop" class=""' in dom
    marks = target_line(picture)
    rows = np.flatnonzero(marks.any(axis=1))
    assert len(rows) >= 3 * 10  # three position bars' target lines
    columns = np.flatnonzero(marks.any(axis=0))
    band = slice(max(columns.min() - 40, 0), columns.max() + 40)
    # No glyph pixel in the rows of a target line, around it: the labels sit above the bars.
    assert text(picture[rows, band]).sum() == 0
    assert red(picture).sum() > 500  # the position bars above their target are red
