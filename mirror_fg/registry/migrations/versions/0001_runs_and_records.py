"""The first schema: runs (one per recorded run, its whole document) and records (one per camera).

Revision ID: 0001
Revises:
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from mirror_fg.registry.models import UtcDateTime

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "runs",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("robot", sa.String(200), nullable=False),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("time", UtcDateTime, nullable=False),
        sa.Column("mirror_fg_version", sa.String(64), nullable=False),
        sa.Column("input_sha256", sa.String(64)),
        sa.Column("input_path", sa.String(1000)),
        sa.Column("document", sa.JSON, nullable=False),
    )
    pose = [sa.Column(name, sa.Float) for name in
            ("tx_m", "ty_m", "tz_m", "qx", "qy", "qz", "qw", "sigma3_x_mm", "sigma3_y_mm", "sigma3_z_mm",
             "sigma3_rx_deg", "sigma3_ry_deg", "sigma3_rz_deg")]
    op.create_table(
        "records",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("run_id", sa.Integer, sa.ForeignKey("runs.id", ondelete="CASCADE"), nullable=False),
        sa.Column("robot", sa.String(200), nullable=False),
        sa.Column("camera", sa.String(200), nullable=False),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("time", UtcDateTime, nullable=False),
        sa.Column("verdict", sa.String(32)),
        *pose,
        sa.UniqueConstraint("run_id", "camera", name="uq_records_run_camera"),
    )


def downgrade() -> None:
    op.drop_table("records")
    op.drop_table("runs")
