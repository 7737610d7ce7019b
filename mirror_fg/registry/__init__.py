"""The calibration registry: every calibration and verification of a robot's cameras, in SQLite or PostgreSQL.

``Registry(url)`` (store.py) records runs and reads history; ``models.py`` the tables, ``schema.py`` the URL,
engine and Alembic migrations (``migrations/``), ``records.py`` what is kept of a document, ``history.py`` the
history page and CSV, ``cli.py`` the ``--registry URL --robot ID`` options the commands share.
docs/formats.md#has-it-moved-mirror-fg-verify-and-the-calibration-registry.
"""
from __future__ import annotations

from mirror_fg.registry.records import HistoryRecord
from mirror_fg.registry.schema import ENV_VAR, RegistryError
from mirror_fg.registry.store import Registry

__all__ = ["Registry", "RegistryError", "HistoryRecord", "ENV_VAR"]
