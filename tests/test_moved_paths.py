"""The old import paths of moved modules still import, for one release, as the module at the new path
(the same object: what a test patches at one is patched at the other), with a DeprecationWarning."""
import importlib
import subprocess
import sys

import pytest

from mirror_fg._moved import MOVED


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_path_is_the_new_module(old):
    new = importlib.import_module("mirror_fg." + MOVED[old])
    with pytest.warns(DeprecationWarning, match="moved to mirror_fg." + MOVED[old].replace(".", r"\.")):
        sys.modules.pop("mirror_fg." + old, None)
        moved = importlib.import_module("mirror_fg." + old)
    assert moved is new


def test_from_import_of_an_old_module_in_a_fresh_interpreter():
    code = ("import warnings; warnings.simplefilter('error')\n"
            "try:\n    from mirror_fg.tools import simulate\nexcept DeprecationWarning as w:\n    print('warned', w)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "warned mirror_fg.tools.simulate moved to mirror_fg.simulate.tree" in out.stdout, out.stderr


def test_the_incremental_package_hands_on_the_calibrator():
    from mirror_fg.solver.incremental import IncrementalCalibrator, calibrate_incremental
    from mirror_fg.solver.incremental import calibrator

    assert IncrementalCalibrator is calibrator.IncrementalCalibrator
    assert calibrate_incremental is calibrator.calibrate_incremental
