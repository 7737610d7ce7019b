"""Alembic's environment for the registry: always given an open connection by ``mirror_fg.registry.schema``
(programmatic use only; there is no alembic.ini)."""
from __future__ import annotations

from alembic import context

connection = context.config.attributes["connection"]
context.configure(connection=connection, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
