"""Kill-safety of the registry at any instant (docs/formats.md "Has it moved?", "Registry"): a writer
SIGKILLed at every statement boundary of a record (after each statement the driver executed, just before and
just after each commit; tests/registry_killer.py), on a database at the newest schema and on empty ones (the
kill then falls in the migrations too), and at random instants while recording in a loop, on SQLite and on a
real PostgreSQL server: the database then holds each record whole (every camera of the rig) or not at all,
the records a kill spared are exactly those whose commit was done, and a later run records and reads its
history."""
from __future__ import annotations

import itertools
import os
import sqlite3
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
from registry_docs import result_document
from sqlalchemy import text

from mirror_fg.registry import Registry

REPO = Path(__file__).resolve().parents[1]
KILLER = Path(__file__).resolve().parent / "registry_killer.py"
CAMERAS = 3
ROBOT = "killed"
_names = itertools.count()


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request, tmp_path):
    """``(url of an empty database, pattern of fresh ones with {k})`` on each backend."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'registry.db'}", f"sqlite:///{tmp_path}/fresh_{{k}}.db"
    cluster = request.getfixturevalue("postgres_cluster")
    n = next(_names)
    return cluster.new_database(f"kill_{n}"), f"{cluster.url(f'kill_{n}_fresh_{{k}}')}"


def _kill(*args: str) -> list[tuple[str, int]]:
    environment = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run([sys.executable, str(KILLER), *args], capture_output=True, text=True, timeout=600,
                          env=environment)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = [line.split() for line in done.stdout.splitlines()]
    assert all(len(w) == 2 and w[0] in ("killed", "whole") for w in lines), done.stdout[-2000:]
    return [(w[0], int(w[1])) for w in lines]


def _runs(url: str) -> dict[str, int]:
    """``{tag: cameras recorded}`` of the robot's runs, checked whole: no record without its run, no run
    without its records."""
    with Registry(url) as registry:
        records = registry.history(ROBOT)
        per_run = Counter(r.run_id for r in records)
        tags = {registry.document(run)["test_tag"]: count for run, count in per_run.items()}
        with registry.engine.connect() as connection:
            runs = connection.execute(text("SELECT count(*) FROM runs WHERE robot = :r"), {"r": ROBOT}).scalar()
            orphans = connection.execute(text("SELECT count(*) FROM records WHERE run_id NOT IN "
                                              "(SELECT id FROM runs)")).scalar()
    assert runs == len(per_run) and orphans == 0
    return tags


def _sound(url: str) -> None:
    if url.startswith("sqlite"):
        assert sqlite3.connect(url.removeprefix("sqlite:///")).execute("PRAGMA integrity_check").fetchone()[0] == "ok"


def _spared_are_the_committed(outcomes: list[tuple[str, int]], present: set[int]) -> None:
    """Killed before the commit: absent; from the instant after it (and the run that outlived every
    kill): present; nothing in between."""
    *killed, (last, total) = outcomes
    assert last == "whole" and [k for _, k in killed] == list(range(1, total))
    assert total in present and 1 not in present
    first = min(present)
    assert present == set(range(first, total + 1)), (sorted(present), total)


def test_killed_at_every_boundary_of_a_record(backend):
    url, _ = backend
    with Registry(url) as registry:  # the schema and a record already there
        registry.record(ROBOT, result_document(tag="before"))
    outcomes = _kill("every", url, str(CAMERAS))
    runs = _runs(url)
    assert runs.pop("before") == 1
    assert set(runs.values()) == {CAMERAS}  # each whole
    _spared_are_the_committed(outcomes, {int(tag[1:]) for tag in runs})
    assert len(outcomes) >= 5  # statements, the commit's two sides: every one of them was a kill instant
    with Registry(url) as registry:  # a later run records and reads
        registry.record(ROBOT, result_document(tag="after"))
    assert "after" in _runs(url)
    _sound(url)


def test_killed_at_every_boundary_of_a_first_record(backend):
    """Each kill on an empty database: inside the schema's creation (Alembic's migrations) too."""
    _, pattern = backend
    outcomes = _kill("fresh", pattern, str(CAMERAS))
    present = set()
    for _, k in outcomes:
        url = pattern.format(k=k)
        with Registry(url) as registry:  # a later run: migrates what the kill left and records
            registry.record(ROBOT, result_document(tag="later"))
        runs = _runs(url)
        assert runs.pop("later") == 1 and set(runs.values()) <= {CAMERAS}, (k, runs)
        if runs:
            present.add(k)
        _sound(url)
    _spared_are_the_committed(outcomes, present)
    assert len(outcomes) > 10  # the migrations' statements were kill instants too


def test_killed_at_random_instants(backend):
    url, _ = backend
    outcomes = _kill("random", url, str(CAMERAS), "8", "5")
    assert [s for s, _ in outcomes].count("killed") == 8
    runs = _runs(url)
    assert set(runs.values()) == {CAMERAS} and {f"r{i}-0" for i in range(8)} <= set(runs)
    with Registry(url) as registry:
        registry.record(ROBOT, result_document(tag="after"))
        assert len(registry.history(ROBOT)) == CAMERAS * len(runs) + 1
    _sound(url)
