"""The log of a resumable study: one JSON record a line, appended as each trial finishes.

The one reader and writer of ``runs.jsonl`` (``scripts/reproduce_fig4.py``, ``scripts/convergence.py``, through
``montecarlo.run_trials``). What holds:

- A record counts once its line is whole: the newline that ends it is written with it, in one ``write``. A last
  line without its newline (a killed writer, a full disk) is a torn record: it is reported, cut off the file, and
  that trial runs again. A line that does not hold a record anywhere else is an error naming its line number.
- A failed append (full disk) cuts the file back to its last whole record and raises ``OutputError`` (one line):
  the log stays resumable.
- An open log is locked (``fcntl.flock``, exclusive) until it is closed, so a second run on the same file stops at
  once with one line instead of running the same trials again; on reading, the first record of each trial key is
  kept (a log written by two runs before this lock existed counts every trial once).
"""
from __future__ import annotations

import fcntl
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from mirror_fg.core.errors import DatasetError, OutputError

__all__ = ["TrialLog"]


class TrialLog:
    """A JSON-lines trial log at ``path`` (``None``: no file, nothing kept), opened with ``with``.

    key_fields: the record fields that name a trial (e.g. ``("sigma_px", "distance_m", "seed")``); a record whose
    key was already read is a repeat and is dropped. fresh: start the log empty (under the lock). ``records``:
    the records read, in file order, one per key.
    """

    def __init__(self, path: str | os.PathLike[str] | None, key_fields: Sequence[str] = (), *,
                 fresh: bool = False) -> None:
        self.path = None if path is None else Path(path)
        self.key_fields = tuple(key_fields)
        self.fresh = fresh
        self.records: list[dict] = []
        self.notes: list[str] = []
        self._fd: int | None = None
        self._end = 0  # bytes up to the end of the last whole record

    def key(self, record: dict) -> tuple:
        return tuple(record.get(field) for field in self.key_fields)

    def __enter__(self) -> TrialLog:
        if self.path is None:
            return self
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as error:
            raise OutputError(f"{self.path}: cannot open the trial log ({error.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise DatasetError(f"{self.path}: another run is writing this trial log; wait for it to finish "
                               "or give this run another output directory") from None
        self._fd = fd
        try:
            if self.fresh:
                os.ftruncate(fd, 0)
            self._read()
        except BaseException:
            self.close()
            raise
        for note in self.notes:
            print(f"{self.path}: {note}", file=sys.stderr, flush=True)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # releases the lock
            self._fd = None

    def _read(self) -> None:
        assert self._fd is not None
        size = os.fstat(self._fd).st_size
        data = os.pread(self._fd, size, 0) if size else b""
        whole, _, torn = data.rpartition(b"\n")  # records end with a newline; what follows the last is torn
        seen: set[tuple] = set()
        repeats = 0
        lines = whole.split(b"\n") if whole else []
        for number, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            record = _record(line)
            if record is None:
                raise DatasetError(f"{self.path}, line {number}: not a whole JSON record (only the last line "
                                   "may be cut short, by a killed run): remove that line, or start afresh (--fresh)")
            key = self.key(record)
            if self.key_fields and key in seen:
                repeats += 1
                continue
            seen.add(key)
            self.records.append(record)
        self._end = len(data) - len(torn)
        if torn.strip():
            self.notes.append(f"line {len(lines) + 1} was cut short (a killed run or a full disk): ignored, "
                              "that trial runs again")
        if self._end < size:
            os.ftruncate(self._fd, self._end)
        if repeats:
            self.notes.append(f"{repeats} repeated trial record(s) ignored (two runs wrote this log at once?)")

    def append(self, record: dict) -> None:
        """Write ``record`` as one whole line; on failure cut the file back and raise ``OutputError``."""
        if self._fd is None:
            return
        line = (json.dumps(record) + "\n").encode()
        try:
            written = 0
            while written < len(line):
                written += os.pwrite(self._fd, line[written:], self._end + written)
        except OSError as error:
            try:
                os.ftruncate(self._fd, self._end)
            except OSError:
                pass  # the next run finds a torn last line and re-runs that trial
            raise OutputError(f"{self.path}: cannot append a trial record ({error.strerror}); the log keeps "
                              "every trial finished before: make room and run again to resume") from None
        self._end += len(line)


def _record(line: bytes) -> dict | None:
    try:
        value = json.loads(line)
    except ValueError:  # JSONDecodeError, UnicodeDecodeError
        return None
    return value if isinstance(value, dict) else None
