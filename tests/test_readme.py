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
