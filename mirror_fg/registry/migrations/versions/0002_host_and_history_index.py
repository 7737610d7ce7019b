"""The machine that recorded each run (a fleet shares one database), and the index history reads by:
records (robot, camera, time).

Revision ID: 0002
Revises: 0001
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.add_column(sa.Column("host", sa.String(255)))
    op.create_index("ix_records_robot_camera_time", "records", ["robot", "camera", "time"])


def downgrade() -> None:
    op.drop_index("ix_records_robot_camera_time", table_name="records")
    with op.batch_alter_table("runs") as batch:
        batch.drop_column("host")
