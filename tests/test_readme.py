"""The README's set-up commands stay true: CI runs the test command verbatim, the example exists."""
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _readme_commands() -> list[str]:
    text = (REPO / "README.md").read_text()
    section = text.split("## Set up on a fresh machine", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```bash\n(.*?)\n```", section, flags=re.S)


def test_readme_has_exactly_two_setup_commands():
    commands = _readme_commands()
    assert len(commands) == 2
    install_and_run, run_tests = commands
    assert "mirror-fg calibrate examples/base_case.json" in install_and_run
    assert (REPO / "examples" / "base_case.json").exists()
    assert "pytest" in run_tests


def test_ci_runs_the_readme_test_command():
    ci = (REPO / ".ci" / "run").read_text().splitlines()
    assert _readme_commands()[1] in ci


def test_readme_python_example_runs(tmp_path, monkeypatch):
    text = (REPO / "README.md").read_text()
    code = re.search(r"## Python API\n\n```python\n(.*?)```", text, re.S).group(1)
    monkeypatch.chdir(REPO)
    code = code.replace('"result.json"', repr(str(tmp_path / "result.json")))
    namespace: dict = {"print": lambda *args: None}
    exec(compile(code, "README.md", "exec"), namespace)
    assert (tmp_path / "result.json").exists()
    assert namespace["final"].covariance.shape == (6, 6)


def test_readme_setup_examples_run(tmp_path):
    """Each set-up's example (tree, fixed mirror, kaleidoscope, no known target, rig) runs and writes its
    result; the rig's also its camchain and URDF with every camera."""
    import json
    import subprocess
    import sys

    text = (REPO / "README.md").read_text()
    section = text.split("## Set-ups:", 1)[1].split("\n## ", 1)[0]
    commands = re.findall(r"```bash\n(.*?)\n```", section, flags=re.S)
    assert len(commands) == 5
    mirror_fg = f"{sys.executable} -c 'import sys; from mirror_fg.cli import main; sys.exit(main())'"
    for command in commands:
        run = subprocess.run(command.replace("mirror-fg ", f"{mirror_fg} "), shell=True, cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, (command, run.stderr[-2000:])
    for name in ("tree", "fixed", "kal", "free", "rig"):
        assert (tmp_path / f"{name}.result.json").exists()
    rig = json.loads((tmp_path / "rig.result.json").read_text())
    assert list(rig["cameras"]) == ["cam0", "cam1"] and len(rig["rig"]) == 1
    assert "cam1_optical_frame" in (tmp_path / "rig.result.urdf.xml").read_text()
    assert "T_cn_cnm1" in (tmp_path / "rig.result.camchain.yaml").read_text()
