"""The package ships its types (py.typed) and mypy finds no error in it."""
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_py_typed_marker_is_installed_with_the_package():
    import mirror_fg

    assert (Path(mirror_fg.__file__).parent / "py.typed").exists()


def test_mypy_finds_no_error():
    pytest.importorskip("mypy")
    proc = subprocess.run([sys.executable, "-m", "mypy", "mirror_fg", "factors", "--ignore-missing-imports",
                           "--cache-dir", str(REPO / ".mypy_cache")],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:]
