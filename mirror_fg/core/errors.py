"""The errors mirror_fg raises for the user's data; each carries the exit status the CLI returns.

Every message is one line that names the file, image or point and what is wrong. The command line
catches :class:`MirrorFgError` once and prints ``mirror-fg: <label>: <message>``.
"""
from __future__ import annotations

__all__ = ["MirrorFgError", "DatasetError", "OutputError", "SolveError"]


class MirrorFgError(Exception):
    """Base of the errors about the user's data (not bugs): one-line message, an exit status."""

    exit_code = 1
    label = "error"


class DatasetError(MirrorFgError, ValueError):
    """Bad input: the message names the file, image or point and what is wrong, in one line. Exit 2."""

    exit_code = 2


class OutputError(DatasetError, OSError):
    """An output file cannot be written (full disk, no permission): one line naming the file. Exit 2."""


class SolveError(MirrorFgError, RuntimeError):
    """The data cannot be solved (degenerate geometry, PnP failure, no convergence). Exit 3."""

    exit_code = 3
    label = "cannot solve"
