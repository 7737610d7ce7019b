"""The documentation site builds without a broken link (mkdocs --strict), and every command its pages
show runs as it is: each ```bash block runs in a temporary folder that holds the repository's
``examples/`` and ``scripts/`` (as a clone's root does); a block that cannot run there (a camera, photographs
of your own, minutes of work) is a ```console block."""
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
CLI = f"{sys.executable} -c 'import sys; from mirror_fg.cli import main; sys.exit(main())'"
# Pages whose ```bash blocks another test runs, word for word.
COVERED_ELSEWHERE = {"gaze_guide.md": "tests/test_gaze_guide.py", "index.md": "test_quick_start_matches_readme_and_runs"}


def _bash_blocks(page: Path) -> list[str]:
    return re.findall(r"```bash\n(.*?)\n```", page.read_text(), flags=re.S)


def _run(command: str, cwd: Path) -> subprocess.CompletedProcess:
    """A block's lines run in turn in one shell (comment lines and trailing ``# ...`` comments dropped), as
    ``mirror-fg`` and ``python`` of this checkout."""
    lines = [re.sub(r"\s+#.*$", "", part) for part in command.splitlines() if part.strip() and not part.startswith("#")]
    line = " && ".join(re.sub(r"^python ", f"{sys.executable} ", part) for part in lines)
    return subprocess.run(line.replace("mirror-fg ", f"{CLI} "), shell=True, cwd=cwd, capture_output=True,
                          text=True, timeout=300, env={**__import__("os").environ, "PYTHONPATH": str(REPO)})


def _clone_root(folder: Path) -> Path:
    """``folder`` made to look like a clone's root for the pages' commands (examples and scripts linked)."""
    for name in ("examples", "scripts"):
        (folder / name).symlink_to(REPO / name, target_is_directory=True)
    return folder


def test_site_builds_strict(tmp_path):
    pytest.importorskip("mkdocs", reason="mkdocs is in the [test] and [docs] extras: pip install '.[docs]'")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
                          cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "T_cam_base" in api and "IncrementalCalibrator" in api  # docstrings rendered, not just headings


def test_every_page_is_in_the_navigation():
    import yaml

    nav = yaml.safe_load((REPO / "mkdocs.yml").read_text())["nav"]
    listed = set(re.findall(r"[\w/.-]+\.md", str(nav)))
    pages = {str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")}
    assert pages == listed, f"pages outside the navigation: {pages - listed}; missing pages: {listed - pages}"


@pytest.mark.parametrize("page", sorted(p.name for p in (DOCS / "setups").glob("*.md")))
def test_setup_page_commands_run(page, tmp_path):
    blocks = _bash_blocks(DOCS / "setups" / page)
    assert blocks, f"{page} shows no runnable example"
    _clone_root(tmp_path)
    for command in blocks:
        run = _run(command, tmp_path)
        assert run.returncode == 0, (command, run.stderr[-2000:])
    written = [p for p in tmp_path.rglob("*.result.json") if "examples" not in p.parts]
    assert written, f"{page}'s example wrote no result"


OTHER_PAGES = sorted(str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")
                     if p.parent != DOCS / "setups" and p.name not in COVERED_ELSEWHERE)


@pytest.mark.parametrize("page", OTHER_PAGES)
def test_other_page_commands_run(page, tmp_path):
    """Every ```bash block of the guides and reference pages runs as shown and says what the page says it
    does (exit 0); pages without one pass."""
    _clone_root(tmp_path)
    for command in _bash_blocks(DOCS / page):
        run = _run(command, tmp_path)
        assert run.returncode == 0, (page, command, run.stderr[-2000:])


def test_pages_say_which_blocks_do_not_run():
    """A shell block is ```bash (run by a test) or ```console (shown only): a bare ``` fence around a
    mirror-fg command would escape both."""
    for page in DOCS.rglob("*.md"):
        for block in re.findall(r"```\n(.*?)\n```", page.read_text(), flags=re.S):
            assert not re.search(r"^(mirror-fg|python) ", block, flags=re.M), (page.name, block[:200])


def test_quick_start_matches_readme_and_runs(tmp_path):
    install, after = _bash_blocks(DOCS / "index.md")[:2]
    readme = (REPO / "README.md").read_text().split("## Set up on a fresh machine", 1)[1]
    assert install in readme  # the site's install command is the README's
    shutil.copytree(REPO / "examples", tmp_path / "examples")
    assert _run("mirror-fg " + install.split("&& .venv/bin/mirror-fg ", 1)[1], tmp_path).returncode == 0
    commands = "\n".join(line for line in after.splitlines() if "activate" not in line)
    run = _run(commands, tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert (tmp_path / "report").is_dir()
