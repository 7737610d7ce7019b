"""The registry's tables (SQLAlchemy 2 declarative models; docs/formats.md#has-it-moved-mirror-fg-verify-and-the-calibration-registry).

``runs``: one row per recorded run (a calibration or a verification): robot, kind, time (UTC), the mirror-fg
version, the input's sha256, the host that recorded it and the whole result@1 or verification@1 document (JSON).
``records``: one row per camera of a run, with the columns queries need without reading the document: the
verdict and ``T_base_cam`` (translation in metres, quaternion x, y, z, w; the camera's pose on the robot, base
axes) with its 3-sigma (``position_mm``, ``rotation_deg`` in the uncertainty convention of docs/formats.md).
A rig's records are written with their run in one transaction: all of them or none.

The schema itself is made by the Alembic revisions in ``migrations/versions`` (these models describe the
newest revision; ``tests/test_registry_schema.py`` checks that they agree).
"""
from __future__ import annotations

from datetime import datetime, timezone
from typing import Any

from sqlalchemy import JSON, DateTime, Float, ForeignKey, Index, Integer, String, TypeDecorator, UniqueConstraint
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

__all__ = ["Base", "Run", "CameraRecord", "UtcDateTime", "KINDS"]

#: The kinds of run a record holds.
KINDS = ("calibration", "verification")


class UtcDateTime(TypeDecorator):
    """A timezone-aware UTC time, stored as UTC on every backend (SQLite keeps no zone) and read back aware."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("registry times must be timezone-aware (UTC)")
        value = value.astimezone(timezone.utc)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=timezone.utc) if value.tzinfo is None else value.astimezone(timezone.utc)


class Base(DeclarativeBase):
    pass


class Run(Base):
    """One recorded run: its whole document and what identifies it."""

    __tablename__ = "runs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    robot: Mapped[str] = mapped_column(String(200), nullable=False)
    kind: Mapped[str] = mapped_column(String(16), nullable=False)
    time: Mapped[datetime] = mapped_column(UtcDateTime, nullable=False)
    mirror_fg_version: Mapped[str] = mapped_column(String(64), nullable=False)
    input_sha256: Mapped[str | None] = mapped_column(String(64))  # None: the input was a pipe, not a file
    input_path: Mapped[str | None] = mapped_column(String(1000))
    document: Mapped[Any] = mapped_column(JSON, nullable=False)
    host: Mapped[str | None] = mapped_column(String(255))  # revision 2: the machine that recorded it

    records: Mapped[list[CameraRecord]] = relationship(back_populates="run", cascade="all, delete-orphan")


class CameraRecord(Base):
    """One camera of a run: the columns history and queries use."""

    __tablename__ = "records"
    __table_args__ = (
        UniqueConstraint("run_id", "camera", name="uq_records_run_camera"),
        Index("ix_records_robot_camera_time", "robot", "camera", "time"),  # revision 2
        Index("ix_records_robot_time_id", "robot", "time", "id"),  # revision 3: history in its order, unsorted
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), nullable=False)
    robot: Mapped[str] = mapped_column(String(200), nullable=False)  # the run's, repeated for the index
    camera: Mapped[str] = mapped_column(String(200), nullable=False)
    kind: Mapped[str] = mapped_column(String(16), nullable=False)
    time: Mapped[datetime] = mapped_column(UtcDateTime, nullable=False)
    verdict: Mapped[str | None] = mapped_column(String(32))
    tx_m: Mapped[float | None] = mapped_column(Float)
    ty_m: Mapped[float | None] = mapped_column(Float)
    tz_m: Mapped[float | None] = mapped_column(Float)
    qx: Mapped[float | None] = mapped_column(Float)
    qy: Mapped[float | None] = mapped_column(Float)
    qz: Mapped[float | None] = mapped_column(Float)
    qw: Mapped[float | None] = mapped_column(Float)
    sigma3_x_mm: Mapped[float | None] = mapped_column(Float)
    sigma3_y_mm: Mapped[float | None] = mapped_column(Float)
    sigma3_z_mm: Mapped[float | None] = mapped_column(Float)
    sigma3_rx_deg: Mapped[float | None] = mapped_column(Float)
    sigma3_ry_deg: Mapped[float | None] = mapped_column(Float)
    sigma3_rz_deg: Mapped[float | None] = mapped_column(Float)

    run: Mapped[Run] = relationship(back_populates="records")
