"""The calibration registry: every calibration and verification of a robot's cameras, in SQLite or PostgreSQL.

``Registry(url)`` (store.py) records runs and reads history; ``models.py`` the tables, ``schema.py`` the URL,
engine and Alembic migrations (``migrations/``), ``records.py`` what is kept of a document, ``history.py`` the
history page and CSV, ``cli.py`` the ``--registry URL --robot ID`` options the commands share.
docs/formats.md#has-it-moved-mirror-fg-verify-and-the-calibration-registry.

The names below are imported on first use, so the command line's parser does not load SQLAlchemy.
"""
from __future__ import annotations

import importlib as _importlib
from typing import Any as _Any

_PUBLIC = {
    "Registry": "mirror_fg.registry.store",
    "RegistryError": "mirror_fg.registry.schema",
    "HistoryRecord": "mirror_fg.registry.records",
    "ENV_VAR": "mirror_fg.registry.cli",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> _Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module 'mirror_fg.registry' has no attribute {name!r}")
    value = getattr(_importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value
    return value
