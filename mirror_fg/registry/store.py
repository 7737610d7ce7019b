"""``Registry(url)``: record runs, read a robot's history and its latest calibration.

A run is recorded in one transaction: its document and one row per camera, all or none (a process killed at
any instant leaves the run or nothing). SQLite writers that meet another's lock wait (busy timeout) and then
retry with a random back-off, so concurrent processes lose nothing; PostgreSQL serialises the inserts itself.
Every failure of the database (down, full, read-only, a newer schema) is a one-line :class:`RegistryError`.
"""
from __future__ import annotations

import gc
import os
import random
import socket
import time as _time
from collections.abc import Callable, Mapping
from datetime import datetime, timezone
from typing import Any, TypeVar

from sqlalchemy import select, type_coerce
from sqlalchemy.engine import Connection
from sqlalchemy.exc import DBAPIError, OperationalError, SQLAlchemyError
from sqlalchemy.orm import Session
from sqlalchemy.types import NullType

from mirror_fg.registry.models import CameraRecord, Run
from mirror_fg.registry.records import CameraRow, HistoryRecord, camera_rows, document_kind, input_sha256
from mirror_fg.registry.schema import (
    RegistryError,
    database_revision,
    describe,
    ensure_schema,
    make_engine,
    check_revision,
)

__all__ = ["Registry", "RegistryError"]

#: PostgreSQL's SQLSTATE of a full disk (``disk_full``: a file could not be extended or written).
DISK_FULL_SQLSTATE = "53100"
#: Seconds a SQLite writer keeps retrying a locked database (after each busy timeout) before it gives up.
LOCKED_RETRY_S = 120.0
_T = TypeVar("_T")


class Registry:
    """The calibration registry at ``url`` (``sqlite:///path.db`` or ``postgresql://user@host:port/db``).

    ``record`` stores a run, ``history`` lists a robot's records in time order, ``latest`` its newest
    calibration with the whole document. Raises :class:`RegistryError` (exit 2, one line) when the database
    cannot be used.
    """

    def __init__(self, url: str) -> None:
        self.url = url
        self.engine = make_engine(url)
        self._migrated = False

    def __repr__(self) -> str:
        return f"Registry({describe(self.url)!r})"

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> Registry:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- writing --------------------------------------------------------------------------------------

    def record(self, robot: str, document: Mapping[str, Any], *, input_path: str | os.PathLike[str] | None = None,
               sha256: str | None = None, time: datetime | None = None) -> list[HistoryRecord]:
        """Store ``document`` (a result@1 or verification@1) for ``robot``: one record per camera, in one
        transaction. ``input_path``: the dataset or capture it came from (its sha256 is stored; ``sha256``
        gives it instead); ``time``: the run's time (default now, UTC). Returns the stored records."""
        robot = _check_robot(robot)
        kind = document_kind(document)
        rows = camera_rows(document)
        when = (time or datetime.now(timezone.utc)).astimezone(timezone.utc)
        digest = sha256 if sha256 is not None else input_sha256(input_path)
        from mirror_fg import __version__

        def write() -> list[HistoryRecord]:
            with Session(self.engine) as session, session.begin():
                run = Run(robot=robot, kind=kind, time=when, mirror_fg_version=__version__[:64], input_sha256=digest,
                          input_path=None if input_path is None else os.fspath(input_path)[:1000],
                          document=dict(document), host=socket.gethostname()[:255])
                run.records = [_record_of(robot, kind, when, row) for row in rows]
                session.add(run)
                session.flush()
                stored = [_history_record(r, run) for r in run.records]
            return stored

        def migrate_and_write() -> list[HistoryRecord]:
            self._migrate()
            return self._retry(write)

        return self._guard("the record was not stored", migrate_and_write)

    def _migrate(self) -> None:
        if not self._migrated:
            self._retry(lambda: ensure_schema(self.engine, self.url))
            self._migrated = True

    def _retry(self, work: Callable[[], _T]) -> _T:
        """``work()``, again after a random pause while SQLite says the database is locked or busy."""
        deadline = _time.monotonic() + LOCKED_RETRY_S
        pause = 0.01
        while True:
            try:
                return work()
            except OperationalError as error:
                if self.engine.dialect.name != "sqlite" or not _locked(error) or _time.monotonic() > deadline:
                    raise
            _time.sleep(pause * (0.5 + random.random()))
            pause = min(pause * 2, 1.0)

    def _guard(self, what: str, work: Callable[[], _T]) -> _T:
        """``work()`` with every database failure as one RegistryError line naming the registry."""
        try:
            return work()
        except RegistryError as error:  # the schema's or the document's own line
            raise RegistryError(f"{error}; {what}") from None
        except (SQLAlchemyError, OSError) as error:
            raise RegistryError(f"registry {describe(self.url)}: {what} ({_reason(error)})") from None

    # --- reading --------------------------------------------------------------------------------------

    def history(self, robot: str, camera: str | None = None, kind: str | None = None) -> list[HistoryRecord]:
        """``robot``'s records (one camera's with ``camera``; one kind's with ``kind``), oldest first, without
        their documents (``latest`` or ``document`` read those)."""
        postgresql = self.engine.dialect.name == "postgresql"

        def read() -> list[HistoryRecord]:
            columns = CameraRecord.__table__.columns
            # the time as the driver gives it (SQLite: text; PostgreSQL: an aware datetime): _history_records
            # makes it a UTC datetime in one C call, not the column type's parse and then a replace of its zone
            query = (select(*(columns[name] for name in _HISTORY_COLUMNS), type_coerce(CameraRecord.time, NullType()),
                            Run.mirror_fg_version, Run.input_sha256, Run.host)
                     .join(Run, Run.id == CameraRecord.run_id).where(CameraRecord.robot == robot))
            if camera is not None:
                query = query.where(CameraRecord.camera == camera)
            if kind is not None:
                query = query.where(CameraRecord.kind == kind)
            query = query.order_by(CameraRecord.time, CameraRecord.id)
            self._check_file()
            with self.engine.connect() as connection:
                if not self._readable(connection):
                    return []
                rows = _binary_rows(connection, query) if postgresql else connection.execute(query).all()
            collecting = gc.isenabled()
            gc.disable()  # 10,000 records are 50,000 new objects: no collection passes over the whole heap meanwhile
            try:
                return _history_records(rows, robot, self.engine.dialect.name == "sqlite")
            finally:
                if collecting:
                    gc.enable()

        return self._guard("cannot read the history", lambda: self._retry(read))

    def latest(self, robot: str, camera: str | None = None, kind: str | None = "calibration") -> HistoryRecord | None:
        """The newest record of ``robot`` (of ``camera``; of ``kind``, calibrations by default; None: any kind),
        with its run's whole document; None when there is none."""
        def read() -> HistoryRecord | None:
            if not self._readable():
                return None
            query = select(CameraRecord).where(CameraRecord.robot == robot)
            if camera is not None:
                query = query.where(CameraRecord.camera == camera)
            if kind is not None:
                query = query.where(CameraRecord.kind == kind)
            with Session(self.engine) as session:
                record = session.scalars(query.order_by(CameraRecord.time.desc(), CameraRecord.id.desc())
                                         .limit(1)).first()
                return None if record is None else _history_record(record, record.run, with_document=True)

        return self._guard("cannot read the latest record", lambda: self._retry(read))

    def robots(self) -> list[str]:
        """The robots with records, in name order."""
        def read() -> list[str]:
            if not self._readable():
                return []
            with self.engine.connect() as connection:
                return list(connection.scalars(select(Run.robot).distinct().order_by(Run.robot)))

        return self._guard("cannot read the robots", lambda: self._retry(read))

    def document(self, run_id: int) -> Any:
        """The whole document a run recorded (None: no such run)."""
        def read() -> Any:
            if not self._readable():
                return None
            with Session(self.engine) as session:
                run = session.get(Run, run_id)
                return None if run is None else run.document

        return self._guard("cannot read the document", lambda: self._retry(read))

    def _readable(self, connection: Connection | None = None) -> bool:
        """Whether the database holds a registry (False: empty); a RegistryError for a missing SQLite file or a
        schema newer than this code. ``connection``: the reader's own (else one for this check; made after
        :meth:`_check_file`: connecting makes a SQLite file)."""
        self._check_file()
        if connection is None:
            with self.engine.connect() as own:
                revision = database_revision(own)
        else:
            revision = database_revision(connection)
        check_revision(revision, self.url)
        return revision is not None

    def _check_file(self) -> None:
        """A RegistryError naming a SQLite file that is not there (a typo in the path), before a reader connects."""
        if self.engine.dialect.name == "sqlite":
            path = self.engine.url.database or ""
            if not self.engine.url.query.get("uri") and not os.path.exists(path):
                raise RegistryError(f"registry {describe(self.url)}: no such database file ({path})")


def _check_robot(robot: str) -> str:
    if not isinstance(robot, str) or not robot.strip() or len(robot) > 200:
        raise RegistryError(f"--robot {str(robot)[:40]!r}: a robot ID is a non-empty name of at most 200 characters")
    return robot


def _record_of(robot: str, kind: str, when: datetime, row: CameraRow) -> CameraRecord:
    t = row.t_m or (None, None, None)
    q = row.q_xyzw or (None, None, None, None)
    sp = row.sigma3_position_mm or (None, None, None)
    sr = row.sigma3_rotation_deg or (None, None, None)
    return CameraRecord(robot=robot, camera=row.camera[:200], kind=kind, time=when, verdict=row.verdict,
                        tx_m=t[0], ty_m=t[1], tz_m=t[2], qx=q[0], qy=q[1], qz=q[2], qw=q[3],
                        sigma3_x_mm=sp[0], sigma3_y_mm=sp[1], sigma3_z_mm=sp[2],
                        sigma3_rx_deg=sr[0], sigma3_ry_deg=sr[1], sigma3_rz_deg=sr[2])


def _triple(*values: Any) -> Any:
    return None if any(v is None for v in values) else tuple(float(v) for v in values)


#: The records' columns history reads, in the order :func:`_history_records` unpacks them (then the time, the
#: run's version, sha256 and host; the robot is the one asked for).
_HISTORY_COLUMNS = ("id", "run_id", "camera", "kind", "verdict", "tx_m", "ty_m", "tz_m", "qx", "qy", "qz", "qw",
                    "sigma3_x_mm", "sigma3_y_mm", "sigma3_z_mm", "sigma3_rx_deg", "sigma3_ry_deg", "sigma3_rz_deg")


def _binary_rows(connection: Connection, query: Any) -> list[Any]:
    """``query``'s rows through psycopg's binary results: the floats and times travel as their bytes, not as text
    the server formats and this process parses (history of 10,000 records: 40 -> 20 ms CPU here, and the
    server's share too: scripts/benchmark_registry.py). A driver error is SQLAlchemy's, as ``execute`` gives."""
    compiled = query.compile(dialect=connection.dialect)
    sql, parameters = str(compiled), compiled.params
    dbapi_error = connection.dialect.loaded_dbapi.Error
    try:
        with connection.connection.driver_connection.cursor(binary=True) as cursor:  # type: ignore[union-attr]
            cursor.execute(sql, parameters)
            return cursor.fetchall()
    except dbapi_error as error:
        raise DBAPIError.instance(sql, parameters, error, dbapi_error) from None


def _history_records(rows: Any, robot: str, sqlite: bool) -> list[HistoryRecord]:
    """The history rows as records; written for speed (history of 10,000 records in <= 0.2 s:
    scripts/benchmark_registry.py): positions, one comprehension, the time in one C call. ``sqlite``: the
    times are SQLAlchemy's SQLite text of a UTC time (``YYYY-MM-DD HH:MM:SS.ffffff``, models.UtcDateTime),
    else the driver's aware datetimes."""
    utc = timezone.utc
    return [HistoryRecord(camera, verdict, None if tx is None else (tx, ty, tz),
                          None if qx is None else (qx, qy, qz, qw), None if sx is None else (sx, sy, sz),
                          None if srx is None else (srx, sry, srz), id_, run_id, robot, kind,
                          datetime.fromisoformat(when + "+00:00") if sqlite else when.astimezone(utc), version, sha,
                          host)
            for (id_, run_id, camera, kind, verdict, tx, ty, tz, qx, qy, qz, qw, sx, sy, sz, srx, sry, srz, when,
                 version, sha, host) in rows]


def _history_record(r: CameraRecord, run: Run, with_document: bool = False) -> HistoryRecord:
    return HistoryRecord(
        camera=r.camera, verdict=r.verdict, t_m=_triple(r.tx_m, r.ty_m, r.tz_m), q_xyzw=_triple(r.qx, r.qy, r.qz, r.qw),
        sigma3_position_mm=_triple(r.sigma3_x_mm, r.sigma3_y_mm, r.sigma3_z_mm),
        sigma3_rotation_deg=_triple(r.sigma3_rx_deg, r.sigma3_ry_deg, r.sigma3_rz_deg),
        id=r.id, run_id=r.run_id, robot=r.robot, kind=r.kind, time=r.time, mirror_fg_version=run.mirror_fg_version,
        input_sha256=run.input_sha256, host=run.host, document=run.document if with_document else None)


def _locked(error: OperationalError) -> bool:
    text = str(error.orig).lower()
    return "locked" in text or "busy" in text


def _reason(error: BaseException) -> str:
    """The database's own first line (not SQLAlchemy's wrapping with the statement)."""
    if isinstance(error, DBAPIError) and error.orig is not None:
        error = error.orig
    elif isinstance(error, SQLAlchemyError) and getattr(error, "orig", None) is not None:
        error = getattr(error, "orig")
    text = str(error).strip().splitlines()
    line = " ".join(text[0].split())[:200] if text else type(error).__name__
    if getattr(error, "sqlstate", None) == DISK_FULL_SQLSTATE:  # PostgreSQL's disk_full, in the user's words
        return f"the database server's disk is full: {line}"
    return line
