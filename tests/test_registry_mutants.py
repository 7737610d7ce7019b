"""The registry's retry on a locked SQLite database: retried while SQLite says locked or busy, any other
database error raised at once (not retried for minutes as if it were a lock)."""
from __future__ import annotations

import sqlite3

import pytest
from sqlalchemy.exc import OperationalError

import mirror_fg.registry.store as store
from mirror_fg.registry import Registry


def _failing(messages: list[str], calls: list[int]):
    """A unit of work that raises SQLite's OperationalError with each of ``messages`` in turn, then returns 7."""
    def work() -> int:
        calls.append(1)
        if len(calls) <= len(messages):
            raise OperationalError("INSERT INTO runs ...", {}, sqlite3.OperationalError(messages[len(calls) - 1]))
        return 7
    return work


@pytest.fixture
def registry(tmp_path, monkeypatch):
    monkeypatch.setattr(store._time, "sleep", lambda seconds: None)  # the back-off's pauses, not its logic
    with Registry(f"sqlite:///{tmp_path / 'r.db'}") as r:
        yield r


def test_a_locked_or_busy_database_is_retried_until_it_is_free(registry):
    calls: list[int] = []
    assert registry._retry(_failing(["database is locked", "database table is busy"], calls)) == 7
    assert len(calls) == 3


def test_another_database_error_is_raised_at_once(registry):
    calls: list[int] = []
    with pytest.raises(OperationalError, match="disk I/O error"):
        registry._retry(_failing(["disk I/O error"], calls))
    assert len(calls) == 1
