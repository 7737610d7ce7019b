"""docs/gaze_guide.md, sections 5-7: every command shown is run here (it must appear in the guide word for word),
and every line of output the guide shows is in what the command printed, its numbers within 2 %."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from conftest import REPO

GUIDE = REPO / "docs" / "gaze_guide.md"
NUMBER = re.compile(r"[-+]?\d+\.\d+|[-+]?\d+")


def guide_text() -> str:
    return GUIDE.read_text()


def section(title: str) -> str:
    text = guide_text()
    start = text.index(title)
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else len(text)]


def shown_outputs(text: str) -> list[list[str]]:
    """The ```text blocks of a section, each a list of lines (``...`` and elided lines left out)."""
    blocks = re.findall(r"```text\n(.*?)```", text, flags=re.S)
    return [[line for line in textwrap.dedent(block).splitlines() if line.strip() and "..." not in line]
            for block in blocks]


def same_line(shown: str, printed: str) -> bool:
    """The same words, and every number within 2 % (or 0.01)."""
    if NUMBER.sub("#", shown).strip() != NUMBER.sub("#", printed).strip():
        return False
    for a, b in zip(NUMBER.findall(shown), NUMBER.findall(printed)):
        if abs(float(a) - float(b)) > max(0.02 * abs(float(a)), 0.01):
            return False
    return True


def run(command: str, cwd: Path) -> str:
    """One command of the guide, as a user types it: ``python scripts/...`` or ``mirror-fg ...``."""
    assert command in guide_text(), command
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    if command.startswith("python scripts/"):
        argv = [sys.executable, str(REPO / command.split()[1]), *command.split()[2:]]
    else:
        assert command.startswith("mirror-fg ")
        argv = [sys.executable, "-m", "mirror_fg", *command.split()[1:]]
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, (command, done.stderr)
    return done.stdout


def check_shown(shown: list[str], printed: str) -> None:
    lines = printed.splitlines()
    for line in shown:
        assert any(same_line(line, p) for p in lines), (line, printed)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    folder = tmp_path_factory.mktemp("guide")
    run("python scripts/render_screen.py --out demo", folder)
    return folder / "demo"


def test_section_5_gaze_error(demo):
    printed = run("mirror-fg calibrate capture.yaml -o result.json --viewing-distance 0.6", demo)
    (shown,) = shown_outputs(section("## 5. How many degrees"))
    check_shown(shown, printed)


def test_section_6_exports(demo):
    if not (demo / "result.json").exists():
        run("mirror-fg calibrate capture.yaml -o result.json --viewing-distance 0.6", demo)
    for command in ("mirror-fg export result.json --to opengaze -o monitor.yml",
                    "mirror-fg export result.json --to eth-xgaze -o mirror_position.xml",
                    "mirror-fg export result.json --to few-shot-gaze -o calib_cam0.pkl"):
        run(command, demo)
    (shown,) = shown_outputs(section("## 6. The files your gaze tool reads"))
    head = (demo / "monitor.yml").read_text().splitlines()[:4]
    assert head[0] == shown[0] == "%YAML:1.0" and head[1].startswith("# written by mirror-fg")
    check_shown(shown[1:], "\n".join(head))
    # the monitor class the guide gives few_shot_gaze's demo, run on the exported file
    code = textwrap.dedent(re.search(r"```python\n( *import pickle.*?) *```", section("## 6."), flags=re.S).group(1))
    namespace: dict = {}
    here = os.getcwd()
    try:
        os.chdir(demo)
        exec(compile(code, "gaze_guide.md", "exec"), namespace)  # noqa: S102 - the guide's own example
        mon = namespace["monitor"]()
    finally:
        os.chdir(here)
    import json

    import numpy as np

    from mirror_fg.core.screen import Screen

    screen = Screen.from_result(json.loads((demo / "result.json").read_text()))
    np.testing.assert_allclose(mon.monitor_to_camera(960.5, 540.5), 1000 * screen.camera_point([960.5, 540.5]), atol=1e-9)
    np.testing.assert_allclose(mon.camera_to_monitor(*mon.monitor_to_camera(100.0, 900.0)), [100.0, 900.0], atol=1e-9)


def test_section_7_two_monitors(tmp_path):
    run("python scripts/render_screen.py --out two --screens 2", tmp_path)
    printed = run("mirror-fg calibrate capture.yaml -o result.json", tmp_path / "two")
    run("mirror-fg export result.json --to opengaze --screen right -o right_monitor.yml", tmp_path / "two")
    assert (tmp_path / "two" / "right_monitor.yml").read_text().startswith("%YAML:1.0")
    (shown,) = shown_outputs(section("## 7. Two or three monitors"))
    check_shown(shown, printed)
