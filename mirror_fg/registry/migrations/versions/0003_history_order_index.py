"""The index history reads a robot's records by, in its order: records (robot, time, id). The (robot, camera,
time) index serves one camera's history; a robot's whole history through it was sorted afterwards (a temporary
B-tree of 10,000 rows: scripts/benchmark_registry.py).

Revision ID: 0003
Revises: 0002
"""
from __future__ import annotations

from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("ix_records_robot_time_id", "records", ["robot", "time", "id"])


def downgrade() -> None:
    op.drop_index("ix_records_robot_time_id", table_name="records")
