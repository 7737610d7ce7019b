"""plan --kind / --cameras (analysis/plan_views.py): Cramér-Rao bounds of the general set-ups and rigs."""
from __future__ import annotations

import subprocess
import sys

import numpy as np

import mirror_fg
from mirror_fg.analysis.plan_views import plan_views
from mirror_fg.simulate.rig import simulate_rig_tree


def test_rig_bound_is_the_covariance_calibrate_reports_on_that_scene() -> None:
    """One draw's bound (at the truth) against calibrate's covariance (at its estimate) on the same scene
    with noise: first order, the same within a few percent."""
    planned = plan_views("tree", cameras=2, draws=1, seed=3, pixel_sigma=0.5)
    data, _ = simulate_rig_tree(2, seed=3, pixel_sigma=0.5)
    cal = mirror_fg.calibrate(data)
    for name, pose in cal.cameras.items():
        sigma3 = 1000.0 * 3.0 * np.sqrt(np.diag(pose.covariance_base_cam))[3:]
        np.testing.assert_allclose(planned.cameras[name][1], sigma3, rtol=0.1)
    link = cal.rig[0]
    np.testing.assert_allclose(planned.rig["cam0 -> cam1"][1], link.sigma3["position_mm"], rtol=0.1)


def test_more_shared_placements_tie_the_rig_tighter() -> None:
    few = plan_views("tree", cameras=2, draws=2, seed=0, shared=1)
    many = plan_views("tree", cameras=2, draws=2, seed=0, shared=8)
    assert np.max(many.rig["cam0 -> cam1"][1]) < 0.5 * np.max(few.rig["cam0 -> cam1"][1])


def test_plan_cli_for_kaleidoscope_and_rigs(tmp_path) -> None:
    def run(*args):
        return subprocess.run([sys.executable, "-c", "import sys; from mirror_fg.cli import main; sys.exit(main())",
                               "plan", *args], capture_output=True, text=True, cwd=tmp_path, timeout=120)

    done = run("--kind", "kaleidoscope", "--draws", "1", "--json", "k.json")
    assert done.returncode == 0, done.stderr
    assert "camera: T_base_cam rotation" in done.stdout and (tmp_path / "k.json").exists()
    done = run("--cameras", "2", "--shared", "2,4", "--draws", "1")
    assert done.returncode == 0, done.stderr
    assert done.stdout.count("rig cam0 -> cam1") == 2
    for bad in (["--shared", "2"], ["--cameras", "2", "--shared", "x"], ["--cameras", "2", "--kind", "kaleidoscope"]):
        refused = run(*bad)
        assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1, (bad, refused.stderr)
