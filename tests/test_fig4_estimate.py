"""`scripts/reproduce_fig4.py` says how long it will take before it starts, and how to bound it."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_paper_size_run_warns_of_hours_and_names_the_time_budget(tmp_path):
    """One worker here (two start a pool that runs a few trials before the budget is looked at)."""
    run = subprocess.run([sys.executable, str(REPO / "scripts" / "reproduce_fig4.py"), "--runs", "100", "--jobs", "1",
                          "--time-budget", "0", "--out", str(tmp_path), "--no-progress"],
                         capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert run.returncode == 0, run.stderr[-2000:]
    first = run.stdout.splitlines()[0]
    assert "1300 runs (13 sweep points x 100) on 1 worker(s): about 4.0 h" in first, first
    assert "--time-budget MIN" in first
    assert "0 runs in the log" in run.stdout  # the budget of 0 minutes started none


def test_the_readme_command_is_estimated_at_two_hours():
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        import reproduce_fig4
    finally:
        sys.path.pop(0)
    line = reproduce_fig4.time_estimate(reproduce_fig4.sweep_points(), 100, 200, 2)
    assert "about 2.0 h" in line and "--time-budget" in line
