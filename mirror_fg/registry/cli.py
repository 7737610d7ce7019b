"""``--registry URL --robot ID`` for the commands that record their runs (calibrate, calibrate-many, verify,
live): the options, their check before any work, and the recording of a written document after it.

The order is the contract (docs/formats.md#has-it-moved-mirror-fg-verify-and-the-calibration-registry): the
result file is written first; then the run is recorded. A database that is down, full, read-only or has a
newer schema never costs the file: the run ends with exit 2 and one line saying the record was not stored.
"""
from __future__ import annotations

import argparse
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["ENV_VAR", "add_registry_arguments", "RegistryTarget", "registry_target", "record_document", "record_row"]


#: The environment variable that gives the registry's URL when ``--registry`` is not given.
ENV_VAR = "MIRROR_FG_REGISTRY"


def add_registry_arguments(parser: argparse.ArgumentParser, per_input: bool = False) -> None:
    """Add ``--registry URL`` and ``--robot ID`` to a sub-command's parser (``per_input``: calibrate-many,
    where a missing ``--robot`` names each input's robot after its file)."""
    group = parser.add_argument_group("calibration registry")
    group.add_argument("--registry", metavar="URL",
                       help=f"record the run in this database: sqlite:///path.db or postgresql://user@host:port/db "
                            f"(default: ${ENV_VAR}; recorded only with --robot)")
    robot_help = "the robot the run belongs to (the registry's key)"
    if per_input:
        robot_help += "; without it, with --registry, each input's file name without its extension"
    group.add_argument("--robot", metavar="ID", help=robot_help)


@dataclass(frozen=True)
class RegistryTarget:
    """Where a run is recorded: the registry URL and the robot (None: each input's stem, calibrate-many)."""

    url: str
    robot: str | None


def registry_target(args: Any, per_input: bool = False) -> RegistryTarget | None:
    """The registry a command records in (None: no recording), checked before any work: a URL from
    ``--registry`` or the environment, ``--robot`` to record (calibrate-many: optional with ``--registry``)."""
    url = getattr(args, "registry", None)
    robot = getattr(args, "robot", None)
    explicit = url is not None
    if url is None:
        url = os.environ.get(ENV_VAR) or None
    if robot is None and not explicit:
        return None  # no recording: the database layer (SQLAlchemy, 0.2 s to import) is not loaded
    from mirror_fg.registry.schema import RegistryError, registry_url

    if robot is None and not (per_input and explicit):
        raise RegistryError("--registry needs --robot ID (the robot the run is recorded for)")
    if url is None:
        raise RegistryError(f"--robot needs a registry: --registry URL or ${ENV_VAR}")
    registry_url(url)  # a malformed URL before the work
    if robot is not None and (not robot.strip() or len(robot) > 200):
        raise RegistryError(f"--robot {robot[:40]!r}: a robot ID is a non-empty name of at most 200 characters")
    return RegistryTarget(url, robot)


def record_document(target: RegistryTarget | None, document: Mapping[str, Any],
                    input_path: str | os.PathLike[str] | None, written: str | os.PathLike[str] | None,
                    out: Any = None) -> None:
    """Record ``document`` (result@1 or verification@1, already written to ``written``, if anywhere) for
    ``target``'s robot; a note on ``out`` (the command's printer) when stored, else a RegistryError (exit 2)
    that says the record was not stored and that the file is written."""
    if target is None:
        return
    from mirror_fg.registry.schema import RegistryError, describe
    from mirror_fg.registry.store import Registry

    robot = target.robot or Path(os.fspath(input_path or "run")).stem
    try:
        with Registry(target.url) as registry:
            stored = registry.record(robot, document, input_path=_file_or_none(input_path))
    except RegistryError as error:
        kept = f"; {os.fspath(written)} is written" if written is not None else ""
        raise RegistryError(f"{error}{kept}") from None
    if out is not None:
        cameras = ", ".join(r.camera for r in stored)
        out.info(f"recorded in {describe(target.url)}: robot {robot}, {stored[0].kind} of {cameras} "
                 f"(run {stored[0].run_id})")


def record_row(url: str | None, robot: str | None, document: Mapping[str, Any], input_path: str,
               written: str) -> str | None:
    """:func:`record_document` for one input of calibrate-many (in its Dask worker): None when stored, else
    the one-line reason, for the parent to report."""
    if url is None:
        return None
    from mirror_fg.registry.schema import RegistryError

    try:
        record_document(RegistryTarget(url, robot), document, input_path, written)
    except RegistryError as error:
        return str(error)
    return None


def _file_or_none(path: str | os.PathLike[str] | None) -> str | None:
    return None if path is None or os.fspath(path) == "-" else os.fspath(path)
