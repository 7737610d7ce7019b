"""The README's set-up commands stay true: CI runs the test command verbatim, the example exists; the
command-line synopsis (docs/cli.md) lists every option of every command, and every command the README and
the site's pages show uses only options its parser and the synopsis know."""
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
    assert namespace["verdict"].level == "good" and namespace["verdict"].line.startswith("verdict: looks right")


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


def _mirror_fg_cli(args: list[str], cwd: Path) -> str:
    """``mirror-fg ARGS`` run in ``cwd`` (this checkout's mirror_fg, as the README runs it), its stdout."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", "import sys; from mirror_fg.cli import main; sys.exit(main())", *args],
                         cwd=cwd, capture_output=True, text=True, timeout=300,
                         env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert run.returncode == 0, (args, run.stderr[-2000:])
    return run.stdout


def _text_blocks(text: str) -> list[list[str]]:
    return [block.splitlines() for block in re.findall(r"```text\n(.*?)\n```", text, flags=re.S)]


def test_readme_takahashi_verdict_is_what_calibrate_prints_and_stores(tmp_path):
    """The README quotes the real photographs' verdict: the console prints it, the result stores it, and the
    report's headline is that verdict's (the report said "Check before use" while the console said
    "looks right")."""
    import json

    quotes = []
    for document in (REPO / "README.md", REPO / "docs" / "cli.md"):
        section = document.read_text().split("Real photographs (Takahashi et al., CVPR 2012", 1)[1].split("\n## ", 1)[0]
        (command,) = re.findall(r"```bash\n(mirror-fg calibrate .*?)\n```", section)
        quotes += [line for block in _text_blocks(section) for line in block if line.startswith("verdict:")]
    quoted = quotes[0]
    assert quotes == [quoted, quoted], "README.md and docs/cli.md quote different verdicts"
    out = _mirror_fg_cli(command.split()[1:-2] + ["-o", str(tmp_path / "takahashi.json")], REPO)
    (printed,) = [line for line in out.splitlines() if line.startswith("verdict:")]
    assert printed == quoted
    verdict = json.loads((tmp_path / "takahashi.json").read_text())["verdict"]
    assert verdict["console"] == printed and verdict["level"] == "check"
    assert verdict["headline"] == "Check before use: residuals grow towards the image edge (distortion)"


def _guide() -> str:
    return (REPO / "docs" / "gaze_guide.md").read_text()


def test_gaze_guide_and_readme_screen_figures_are_what_the_tool_prints(tmp_path):
    """docs/gaze_guide.md section 3 quotes `mirror-fg calibrate` on `scripts/render_screen.py`'s capture, at its
    pixel_sigma 0.3 and at the 0.07 px the verdict says the residuals fit; docs/setups/screen.md quotes the same bounds,
    and the guide's Python example prints what it says."""
    import subprocess
    import sys

    subprocess.run([sys.executable, str(REPO / "scripts" / "render_screen.py"), "--out", str(tmp_path)], check=True,
                   capture_output=True, timeout=300, env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    section = _guide().split("## 3. ", 1)[1].split("\n## ", 1)[0]
    first, second = _text_blocks(section)[:2]
    capture = tmp_path / "capture.yaml"
    assert "pixel_sigma: 0.3\n" in capture.read_text()
    printed = _mirror_fg_cli(["calibrate", "capture.yaml", "-o", "result.json"], tmp_path).splitlines()
    for line in first:
        if line != "...":
            assert line in printed, (line, printed)
    example = re.search(r"```python\n(import json\n.*?)```", _guide(), re.S).group(1)
    run = subprocess.run([sys.executable, "-c", example], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    expected = re.search(r"prints, for the result above,\n\n```text\n(.*?)\n```", _guide(), re.S).group(1)
    assert run.stdout.strip() == expected.strip(), run.stderr[-1000:]
    capture.write_text(capture.read_text().replace("pixel_sigma: 0.3\n", "pixel_sigma: 0.07\n"))
    again = _mirror_fg_cli(["calibrate", "capture.yaml", "-o", "result.json"], tmp_path).splitlines()
    for line in second:
        assert line in again, (line, again)
    readme = (REPO / "docs" / "setups" / "screen.md").read_text()
    bounds = re.findall(r"\[([0-9., ]+)\] deg and \[([0-9., ]+)\] mm", " ".join(readme.split()))
    assert len(bounds) == 2
    for (deg, mm), lines in zip(bounds, (printed, again)):
        assert any(f"rotation ±[{deg}] deg, base origin ±[{mm}] mm" in line for line in lines), (deg, mm)


_OPTION = re.compile(r"(?<![\w-])(--?[a-zA-Z][\w-]*)")


def _synopsis() -> dict[str, set[str]]:
    """Each command's options in the synopsis on docs/cli.md (its lines and their indented continuations),
    and the options every command takes under ``"*"``."""
    text = (REPO / "docs" / "cli.md").read_text()
    block = re.search(r"## Synopsis\n\n```text\n(.*?)\n```", text, re.S).group(1)
    options: dict[str, set[str]] = {"*": set()}
    command = None
    for line in block.splitlines():
        if line.startswith("mirror-fg "):
            command = line.split()[1]
            line = line.split(None, 2)[2] if len(line.split()) > 2 else ""
        elif line.startswith("every command"):
            command = "*"
        options.setdefault(command, set()).update(_OPTION.findall(line))
    return options


def _readme_invocations() -> list[tuple[str, list[str]]]:
    """``(command, options)`` of every ``mirror-fg COMMAND ...`` in the shell examples (bash and console)
    and inline code of the README and the site's pages."""
    text = "\n".join(page.read_text() for page in [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))])
    snippets = re.findall(r"```(?:bash|console)\n(.*?)\n```", text, flags=re.S) + re.findall(r"`(mirror-fg [^`]+)`", text)
    found = []
    for snippet in snippets:
        for line in snippet.splitlines():
            line = line.split("#", 1)[0]
            for part in re.split(r"&&|;|\|\|", line):
                words = part.split()
                if len(words) >= 2 and words[0] == "mirror-fg" and not words[1].startswith(("-", ".")) and not words[1].isupper():
                    found.append((words[1], _OPTION.findall(" ".join(words[2:]))))
    return found


def _parser_options() -> dict[str, list[list[str]]]:
    import argparse

    from mirror_fg.cli.parser import build_parser

    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return {name: [a.option_strings for a in parser._actions if a.option_strings] for name, parser in sub.choices.items()}


def test_every_option_the_readme_uses_is_in_its_synopsis_and_its_parser():
    synopsis, parser = _synopsis(), _parser_options()
    invocations = _readme_invocations()
    assert len(invocations) > 20 and {"plan", "simulate", "calibrate"} <= {c for c, _ in invocations}
    for command, options in invocations:
        known = {o for strings in parser[command] for o in strings}
        for option in options:
            assert option in known, f"the docs run mirror-fg {command} {option}, which its parser does not take"
            assert option in synopsis.get(command, set()) | synopsis["*"], \
                f"the docs run mirror-fg {command} {option}, which the synopsis does not list"


def test_the_synopsis_lists_every_option_of_every_command():
    synopsis, parser = _synopsis(), _parser_options()
    assert set(parser) <= set(synopsis)
    for command, actions in parser.items():
        for strings in actions:
            assert set(strings) & (synopsis[command] | synopsis["*"]), f"synopsis lacks mirror-fg {command} {strings}"


def test_the_setup_says_to_activate_the_environment_before_bare_commands():
    text = (REPO / "README.md").read_text()
    section = text.split("## Set up on a fresh machine", 1)[1].split("\n## ", 1)[0]
    assert "`. .venv/bin/activate`" in section
    assert text.index(". .venv/bin/activate") < text.index("\nmirror-fg calibrate examples/takahashi2012")
