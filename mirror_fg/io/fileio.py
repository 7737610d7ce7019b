"""Reading input files once, within bounds, and writing output files all-or-nothing.

Every file the user gives goes through here:

- :func:`read_input` reads a file (or ``-``, standard input) exactly once, at most
  :data:`MAX_INPUT_BYTES`, so a named pipe, ``/dev/stdin`` or ``/dev/zero`` is read once and bounded.
- :func:`parse_json` / :func:`parse_yaml` / :func:`parse_structured` parse that text into plain Python
  values within :data:`MAX_DEPTH` levels of nesting, :data:`MAX_NODES` values (YAML aliases counted
  as often as they are expanded, so an alias bomb is refused before it is built) and integers of at
  smaller than :data:`INT_LIMIT` (larger ones become infinities, which every validator refuses by
  name); a key repeated in one object is an error.
- :class:`OutputPlan` checks every output path before any work (never an input, never a directory,
  never under a regular file, never a FIFO or block device) and :meth:`OutputPlan.commit` writes all
  outputs to temporary files first and renames them over their targets only when every one was
  written, so a failed run leaves every existing file as it was. A character device (``/dev/null``)
  is written into, never replaced.

Every problem is a :class:`~mirror_fg.io.dataset.DatasetError` with one line that names the file.
Formats: ``docs/formats.md``.
"""
from __future__ import annotations

import json
import math
import os
import re
import stat
import sys
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "MAX_INPUT_BYTES",
    "MAX_DEPTH",
    "MAX_NODES",
    "INT_LIMIT",
    "read_input",
    "read_text",
    "parse_json",
    "parse_yaml",
    "parse_structured",
    "load_structured",
    "OutputPlan",
    "same_file",
]

#: Largest input file read (bytes); a larger file (or an endless one such as /dev/zero) is refused.
MAX_INPUT_BYTES = 256 * 1024 * 1024
#: Deepest nesting of objects/lists accepted in a JSON or YAML input.
MAX_DEPTH = 64
#: Most values (scalars, lists, objects) in one JSON or YAML input, YAML aliases counted expanded.
MAX_NODES = 20_000_000
#: Integers at least this large in magnitude are read as +-inf (they fit no int64 or float64 field;
#: the validators then refuse them as not finite, naming the field).
INT_LIMIT = 2**63


def _error(message: str) -> Exception:
    from mirror_fg.core.errors import DatasetError

    return DatasetError(message)


def _write_error(target: str, exc: OSError) -> Exception:
    from mirror_fg.core.errors import OutputError

    return OutputError(f"{target}: cannot write: {exc.strerror or exc}")


# --------------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------------


def read_input(path: str | os.PathLike[str], limit: int = MAX_INPUT_BYTES) -> bytes:
    """The bytes of ``path`` (``-``: standard input), read once and at most ``limit`` bytes."""
    source = os.fspath(path)
    try:
        if source == "-":
            return _read_bounded(sys.stdin.buffer, source, limit)
        with open(source, "rb") as handle:
            return _read_bounded(handle, source, limit)
    except IsADirectoryError:
        raise _error(f"{source}: cannot read file: is a directory") from None
    except OSError as exc:
        raise _error(f"{source}: cannot read file: {exc.strerror or exc}") from None


def _read_bounded(handle: Any, source: str, limit: int) -> bytes:
    data = handle.read(limit + 1)
    if len(data) > limit:
        raise _error(f"{source}: larger than {limit // (1024 * 1024)} MiB, refused (an endless or wrong file?)")
    return data


def read_text(path: str | os.PathLike[str], limit: int = MAX_INPUT_BYTES) -> str:
    """The UTF-8 text of ``path`` (a BOM is dropped), read once; DatasetError naming the file otherwise."""
    source = os.fspath(path)
    raw = read_input(source, limit)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise _error(f"{source}: not UTF-8 text (byte {exc.start})") from None


_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')


def _json_depth(text: str) -> int:
    """Deepest nesting of ``[``/``{`` in JSON text, strings skipped (no recursion)."""
    bare = _JSON_STRING.sub('""', text).encode("utf-8", "surrogatepass")
    raw = np.frombuffer(bare, dtype=np.uint8)
    step = np.isin(raw, (ord("["), ord("{"))).astype(np.int64) - np.isin(raw, (ord("]"), ord("}")))
    return int(np.cumsum(step).max(initial=0))


def parse_json(text: str, source: str) -> Any:
    """Parse JSON within the bounds above; a key repeated in one object is an error."""
    if _json_depth(text) > MAX_DEPTH:
        raise _error(f"{source}: nested more than {MAX_DEPTH} levels deep, refused")

    def no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in pairs:
            if key in out:
                raise _error(f"{source}: key {_quote(key)} appears twice in one JSON object")
            out[key] = value
        return out

    def bounded_int(digits: str) -> int | float:
        if len(digits.lstrip("-")) > 19:  # also spares int() its 4300-digit ValueError
            return -math.inf if digits.startswith("-") else math.inf
        value = int(digits)
        return value if abs(value) < INT_LIMIT else (math.inf if value > 0 else -math.inf)

    try:
        data = json.loads(text, object_pairs_hook=no_duplicates, parse_int=bounded_int)
    except json.JSONDecodeError as exc:
        raise _error(f"{source}: not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}") from None
    except RecursionError:  # the depth scan above makes this unreachable in practice
        raise _error(f"{source}: nested too deeply") from None
    return data


def parse_yaml(text: str, source: str) -> Any:
    """Parse YAML (safe tags only) within the bounds above; aliases are counted as expanded."""
    import yaml

    depth = 0
    try:
        for event in yaml.parse(text, Loader=yaml.SafeLoader):  # events: iterative, no recursion
            if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    raise _error(f"{source}: nested more than {MAX_DEPTH} levels deep, refused")
            elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
        loader = _UniqueKeyLoader(text)
        try:
            node = loader.get_single_node()
            if node is None:
                return None
            _check_yaml_size(node, source)
            data = loader.construct_document(node)
        finally:
            loader.dispose()
    except _DuplicateKey as exc:
        raise _error(f"{source}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "syntax error"
        raise _error(f"{source}: not valid YAML: {problem}{at}") from None
    except RecursionError:
        raise _error(f"{source}: nested too deeply") from None
    return _bound_integers(data)


def parse_structured(text: str, source: str) -> Any:
    """JSON where ``source`` ends in .json, else YAML (JSON is YAML)."""
    if source.lower().endswith(".json"):
        return parse_json(text, source)
    return parse_yaml(text, source)


def load_structured(path: str | os.PathLike[str], where: str | None = None) -> Any:
    """Read a JSON (by suffix) or YAML file once and parse it; messages start with ``where``."""
    source = os.fspath(path)
    text = read_text(source)
    where = where or source
    return parse_json(text, where) if source.lower().endswith(".json") else parse_yaml(text, where)


def _check_yaml_size(root: Any, source: str) -> None:
    """Refuse a YAML node graph with more than MAX_NODES values once its aliases are expanded."""
    import yaml

    sizes: dict[int, int] = {}
    stack: list[tuple[Any, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        if id(node) in sizes:
            continue
        if isinstance(node, yaml.ScalarNode):
            sizes[id(node)] = 1
            continue
        children = [n for pair in node.value for n in pair] if isinstance(node, yaml.MappingNode) else list(node.value)
        if not children_done:
            stack.append((node, True))
            stack.extend((child, False) for child in children if id(child) not in sizes)
            continue
        total = 1 + sum(sizes.get(id(child), 0) for child in children)
        if total > MAX_NODES:
            raise _error(f"{source}: more than {MAX_NODES} values once its aliases are expanded, refused")
        sizes[id(node)] = total


def _bound_integers(data: Any) -> Any:
    """``data`` with every integer of magnitude >= INT_LIMIT replaced by +-inf (iterative; shared
    objects visited once)."""
    def bounded(value: Any) -> Any:
        if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= INT_LIMIT:
            return math.inf if value > 0 else -math.inf
        return value

    seen: set[int] = set()
    stack = [data]
    while stack:
        value = stack.pop()
        if not isinstance(value, (dict, list)) or id(value) in seen:
            continue
        seen.add(id(value))
        if isinstance(value, dict):
            for key in list(value):
                value[key] = bounded(value[key])
                stack.append(value[key])
        else:
            for i, item in enumerate(value):
                value[i] = bounded(item)
                stack.append(value[i])
    return bounded(data)


class _DuplicateKey(Exception):
    pass


def _make_loader() -> Any:
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def construct_mapping(loader: Any, node: Any, deep: bool = False) -> dict[Any, Any]:
        loader.flatten_mapping(node)
        out: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            key = loader.construct_object(key_node, deep=deep)
            try:
                hash(key)
            except TypeError:
                raise _DuplicateKey(f"a key that is not a scalar (line {key_node.start_mark.line + 1})") from None
            if key in out:
                raise _DuplicateKey(f"key {_quote(key)} appears twice in one mapping "
                                    f"(line {key_node.start_mark.line + 1})")
            out[key] = loader.construct_object(value_node, deep=deep)
        return out

    Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, construct_mapping)
    return Loader


_UniqueKeyLoader = _make_loader()


def _quote(value: Any, limit: int = 60) -> str:
    from mirror_fg.io.dataset import _short

    return _short(value, limit)


# --------------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------------


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
                raise _error(f"{target}: the {role} and the {other_role} would be the same file")
        self._check_not_input(target, role)
        kind = _existing_kind(target)
        if kind == "directory":
            raise _error(f"{target}: is a directory; give a file name for the {role}")
        if kind not in (None, "file", "character device"):
            raise _error(f"{target}: is a {kind}; the {role} must go to a regular file")
        if kind == "file" and marker is not None and marker not in _head(target):
            raise _error(f"{target}: exists and was not written by mirror-fg; refusing to replace it with the "
                         f"{role} (move it, or choose another output name)")
        if kind is None:
            parent = _nearest_existing_parent(target)
            if parent is not None and not os.path.isdir(parent):
                raise _error(f"{target}: cannot create the {role}: {parent} is a file, not a directory")
        self.outputs[target] = role
        return target

    def is_device(self, path: str | os.PathLike[str]) -> bool:
        """Whether ``path`` is a character device (written into, e.g. /dev/null)."""
        return _existing_kind(os.fspath(path)) == "character device"

    def _check_not_input(self, target: str, role: str) -> None:
        for source in self.inputs:
            if same_file(source, target):
                raise _error(f"{target}: refusing to write the {role} over an input file "
                             f"({source}); choose another name")

    def commit(self, contents: Mapping[str | os.PathLike[str], str | bytes]) -> list[Path]:
        """Write every ``{path: content}`` (text is UTF-8): temporary files first, then renames.

        Each path must have been :meth:`add`-ed. Any failure before the renames removes every
        temporary file and leaves every existing file untouched (DatasetError naming the file).
        """
        staged: list[tuple[str, str]] = []  # (temporary, target)
        devices: list[tuple[str, bytes]] = []
        try:
            for path, data in contents.items():
                target = os.fspath(path)
                if target not in self.outputs:
                    raise ValueError(f"{target}: not an output of this plan")
                raw = data.encode("utf-8") if isinstance(data, str) else data
                if self.is_device(target):
                    devices.append((target, raw))
                else:
                    staged.append((_stage(target, raw), os.path.realpath(target)))
        except BaseException:
            for tmp, _ in staged:
                _unlink(tmp)
            raise
        renamed = 0
        try:
            for tmp, target in staged:
                os.replace(tmp, target)
                renamed += 1
        except BaseException:
            for tmp, _ in staged[renamed:]:
                _unlink(tmp)
            raise
        for target, raw in devices:
            try:
                with open(target, "wb") as handle:
                    handle.write(raw)
            except OSError as exc:
                raise _write_error(target, exc) from None
        return [Path(p) for p in contents]


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


def _head(path: str, size: int = 512) -> bytes:
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


def _stage(target: str, raw: bytes) -> str:
    """Write ``raw`` to a temporary file beside ``target`` (through symlinks); return its path."""
    real = os.path.realpath(target)  # keep a symlink a symlink: replace what it points to
    directory = os.path.dirname(real)
    try:
        os.makedirs(directory, exist_ok=True)  # "-o out/result.json" creates out/
        fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(real)}.", suffix=".tmp", dir=directory)
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
