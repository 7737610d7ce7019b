"""What a user reads points at docs/formats.md, never at a "SPEC" a clone does not have: the scripts (their
--help is their docstring) and what they print, and every command's -h (live's is its own module's)."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from conftest import load_script

from mirror_fg.cli import main

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("script", sorted(p.name for p in (REPO / "scripts").glob("*.py")))
def test_no_script_says_spec(script):
    assert not re.search(r"\bSPEC\b", (REPO / "scripts" / script).read_text(encoding="utf-8"))


def test_inspect_covariance_names_the_convention_in_docs_formats():
    inspect = load_script("inspect_covariance")
    eye = np.eye(3).tolist()
    transform = {"R": eye, "t": [0.0, 0.0, 0.0], "q_xyzw": [0.0, 0.0, 0.0, 1.0]}
    result = {"format": "mirror-fg/result@1", "T_cam_base": transform, "T_base_cam": transform,
              "covariance_cam_base": (np.eye(6) * 1e-6).tolist(),
              "sigma3_cam_base": {"rotation_deg": [0.0] * 3, "position_mm": [0.0] * 3},
              "optimizer": {"iterations": 1, "initial_error": 1.0, "final_error": 0.5, "converged": True},
              "residuals": {"rms_px": 1.0, "max_px": 3.0}}
    text, _ = inspect.report(result)
    assert "SPEC" not in text and "docs/formats.md's [dtheta, dt]" in text


@pytest.mark.parametrize("command", ["simulate", "calibrate", "calibrate-many", "detect", "report", "plan", "pattern"])
def test_command_help_does_not_say_spec(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "-h"])
    assert "SPEC" not in capsys.readouterr().out


#: The files that check a word is absent must name it.
_CHECKERS = {"tests/test_user_text.py", "tests/test_live_outputs.py"}


def test_the_repository_names_no_specification_or_issue_number_a_reader_does_not_have():
    """Comments, docstrings and pages cite docs/formats.md and the paper, not the project's private
    specification or its issue tracker (neither comes with a clone)."""
    found = []
    for folder in ("mirror_fg", "factors", "scripts", "tests", "docs"):
        for path in sorted((REPO / folder).rglob("*")):
            if path.suffix not in (".py", ".md", ".html", ".yaml") or path.relative_to(REPO).as_posix() in _CHECKERS:
                continue
            for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if re.search(r"\bSPEC\b|\b[Ii]ssues? #?\d+", line):
                    found.append(f"{path.relative_to(REPO)}:{number}: {line.strip()[:80]}")
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    found += [f"README.md: {m.group(0)}" for m in re.finditer(r"\bSPEC\b|\b[Ii]ssues? #?\d+", readme)]
    assert not found, "\n".join(found)
