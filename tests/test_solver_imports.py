"""The pipeline and the pixel problem without an import circle: ``intrinsics.py`` is below
``calibrate.py``, which imports it at the top (through ``pixel_problem.py``, the pixel problem of the
pipeline); neither imports the other inside a function."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

SOLVER = Path(__file__).resolve().parents[1] / "mirror_fg" / "solver"


def _imports(path: Path) -> tuple[set[str], set[str]]:
    """The modules ``path`` imports at module level and inside functions."""
    tree = ast.parse(path.read_text())
    top: set[str] = set()
    inner: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for inside in ast.walk(node):
                if isinstance(inside, ast.ImportFrom) and inside.module:
                    inner.add(inside.module)
                elif isinstance(inside, ast.Import):
                    inner.update(alias.name for alias in inside.names)
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module:
            top.add(node.module)
        elif isinstance(node, ast.Import):
            top.update(alias.name for alias in node.names)
    return top, inner


def test_calibrate_and_intrinsics_import_each_other_in_one_direction_only():
    calibrate_top, calibrate_inner = _imports(SOLVER / "calibrate.py")
    pixel_top, pixel_inner = _imports(SOLVER / "pixel_problem.py")
    intrinsics_top, intrinsics_inner = _imports(SOLVER / "intrinsics.py")
    assert "mirror_fg.solver.batch.pixel_problem" in calibrate_top and "mirror_fg.solver.batch.intrinsics" in pixel_top
    assert "mirror_fg.solver.batch.intrinsics" not in calibrate_inner | pixel_inner
    assert "mirror_fg.solver.calibrate" not in pixel_top | pixel_inner
    assert "mirror_fg.solver.calibrate" not in intrinsics_top | intrinsics_inner


def test_the_pixel_problem_loads_without_the_pipeline():
    code = "import sys, mirror_fg.solver.batch.intrinsics; print('mirror_fg.solver.calibrate' in sys.modules)"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "False"


def test_the_general_view_model_does_not_import_the_pipeline_entry_back():
    """calibrate.py imports views_solve.py; views_solve.py reaches the tree problem directly (its rule 2),
    never calibrate.py (at the top or inside a function)."""
    calibrate_top, _ = _imports(SOLVER / "calibrate.py")
    views_top, views_inner = _imports(SOLVER / "views_solve.py")
    assert "mirror_fg.solver.batch.views_solve" in calibrate_top
    assert "mirror_fg.solver.calibrate" not in views_top | views_inner
