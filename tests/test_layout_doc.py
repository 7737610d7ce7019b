"""docs/layout.md names every sub-package and only modules that exist, and no module imports a moved path."""
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAYOUT = (REPO / "docs" / "layout.md").read_text(encoding="utf-8")


def test_every_sub_package_is_in_the_layout():
    folders = sorted({p.parent.relative_to(REPO / "mirror_fg").as_posix()
                      for p in (REPO / "mirror_fg").rglob("__init__.py")} - {"."})
    missing = [f for f in folders if not f.startswith("registry/migrations")
               and f"{f.rsplit('/', 1)[-1]}/" not in LAYOUT]
    assert not missing, missing


def test_every_module_the_layout_names_exists():
    names = set(re.findall(r"\b([a-z_0-9]+\.(?:py|html))\b", LAYOUT))
    files = {p.name for p in REPO.rglob("*") if p.suffix in (".py", ".html") and ".venv" not in p.parts}
    assert names <= files, sorted(names - files)


def test_the_package_uses_no_moved_import_path():
    from mirror_fg._moved import MOVED

    old = re.compile(r"mirror_fg\.(" + "|".join(re.escape(k) for k in sorted(MOVED, key=len, reverse=True)) + r")(?![\w.])")
    found = [f"{p.relative_to(REPO)}: {m.group(0)}" for folder in ("mirror_fg", "factors", "scripts", "tests")
             for p in (REPO / folder).rglob("*.py") if p.name not in ("_moved.py", "test_layout_doc.py", "test_moved_paths.py")
             for m in old.finditer(p.read_text(encoding="utf-8"))]
    assert not found, found
