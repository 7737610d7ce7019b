"""The registry under load and under SIGKILL: 8 writer processes x 250 records, and 8 Dask workers x 250 recording
as calibrate-many's do, lose and duplicate nothing (SQLite and PostgreSQL), a writer killed inside a run's
transaction leaves that run out whole, and calibrate-many records from its Dask workers."""
from __future__ import annotations

import itertools
import json
import os
import signal
import sqlite3
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
from sqlalchemy import text

from mirror_fg.registry import Registry

REPO = Path(__file__).resolve().parents[1]
WRITER = Path(__file__).resolve().parent / "registry_writer.py"
WRITERS, PER_WRITER = 8, 250
_names = itertools.count()


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request, tmp_path) -> str:
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'registry.db'}"
    return request.getfixturevalue("postgres_cluster").new_database(f"load_{next(_names)}")


def _env() -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))


@pytest.mark.parametrize("per_writer", [pytest.param(PER_WRITER, marks=pytest.mark.slow), 25])
def test_concurrent_writers_lose_nothing(url, per_writer):
    """8 processes start together on an empty database (they also race to create its schema): the goal's 8 x 250
    (slow: 20 to 60 s on a busy 2-core machine) and 8 x 25 for CI."""
    writers = [subprocess.Popen([sys.executable, str(WRITER), url, f"w{n}", str(per_writer)], env=_env(),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for n in range(WRITERS)]
    for writer in writers:
        _, err = writer.communicate(timeout=600)
        assert writer.returncode == 0, err[-2000:]
    with Registry(url) as registry:
        records = registry.history("fleet")
        with registry.engine.connect() as connection:
            tags = [json.loads(d)["test_tag"] if isinstance(d, str) else d["test_tag"]
                    for d in connection.execute(text("SELECT document FROM runs")).scalars()]
    expected = {f"w{n}-{i}" for n in range(WRITERS) for i in range(per_writer)}
    assert len(records) == WRITERS * per_writer == len(expected)  # 2,000 in the goal's test
    assert Counter(tags) == Counter(expected)  # each exactly once
    assert len({r.run_id for r in records}) == len(expected)


@pytest.mark.parametrize("per_worker", [pytest.param(PER_WRITER, marks=pytest.mark.slow), 25])
def test_dask_workers_lose_nothing(url, per_worker):
    """8 Dask worker processes record as calibrate-many's workers do (``registry.cli.record_row``, one Registry per
    input), one input per task: the goal's 8 x 250 (slow) and 8 x 25 for CI."""
    from registry_writer import record_in_worker

    from mirror_fg.analysis.montecarlo import run_trials

    todo = [{"url": url, "tag": f"d{n}-{i}"} for i in range(per_worker) for n in range(WRITERS)]
    rows = run_trials(record_in_worker, todo, [], total=len(todo), progress=False, jobs=WRITERS)
    assert [r["error"] for r in rows if r["error"] is not None] == []
    assert len({r["pid"] for r in rows}) > 1  # written from several worker processes at once
    with Registry(url) as registry:
        records = registry.history("fleet")
        with registry.engine.connect() as connection:
            tags = [json.loads(d)["test_tag"] if isinstance(d, str) else d["test_tag"]
                    for d in connection.execute(text("SELECT document FROM runs")).scalars()]
    expected = [item["tag"] for item in todo]
    assert len(records) == WRITERS * per_worker == len(set(expected))  # 2,000 in the goal's test
    assert Counter(tags) == Counter(expected)  # each exactly once


def test_a_writer_killed_mid_run_leaves_it_out_whole(url):
    """The writer records rigs of 4 cameras; it is killed after its third run's rows are inserted, before that
    run commits: the database holds the first two runs, each with its 4 rows, and takes new records."""
    writer = subprocess.Popen([sys.executable, str(WRITER), url, "k", "10", "4", "--slow"], env=_env(),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    try:
        for line in writer.stdout:
            lines.append(line.strip())
            if line.startswith("inserted") and line.split()[-1] == "3":
                break
    finally:
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait(timeout=60)
    assert lines[-1] == "inserted camera rows of run 3", lines + [writer.stderr.read()[-2000:]]
    committed = [line for line in lines if line.startswith("committed")]
    with Registry(url) as registry:
        records = registry.history("killed")
        per_run = Counter(r.run_id for r in records)
        assert len(per_run) == len(committed) == 2 and set(per_run.values()) == {4}
        registry.record("killed", json.loads(json.dumps({"format": "mirror-fg/result@1"})))  # not left locked
        with registry.engine.connect() as connection:
            assert connection.execute(text("SELECT count(*) FROM runs")).scalar() == 3
    if url.startswith("sqlite"):
        path = url.removeprefix("sqlite:///")
        assert sqlite3.connect(path).execute("PRAGMA integrity_check").fetchone()[0] == "ok"


def test_calibrate_many_records_from_its_dask_workers(tmp_path):
    """Four small datasets through a local Dask cluster of 2 workers, each recording its run: 4 robots
    (the inputs' names), one calibration each, their files written."""
    from mirror_fg.cli import main

    inputs = []
    for n in range(4):
        path = tmp_path / f"robot{n}.json"
        assert main(["simulate", "-o", str(path), "--images", "30", "--seed", str(n), "-q"]) == 0
        inputs.append(str(path))
    url = f"sqlite:///{tmp_path / 'fleet.db'}"
    done = subprocess.run([sys.executable, "-m", "mirror_fg", "calibrate-many", *inputs, "-o", str(tmp_path / "out"),
                           "--dask", "--workers", "2", "-q", "--registry", url],
                          env=_env(), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    with Registry(url) as registry:
        assert registry.robots() == [f"robot{n}" for n in range(4)]
        for n in range(4):
            [record] = registry.history(f"robot{n}")
            stored = registry.latest(f"robot{n}").document
            written = json.loads((tmp_path / "out" / f"robot{n}.result.json").read_text())
            assert stored["T_base_cam"] == written["T_base_cam"] and record.input_sha256 is not None
