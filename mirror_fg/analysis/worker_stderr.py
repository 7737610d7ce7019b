"""A Dask worker preload for mirror-fg's local clusters (``montecarlo._local_cluster``): once a worker
begins to close, what its process writes to stderr is dropped.

A worker that closes while the scheduler is going away can fail inside distributed itself (seen:
``Worker.close_gracefully`` -> ``RuntimeError: ConnectionPool is closed``, under load), and Python's
multiprocessing prints that traceback straight to the stderr the command shares with its workers, after
every result is in. Logging settings cannot reach it. What a worker writes while it works is kept.
"""
from __future__ import annotations

import io
import sys
from typing import Any

__all__ = ["dask_setup", "CLOSING"]

#: The worker states (``distributed.core.Status`` names) from which its stderr is dropped.
CLOSING = frozenset({"closing", "closing_gracefully", "closed", "failed"})


class _UntilClosing(io.TextIOBase):
    """``stream`` while ``worker`` works; nothing once it closes."""

    def __init__(self, stream: Any, worker: Any) -> None:
        self._stream, self._worker = stream, worker

    def write(self, text: str) -> int:
        if getattr(getattr(self._worker, "status", None), "name", "") in CLOSING:
            return len(text)
        return self._stream.write(text)

    def flush(self) -> None:
        self._stream.flush()

    def fileno(self) -> int:
        return self._stream.fileno()

    def isatty(self) -> bool:
        return False


def dask_setup(worker: Any) -> None:
    """Distributed's preload hook, run in the worker's process as it starts."""
    if not isinstance(sys.stderr, _UntilClosing):
        sys.stderr = _UntilClosing(sys.stderr, worker)
