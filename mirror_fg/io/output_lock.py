"""The lock beside an output set, the commit record it holds, and the signals held back while the set is replaced.

A commit of :class:`mirror_fg.io.output.OutputPlan` holds ``.<first output>.lock`` beside its first
output (``fcntl.flock``). A second writer of the same set waits for it (a commit takes milliseconds) up
to :data:`LOCK_WAIT_S`, then gets OutputError naming the holder's pid. The lock file is also the commit
record, JSON ``{"pid", "state", "targets", "renames"}``: state ``writing`` while the temporary files
are written, ``committing`` from just before the first rename; the commit removes it when it ends, so
only a run killed without cleanup (SIGKILL) leaves it. The next run that plans one of those outputs
(:func:`recover`) removes the dead run's temporary files (``.<name>.mirror-fg.<pid>.<random>.tmp``, only
those whose pid is dead) and, if the renames had stopped half-way, warns once per run and keeps the
record (state ``mixed``) until a commit replaces the whole set.

SIGTERM, SIGINT and SIGHUP are held back across a commit (:class:`DeferredSignals`, in the main
thread, where Python runs signal handlers): one that arrives before the first rename stops the commit
(temporary files removed, the old set intact), one after it waits until every rename is done; then
the signal acts as it would have (SIGTERM ends the process, SIGINT raises KeyboardInterrupt).
"""
from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import signal
import threading
import time
import warnings
from typing import Any

from mirror_fg.core.errors import OutputError

__all__ = ["LOCK_WAIT_S", "DeferredSignals", "Interrupted", "MixedOutputWarning", "OutputLock", "lock_path", "recover",
           "temporary_prefix"]

#: How long a second writer of one output set waits for the first one's commit, seconds.
LOCK_WAIT_S = 10.0
_LOCK_POLL_S = 0.05
_pause = time.sleep  # between two tries of a busy lock

_NO_LOCKS = (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL)
_DEFERRED = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGINT", "SIGHUP") if hasattr(signal, name))
_TEMPORARY = re.compile(r"\.(?P<name>.+)\.mirror-fg\.(?P<pid>[0-9]+)\.[a-z0-9_]+\.tmp")


class MixedOutputWarning(UserWarning):
    """A run was killed half-way through replacing an output set: its files come from two runs."""


class Interrupted(Exception):
    """A held-back signal stopped a commit before its first rename (nothing was replaced)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class DeferredSignals:
    """Hold back SIGTERM, SIGINT and SIGHUP while the block runs; deliver them, in order, when it ends.

    Only in the main thread (elsewhere Python cannot install handlers) and only for signals whose
    handler Python set and that are not ignored. :meth:`check` raises :class:`Interrupted` once one came.
    """

    def __enter__(self) -> DeferredSignals:
        self.received: list[int] = []
        self.previous: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for signum in _DEFERRED:
                handler = signal.getsignal(signum)
                if handler is not None and handler is not signal.SIG_IGN:
                    self.previous[signum] = signal.signal(signum, self._hold)
        return self

    def _hold(self, signum: int, frame: Any) -> None:
        self.received.append(signum)

    def check(self) -> None:
        if self.received:
            raise Interrupted(self.received[0])

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)
        for signum in dict.fromkeys(self.received):
            signal.raise_signal(signum)


def lock_path(real: str) -> str:
    """``.<name>.lock`` beside ``real``, the first output of a set."""
    return os.path.join(os.path.dirname(real), f".{os.path.basename(real)}.lock")


def temporary_prefix(real: str) -> str:
    """The name a temporary file for ``real`` starts with: hidden, ours, with our pid."""
    return f".{os.path.basename(real)}.mirror-fg.{os.getpid()}."


class OutputLock:
    """An exclusive ``flock`` on the lock file of an output set, and the commit record in it."""

    def __init__(self, path: str, fd: int):
        self.path, self.fd = path, fd
        self.previous = _read_record(fd)  # what a run killed in its commit left

    @classmethod
    def acquire(cls, real: str, target: str, targets: list[str], signals: DeferredSignals) -> OutputLock:
        """The lock of the set whose first output is ``real`` (``target`` as the user named it), waiting
        up to LOCK_WAIT_S for another writer; records ``targets`` (real paths) as being written."""
        path = lock_path(real)
        deadline = time.monotonic() + LOCK_WAIT_S
        while True:
            try:
                lock, holder = cls._try(path)
                if lock is not None:
                    try:
                        _remove_dead_temporaries(_targets(lock.previous))  # a killed run's, not seen by recover()
                        lock.note("writing", targets=targets)
                    except BaseException:
                        lock.release()
                        raise
                    return lock
            except OSError as exc:
                raise OutputError(f"{target}: cannot write: {exc.strerror or exc} (taking the lock "
                                  f"{os.path.basename(path)})") from None
            if time.monotonic() >= deadline:
                pid = holder.get("pid", "unknown")
                raise OutputError(f"{target}: another mirror-fg run (pid {pid}) is writing it; waited "
                                  f"{LOCK_WAIT_S:g} s: try again when it has finished")
            signals.check()
            _pause(_LOCK_POLL_S)

    @classmethod
    def _try(cls, path: str) -> tuple[OutputLock | None, dict]:
        """The lock if it is free, else None and the holder's record."""
        while True:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read_record(fd)
                os.close(fd)
                return None, holder
            except OSError as exc:
                if exc.errno in _NO_LOCKS:  # a file system without flock: write unlocked, as before
                    return cls(path, fd), {}
                os.close(fd)
                raise
            except BaseException:
                os.close(fd)
                raise
            try:
                same = os.path.samestat(os.stat(path), os.fstat(fd))
            except FileNotFoundError:
                same = False
            if same:
                return cls(path, fd), {}
            os.close(fd)  # the holder removed this file as it let go: lock the one now at that path

    def note(self, state: str, pid: int | None = None, **record: Any) -> None:
        """Replace the commit record: ``state``, the writer's pid (ours by default) and more fields."""
        text = json.dumps({"pid": os.getpid() if pid is None else pid, "state": state, **record}).encode("utf-8")
        size = os.fstat(self.fd).st_size  # blanks over a longer old record: ext4 flushes a truncated file on close
        os.pwrite(self.fd, text + b" " * max(0, size - len(text)), 0)

    def release(self, mixed: tuple[list[str], list[str]] | None = None, pid: int | None = None) -> None:
        """Let go: the lock file is removed, or kept with state ``mixed`` when ``mixed`` = (the targets
        replaced, those not) says the renames of the run ``pid`` (ours by default) stopped half-way."""
        try:
            if mixed is not None:
                self.note("mixed", pid, targets=mixed[0] + mixed[1], new=mixed[0], old=mixed[1])
            else:
                _unlink(self.path)  # while still holding it (a waiting writer sees the file go and retries)
        except OSError:
            pass
        finally:
            os.close(self.fd)


def recover(real: str) -> None:
    """Clean up after a run killed in the commit of the set whose first output is ``real``: remove its
    temporary files; a :class:`MixedOutputWarning` (one line) if it replaced only part of the set."""
    path = lock_path(real)
    if not os.path.lexists(path):
        return
    try:
        lock, _ = OutputLock._try(path)
    except OSError:
        return
    if lock is None:
        return  # a live run is committing this set now
    record = lock.previous
    mixed = None
    targets = _targets(record)
    try:
        if record.get("state") == "committing":
            renames = [(os.fspath(tmp), os.fspath(t)) for tmp, t in record.get("renames", [])]
            new = [t for tmp, t in renames if not os.path.lexists(tmp)]
            old = [t for tmp, t in renames if os.path.lexists(tmp)]
            mixed = (new, old) if new and old else None
        elif record.get("state") == "mixed":
            mixed = ([os.fspath(t) for t in record["new"]], [os.fspath(t) for t in record["old"]])
    except (AttributeError, KeyError, TypeError, ValueError):  # not a record we wrote: nothing to say
        mixed = None
    if mixed is not None and not (mixed[0] and mixed[1]):
        mixed = None
    _remove_dead_temporaries(targets)
    pid = record.get("pid")
    lock.release(mixed, pid if isinstance(pid, int) else None)
    if mixed is not None:
        new, old = mixed
        names = ", ".join([new[0]] + [os.path.basename(t) for t in new[1:]])
        warnings.warn(f"{names}: written by a mirror-fg run (pid {pid}) that was killed or failed before it "
                      f"replaced {', '.join(os.path.basename(t) for t in old)}: these files do not belong "
                      "together until a run writes them again", MixedOutputWarning, stacklevel=2)


def _targets(record: dict) -> list[str]:
    """The real paths a commit record names (none if it is not one we wrote)."""
    try:
        return [os.fspath(t) for t in record.get("targets", [])]
    except TypeError:
        return []


def _remove_dead_temporaries(targets: list[str]) -> None:
    """Remove our temporary files for ``targets`` whose writer (the pid in the name) is dead."""
    names: dict[str, set[str]] = {}
    for target in targets:
        names.setdefault(os.path.dirname(target), set()).add(os.path.basename(target))
    for directory, bases in names.items():
        try:
            entries = os.listdir(directory)
        except OSError:
            continue
        for entry in entries:
            match = _TEMPORARY.fullmatch(entry)
            if match and match["name"] in bases and not _alive(int(match["pid"])):
                try:
                    _unlink(os.path.join(directory, entry))
                except OSError:
                    pass


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except PermissionError:  # another user's process
        return True
    except (ProcessLookupError, OverflowError):
        return False
    return True


def _read_record(fd: int) -> dict:
    try:
        record = json.loads(os.pread(fd, 1 << 20, 0).decode("utf-8"))
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
