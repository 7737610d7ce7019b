"""The registry's database: its URL, its engine and its schema (created and migrated by Alembic).

URLs: ``sqlite:///path.db`` (embedded; several processes share it through WAL, a busy timeout and retries)
and ``postgresql://user@host:port/db`` (a fleet; read with psycopg 3: ``postgresql+psycopg://``). The
migrations ship inside the package (``migrations/versions``); a database is brought to the newest revision
the first time this code writes to it, under a lock (SQLite: one write transaction; PostgreSQL: an advisory
lock) so that concurrent first writers migrate it once. A database at a revision this code does not know (a
newer mirror-fg wrote it) is refused in one line (exit 2).
"""
from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.engine import Connection, make_url
from sqlalchemy.exc import ArgumentError

from mirror_fg.core.errors import DatasetError

__all__ = ["RegistryError", "registry_url", "make_engine", "ensure_schema", "head_revision", "database_revision",
           "MIGRATIONS"]

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
#: Seconds a SQLite writer waits for another's lock before the retry loop (store.py) takes over.
SQLITE_BUSY_TIMEOUT_S = 30.0
#: Seconds to wait for a PostgreSQL server to answer before the record is given up (a server that is down).
CONNECT_TIMEOUT_S = 10
#: The PostgreSQL advisory lock key under which the schema is migrated (any fixed 64-bit number).
_MIGRATION_LOCK = 0x6D6972726F72


class RegistryError(DatasetError):
    """The registry cannot be used (unreachable, full, read-only, a newer schema, a bad URL): exit 2, one line."""


def registry_url(url: str) -> str:
    """The SQLAlchemy URL of a registry URL (``postgresql://`` read with psycopg 3), or a RegistryError."""
    try:
        parsed = make_url(url)
    except ArgumentError:
        raise RegistryError(f"--registry {url[:80]!r}: not a database URL (sqlite:///path.db or "
                            "postgresql://user@host:port/db)") from None
    backend = parsed.get_backend_name()
    if backend == "postgresql":
        return parsed.set(drivername="postgresql+psycopg").render_as_string(hide_password=False)
    if backend == "sqlite":
        if not parsed.database or parsed.database == ":memory:":
            raise RegistryError(f"--registry {url[:80]!r}: a SQLite registry is a file (sqlite:///path.db)")
        return url
    raise RegistryError(f"--registry {url[:80]!r}: the registry is SQLite (sqlite:///path.db) or PostgreSQL "
                        f"(postgresql://user@host:port/db), not {backend}")


def describe(url: str) -> str:
    """The URL as printed in messages (no password)."""
    try:
        return make_url(url).render_as_string(hide_password=True)
    except ArgumentError:
        return url[:80]


def make_engine(url: str) -> Engine:
    """An engine for the registry at ``url`` (a registry URL, :func:`registry_url`). SQLite: WAL, a busy timeout
    and ``BEGIN IMMEDIATE`` (a writer takes the write lock when it starts, so two writers never deadlock
    upgrading their read locks)."""
    sa_url = registry_url(url)
    if sa_url.startswith("sqlite"):
        database = make_url(sa_url).database or ""
        if not make_url(sa_url).query.get("uri") and not os.path.isdir(os.path.dirname(os.path.abspath(database))):
            raise RegistryError(f"--registry {url[:80]!r}: the folder {os.path.dirname(database) or '.'} does not exist")
        engine = create_engine(sa_url, connect_args={"timeout": SQLITE_BUSY_TIMEOUT_S}, poolclass=_null_pool())
        event.listen(engine, "connect", _sqlite_connect)
        event.listen(engine, "begin", lambda conn: conn.exec_driver_sql("BEGIN IMMEDIATE"))
        return engine
    return create_engine(sa_url, connect_args={"connect_timeout": CONNECT_TIMEOUT_S}, pool_pre_ping=True)


def _null_pool() -> Any:
    from sqlalchemy.pool import NullPool

    return NullPool  # a connection per use: nothing held open between records (other processes write too)


def _sqlite_connect(dbapi_connection: Any, _record: Any) -> None:
    import sqlite3

    dbapi_connection.isolation_level = None  # the driver's own BEGIN off: ours (BEGIN IMMEDIATE) is emitted
    cursor = dbapi_connection.cursor()
    try:
        try:
            cursor.execute("PRAGMA journal_mode=WAL")  # readers never block the writer, nor it them
        except sqlite3.OperationalError:  # a read-only database: its writes fail later, by name
            pass
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute("PRAGMA synchronous=NORMAL")  # with WAL: a commit survives a killed process
    finally:
        cursor.close()


def _script() -> Any:
    from alembic.config import Config
    from alembic.script import ScriptDirectory

    config = Config()
    config.set_main_option("script_location", os.fspath(MIGRATIONS))
    return config, ScriptDirectory.from_config(config)


@functools.lru_cache(maxsize=1)
def head_revision() -> str:
    """The newest schema revision this code knows (the package's migrations: read once)."""
    return _script()[1].get_current_head()


@functools.lru_cache(maxsize=1)
def _revisions() -> frozenset[str]:
    """Every schema revision this code knows (read once: every reader checks the database's against them)."""
    return frozenset(script.revision for script in _script()[1].walk_revisions())


def database_revision(connection: Connection) -> str | None:
    """The database's schema revision (None: an empty database)."""
    from alembic.runtime.migration import MigrationContext

    return MigrationContext.configure(connection).get_current_revision()


def _known(revision: str | None) -> bool:
    return revision is None or revision in _revisions()


def check_revision(revision: str | None, url: str) -> None:
    """A RegistryError when ``revision`` is one this code does not know (a newer mirror-fg made the schema)."""
    if not _known(revision):
        raise RegistryError(f"registry {describe(url)}: its schema (revision {revision}) is newer than this "
                            f"mirror-fg knows (up to {head_revision()}), upgrade mirror-fg")


def ensure_schema(engine: Engine, url: str) -> None:
    """Bring the database to the newest revision (create it when empty), once among concurrent writers."""
    from alembic import command

    head = head_revision()
    with engine.connect() as connection:  # the common case: already there, nothing locked
        current = database_revision(connection)
        connection.rollback()
    check_revision(current, url)
    if current == head:
        return
    config, _ = _script()
    with engine.connect() as connection:
        if engine.dialect.name == "postgresql":  # one migrator at a time; the others wait here
            connection.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _MIGRATION_LOCK})
        else:
            connection.begin()  # BEGIN IMMEDIATE: SQLite's write lock until the commit
        current = database_revision(connection)  # another writer may have migrated it meanwhile
        check_revision(current, url)
        if current != head:
            config.attributes["connection"] = connection
            command.upgrade(config, "head")
        connection.commit()
