"""Writing output files all-or-nothing, never over an input (docs/formats.md, "Output files").

:class:`OutputPlan` checks every output path before any work (never an input, never a directory,
never under a regular file, never a FIFO or block device) and :meth:`OutputPlan.commit` writes all
outputs to temporary files first and renames them over their targets only when every one was
written, so a failed run leaves every existing file as it was (and removes the directories it made);
a second writer of the same set waits, SIGTERM never leaves part of a set replaced, and the next run
notices what a SIGKILL left (:mod:`mirror_fg.io.output_lock`). A character device (``/dev/null``) is
written into, never replaced; :func:`atomic_write` does that for one file, and :func:`json_text` lays
out the JSON it writes. Problems are one-line DatasetError / OutputError naming the file.
"""
from __future__ import annotations

import json
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mirror_fg.core.errors import DatasetError, OutputError
from mirror_fg.io.output_lock import DeferredSignals, Interrupted, OutputLock, recover, temporary_prefix

__all__ = ["OutputPlan", "same_file", "atomic_write", "json_text", "is_yaml", "file_head"]


def _write_error(target: str, exc: OSError) -> Exception:
    return OutputError(f"{target}: cannot write: {exc.strerror or exc}")


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """Whether two paths name the same file (through symlinks, hard links, ``..``)."""
    a, b = os.fspath(a), os.fspath(b)
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


@dataclass
class OutputPlan:
    """The files one command will write, checked before any work and written all-or-nothing.

    ``inputs``: every file the command reads (the dataset or capture and what it names); no output
    may be one of them. Add outputs with :meth:`add` (which checks the path at once), then
    :meth:`commit` their contents.
    """

    inputs: list[str] = field(default_factory=list)
    outputs: dict[str, str] = field(default_factory=dict)  # path -> what it is ("result", "ROS YAML", ...)

    def add_inputs(self, paths: Iterable[str | os.PathLike[str]]) -> None:
        """Record more input files (e.g. the images a capture names, once it is read)."""
        self.inputs.extend(os.fspath(p) for p in paths)
        for path, role in self.outputs.items():
            self._check_not_input(path, role)

    def add(self, path: str | os.PathLike[str], role: str = "output", marker: bytes | None = None) -> str:
        """Check ``path`` as an output and record it; DatasetError (one line) if it must not be written.

        ``marker``: for a file the user did not name (a side file derived from another output's name),
        an existing file is replaced only if its first bytes contain ``marker`` (it was written by us).
        """
        target = os.fspath(path)
        for other, other_role in self.outputs.items():
            if same_file(other, target):
                raise DatasetError(f"{target}: the {role} and the {other_role} would be the same file")
        self._check_not_input(target, role)
        kind = _existing_kind(target)
        if kind == "directory":
            raise DatasetError(f"{target}: is a directory; give a file name for the {role}")
        if kind not in (None, "file", "character device"):
            raise DatasetError(f"{target}: is a {kind}; the {role} must go to a regular file")
        if kind == "file" and marker is not None and marker not in file_head(target):
            raise DatasetError(f"{target}: exists and was not written by mirror-fg; refusing to replace it with the "
                         f"{role} (move it, or choose another output name)")
        if kind is None:
            parent = _nearest_existing_parent(target)
            if parent is not None and not os.path.isdir(parent):
                raise DatasetError(f"{target}: cannot create the {role}: {parent} is a file, not a directory")
        self.outputs[target] = role
        if kind != "character device":
            recover(os.path.realpath(target))  # a run killed while replacing it: clean up, say so
        return target

    def is_device(self, path: str | os.PathLike[str]) -> bool:
        """Whether ``path`` is a character device (written into, e.g. /dev/null)."""
        return _existing_kind(os.fspath(path)) == "character device"

    def _check_not_input(self, target: str, role: str) -> None:
        for source in self.inputs:
            if same_file(source, target):
                raise DatasetError(f"{target}: refusing to write the {role} over an input file "
                             f"({source}); choose another name")

    def commit(self, contents: Mapping[Any, str | bytes]) -> list[Path]:  # keys: str or PathLike paths
        """Write every ``{path: content}`` (text is UTF-8): temporary files first, then renames.

        Each path must have been :meth:`add`-ed. Any failure before the renames removes every
        temporary file and the directories this commit made, and leaves every existing file untouched
        (DatasetError naming the file). The set is locked against a second writer and held against
        SIGTERM/SIGINT/SIGHUP while it is replaced (:mod:`mirror_fg.io.output_lock`).
        """
        files: list[tuple[str, bytes, str]] = []  # (real path, content, the path as given)
        devices: list[tuple[str, bytes]] = []
        for path, data in contents.items():
            target = os.fspath(path)
            if target not in self.outputs:
                raise ValueError(f"{target}: not an output of this plan")
            raw = data.encode("utf-8") if isinstance(data, str) else data
            if self.is_device(target):
                devices.append((target, raw))
            else:
                files.append((os.path.realpath(target), raw, target))  # a symlink stays one: replace what it names
        if files:
            try:
                with DeferredSignals() as signals:
                    _replace_all(files, signals)
            except Interrupted as stop:  # the signal's own handler let the process go on
                raise OutputError(f"{files[0][2]}: not written: interrupted by {stop}") from None
        for target, raw in devices:
            try:
                with open(target, "wb") as handle:
                    handle.write(raw)
            except OSError as exc:
                raise _write_error(target, exc) from None
        return [Path(p) for p in contents]


def _replace_all(files: list[tuple[str, bytes, str]], signals: DeferredSignals) -> None:
    """Under the set's lock: every file to a temporary file, then each renamed over its target. A
    failure or a signal before the first rename leaves the old set and nothing of ours."""
    created: list[str] = []  # directories made for the outputs, outermost first
    staged: list[tuple[str, str]] = []  # (temporary, real target)
    renamed, lock = 0, None
    try:
        for real, _, target in files:
            created += _make_directories(os.path.dirname(real), target)
        lock = OutputLock.acquire(files[0][0], files[0][2], [real for real, _, _ in files], signals)
        for real, raw, target in files:
            staged.append((_stage(real, raw, target), real))
            signals.check()  # a signal now stops the commit: nothing is replaced yet
        try:
            lock.note("committing", targets=[real for real, _, _ in files], renames=staged)
        except OSError as exc:
            raise _write_error(files[0][2], exc) from None
        for (tmp, real), (_, _, target) in zip(staged, files):
            try:
                os.replace(tmp, real)
            except OSError as exc:
                done = "" if not renamed else f" ({', '.join(t for _, t in staged[:renamed])} already replaced)"
                raise OutputError(f"{target}: cannot write: {exc.strerror or exc}{done}") from None
            renamed += 1
    except BaseException:
        for tmp, _ in staged[renamed:]:
            _unlink(tmp)
        if lock is not None:
            half = 0 < renamed < len(staged)
            lock.release(([t for _, t in staged[:renamed]], [t for _, t in staged[renamed:]]) if half else None)
        _remove_directories(created)
        raise
    lock.release()


def _make_directories(directory: str, target: str) -> list[str]:
    """Make ``directory`` and its missing parents ("-o out/result.json" creates out/); the ones made."""
    missing = []
    while directory and not os.path.lexists(directory):
        missing.append(directory)
        directory = os.path.dirname(directory)
    made: list[str] = []
    for path in reversed(missing):
        try:
            os.mkdir(path)
        except FileExistsError:
            continue  # made by another run meanwhile: not ours to remove
        except OSError as exc:
            _remove_directories(made)
            raise _write_error(target, exc) from None
        made.append(path)
    return made


def _remove_directories(made: list[str]) -> None:
    """Remove the directories a failed commit made (outermost first in ``made``), while they are empty."""
    for directory in reversed(made):
        try:
            os.rmdir(directory)
        except OSError:
            break


def _existing_kind(path: str) -> str | None:
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return None
    except NotADirectoryError:
        return None  # a parent is a file: reported by add()
    except OSError:
        return None
    kinds = ((stat.S_ISREG, "file"), (stat.S_ISDIR, "directory"), (stat.S_ISCHR, "character device"),
             (stat.S_ISFIFO, "named pipe"), (stat.S_ISSOCK, "socket"), (stat.S_ISBLK, "block device"))
    return next((name for test, name in kinds if test(mode)), "special file")


def file_head(path: str, size: int = 512) -> bytes:
    """The first ``size`` bytes of the file at ``path`` (where a marker of mirror-fg's own files sits), or
    nothing where it cannot be read."""
    try:
        with open(path, "rb") as handle:
            return handle.read(size)
    except OSError:
        return b""


def _nearest_existing_parent(path: str) -> str | None:
    parent = os.path.dirname(os.path.abspath(os.path.realpath(path)))
    while parent and not os.path.lexists(parent):
        up = os.path.dirname(parent)
        if up == parent:
            return None
        parent = up
    return parent or None


def _stage(real: str, raw: bytes, target: str) -> str:
    """Write ``raw`` to a temporary file beside ``real``, named as ours with our pid; return its path."""
    directory = os.path.dirname(real)
    try:
        fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(real), suffix=".tmp", dir=directory)
    except OSError as exc:
        raise _write_error(target, exc) from None
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(raw)
            handle.flush()
            os.fsync(handle.fileno())
        try:  # mkstemp makes the file 0600; give it the mode an ordinary open() would have
            mode = os.stat(real).st_mode & 0o7777
        except FileNotFoundError:
            mode = 0o666 & ~_umask()
        os.chmod(tmp, mode)
    except OSError as exc:
        _unlink(tmp)
        raise _write_error(target, exc) from None
    except BaseException:
        _unlink(tmp)
        raise
    return tmp


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


def _umask() -> int:
    """The process umask, read without changing it where /proc allows."""
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike[str], data: str | bytes) -> Path:
    """Write ``data`` (text is UTF-8) to ``path`` all-or-nothing (:class:`OutputPlan`): a temporary file
    in the same directory replaces an existing file only once complete; on any failure the old file
    stays as it was. DatasetError (one line) where ``path`` cannot be written."""
    plan = OutputPlan()
    plan.add(path)
    plan.commit({os.fspath(path): data})
    return Path(path)


# An innermost list of numbers as json.dumps(indent=...) lays it out, one number a line. Strings
# cannot match: JSON escapes newlines inside them.
_NUMBER_LIST = re.compile(r"\[\n\s*(-?[0-9][-+0-9.eE]*(?:,\n\s*-?[0-9][-+0-9.eE]*)*)\n\s*\]")


def json_text(data: Any, allow_nan: bool) -> str:
    """JSON with indent 2, innermost lists of numbers kept on one line (``[x, y, z]``)."""
    text = json.dumps(data, indent=2, allow_nan=allow_nan, ensure_ascii=False)
    return _NUMBER_LIST.sub(_one_line, text) + "\n"


def _one_line(match: re.Match[str]) -> str:
    return "[" + ", ".join(number.strip() for number in match.group(1).split(",")) + "]"


def is_yaml(path: str) -> bool:
    """Whether ``path`` names a YAML file (by its ending)."""
    return path.lower().endswith((".yaml", ".yml"))


