"""The resumable Monte Carlo log (analysis/trial_log.py) through its users, scripts/reproduce_fig4.py and
scripts/convergence.py: a torn last record, a torn line elsewhere, a full disk, two runs on one log."""
from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, load_script

from mirror_fg.core.errors import DatasetError
from mirror_fg.analysis.trial_log import TrialLog

POINTS = [("a", 0.5, 0.5)]
SMALL = dict(num_images=9, num_points=2, jobs=1, progress=False)


@pytest.fixture(scope="module")
def fig4():
    return load_script("reproduce_fig4")


@pytest.fixture(scope="module")
def two_runs(fig4, tmp_path_factory):
    """The log lines of the first two runs (seeds 0 and 1) of the small sweep, written by an undisturbed run."""
    log = tmp_path_factory.mktemp("reference") / "runs.jsonl"
    fig4.run_sweep(POINTS, 2, log_path=log, **SMALL)
    lines = log.read_bytes().splitlines(keepends=True)
    assert len(lines) == 2
    return lines


def _seeds(log: Path) -> list[int]:
    return sorted(json.loads(line)["seed"] for line in log.read_text().splitlines())


def test_a_torn_last_record_is_reported_and_its_trial_runs_again(fig4, two_runs, tmp_path, capsys):
    log = tmp_path / "runs.jsonl"
    log.write_bytes(two_runs[0] + two_runs[1][: len(two_runs[1]) // 2])  # the writer killed mid-record
    records = fig4.run_sweep(POINTS, 3, log_path=log, **SMALL)
    assert sorted(r["seed"] for r in records) == [0, 1, 2]
    assert _seeds(log) == [0, 1, 2]  # the torn fragment is gone, seed 1 written whole again
    again = {r["seed"]: r for r in records}
    assert again[1]["mle_pose"] == json.loads(two_runs[1])["mle_pose"]  # the same trial, the same answer
    err = capsys.readouterr().err
    assert "line 2 was cut short" in err and "runs again" in err


def test_a_torn_line_before_the_last_is_an_error_with_its_line_number(fig4, two_runs, tmp_path):
    log = tmp_path / "runs.jsonl"
    log.write_bytes(two_runs[0][:40] + two_runs[0] + two_runs[1])  # a fragment, then a later run appended
    with pytest.raises(DatasetError, match=r"runs\.jsonl, line 1: not a whole JSON record"):
        fig4.run_sweep(POINTS, 3, log_path=log, **SMALL)
    # The script: that one line and exit 2.
    out = tmp_path / "out"
    out.mkdir()
    (out / "runs.jsonl").write_bytes(two_runs[0] + b'{"seed": 1, "sigm\n' + two_runs[1])
    done = _script("convergence", "--runs", "1", "--images", "9", "--jobs", "1", "--no-progress", "--out", out)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().count("\n") == 0 and "runs.jsonl, line 2: not a whole JSON record" in done.stderr


def test_two_runs_on_one_log_the_second_stops_with_one_line(fig4, two_runs, tmp_path):
    log = tmp_path / "runs.jsonl"
    log.write_bytes(two_runs[0])
    with TrialLog(log):  # the first run, still going
        with pytest.raises(DatasetError, match="another run is writing this trial log"):
            fig4.run_sweep(POINTS, 2, log_path=log, **SMALL)
    assert log.read_bytes() == two_runs[0]  # the second run wrote nothing
    records = fig4.run_sweep(POINTS, 2, log_path=log, **SMALL)  # once the first is done
    assert sorted(r["seed"] for r in records) == [0, 1]


def test_a_log_written_twice_counts_every_trial_once(fig4, two_runs, tmp_path, capsys):
    log = tmp_path / "runs.jsonl"
    log.write_bytes(two_runs[0] + two_runs[1] + two_runs[1] + two_runs[0])  # two runs at once, before the lock
    records = fig4.run_sweep(POINTS, 2, log_path=log, **SMALL)
    assert sorted(r["seed"] for r in records) == [0, 1]
    assert "2 repeated trial record(s) ignored" in capsys.readouterr().err


def test_a_full_disk_mid_run_gives_one_line_and_a_resumable_log(fig4, two_runs, tmp_path):
    """The disk fills while the second record is written (a file-size limit makes write() fail with EFBIG
    after a part of it, as ENOSPC does): exit 2, one line, the log cut back to its first whole record."""
    out = tmp_path / "out"
    limit = len(two_runs[0]) + len(two_runs[1]) // 2

    def limit_file_size() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # write() fails instead of the process being killed
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    done = _script("reproduce_fig4", "--runs", "3", "--images", "9", "--points", "2", "--sigmas", "0.5",
                   "--distances", "", "--jobs", "1", "--no-progress", "--out", out, preexec_fn=limit_file_size)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().count("\n") == 0, done.stderr
    assert "runs.jsonl: cannot append a trial record" in done.stderr and "resume" in done.stderr
    assert (out / "runs.jsonl").read_text().endswith("\n") and _seeds(out / "runs.jsonl") == [0]
    records = fig4.run_sweep(POINTS, 3, log_path=out / "runs.jsonl", **SMALL)  # room again: it resumes
    assert sorted(r["seed"] for r in records) == [0, 1, 2] and _seeds(out / "runs.jsonl") == [0, 1, 2]


def _script(name: str, *args, preexec_fn=None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONDONTWRITEBYTECODE": "1"}
    return subprocess.run([sys.executable, str(REPO / "scripts" / f"{name}.py"), *map(str, args)], env=env,
                          capture_output=True, text=True, timeout=300, preexec_fn=preexec_fn, check=False)
