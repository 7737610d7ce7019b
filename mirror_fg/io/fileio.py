"""Reading input files once, within bounds (writing them: :mod:`mirror_fg.io.output`).

Every file the user gives goes through here:

- :func:`read_input` reads a file (or ``-``, standard input) exactly once, at most
  :data:`MAX_INPUT_BYTES`, so a named pipe, ``/dev/stdin`` or ``/dev/zero`` is read once and bounded.
- :func:`parse_json` / :func:`parse_yaml` / :func:`parse_structured` parse that text into plain Python
  values within :data:`MAX_DEPTH` levels of nesting, :data:`MAX_NODES` values (YAML aliases counted
  as often as they are expanded, so an alias bomb is refused before it is built; a YAML file also at
  most :data:`MAX_YAML_NODES` nodes as written, counted before any is kept) and integers smaller than
  :data:`INT_LIMIT` (larger ones become infinities, which every validator refuses by name); a key
  repeated in one object is an error. Extra memory is a few copies of the text, never a cost per
  character (the string pattern of the JSON depth scan keeps no backtracking state).
- :func:`open_video` / :func:`video_frame_count` open a video within :data:`MAX_IMAGE_PIXELS` per frame.
- :func:`native_stderr` keeps what native decoders (libpng, libjpeg, FFmpeg, OpenCV's FileStorage)
  write to file descriptor 2 while they read a user's file, so that the problem is reported in our one
  line; :data:`MAX_IMAGE_PIXELS` bounds what an image or video frame may decode to.

Every problem is a :class:`~mirror_fg.data.DatasetError` with one line that names the file.
Formats: ``docs/formats.md``.
"""
from __future__ import annotations

import json
import math
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError

from mirror_fg.core.values import clip, short

__all__ = [
    "MAX_INPUT_BYTES",
    "MAX_DEPTH",
    "MAX_NODES",
    "MAX_YAML_NODES",
    "INT_LIMIT",
    "read_input",
    "read_text",
    "NotTextError",
    "media_kind",
    "parse_json",
    "parse_yaml",
    "parse_structured",
    "load_structured",
    "resolve_path",
    "MAX_IMAGE_PIXELS",
    "NativeOutput",
    "native_stderr",
    "open_video",
    "video_frame_count",
]

#: Largest input file read (bytes); a larger file (or an endless one such as /dev/zero) is refused.
MAX_INPUT_BYTES = 256 * 1024 * 1024
#: Deepest nesting of objects/lists accepted in a JSON or YAML input.
MAX_DEPTH = 64
#: Most values (scalars, lists, objects) in one JSON or YAML input, YAML aliases counted expanded.
MAX_NODES = 20_000_000
#: Most nodes (scalars, lists, mappings, aliases unexpanded) in one YAML input: PyYAML's composer keeps
#: every node (about 450 bytes each with libyaml, measured) before any is checked, so 1 million is ~0.5 GB
#: and 15 s; the 256 MiB limit alone would allow 100 million (45 GB). JSON has no such limit.
MAX_YAML_NODES = 1_000_000
#: Integers at least this large in magnitude are read as +-inf (they fit no int64 or float64 field;
#: the validators then refuse them as not finite, naming the field).
INT_LIMIT = 2**63
#: Largest image or video frame read (width x height, pixels): 8000 x 6000 photographs pass; a larger
#: image is refused from its header before it is decoded (a 20000 x 20000 PNG of 2 MB decodes to GBs).
MAX_IMAGE_PIXELS = 100_000_000


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
        raise DatasetError(f"{source}: cannot read file: is a directory") from None
    except OSError as exc:
        raise DatasetError(f"{source}: cannot read file: {exc.strerror or exc}") from None


def _read_bounded(handle: Any, source: str, limit: int) -> bytes:
    data = handle.read(limit + 1)
    if len(data) > limit:
        raise DatasetError(f"{source}: larger than {limit // (1024 * 1024)} MiB, refused (an endless or wrong file?)")
    return data


class NotTextError(DatasetError):
    """A file read as text (JSON / YAML) that is not: ``kind`` names it where it is a photograph or a
    video ("a JPEG image"), else None. Exit 2."""

    def __init__(self, message: str, kind: str | None = None):
        super().__init__(message)
        self.kind = kind


#: The first bytes of the image and video files a user may give where a text file is wanted.
_MEDIA_MAGIC = (
    (0, b"\xff\xd8\xff", "a JPEG image"), (0, b"\x89PNG\r\n\x1a\n", "a PNG image"), (0, b"GIF8", "a GIF image"),
    (0, b"BM", "a BMP image"), (0, b"II*\x00", "a TIFF image"), (0, b"MM\x00*", "a TIFF image"),
    (8, b"WEBP", "a WebP image"), (8, b"AVI ", "an AVI video"), (4, b"ftyp", "a video (MP4/MOV) or HEIC photo"),
    (0, b"\x1a\x45\xdf\xa3", "a video (MKV/WebM)"),
)


def media_kind(raw: bytes) -> str | None:
    """"a JPEG image", "a video (MP4/MOV) ..." where ``raw`` starts as such a file does, else None."""
    return next((kind for offset, magic, kind in _MEDIA_MAGIC if raw[offset:offset + len(magic)] == magic), None)


def read_text(path: str | os.PathLike[str], limit: int = MAX_INPUT_BYTES) -> str:
    """The UTF-8 text of ``path`` (a BOM is dropped), read once; DatasetError naming the file otherwise
    (:class:`NotTextError`, saying so where it is a photograph or a video)."""
    source = os.fspath(path)
    raw = read_input(source, limit)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        kind = media_kind(raw)
        if kind is not None:
            raise NotTextError(f"{source}: is {kind}, not a text file (JSON or YAML)", kind) from None
        raise NotTextError(f"{source}: not UTF-8 text (byte {exc.start})") from None


# A JSON string, written so that matching it needs no memory per character: the old form
# '"(?:[^"\\]|\\.)*"' kept one backtracking entry per character, 6.5 GB (MemoryError) for one 50 MB
# string value. Possessive (*+) repeats give nothing back, which here changes no match: the character
# classes exclude what may follow them.
_JSON_STRING = re.compile(r'"[^"\\]*+(?:\\.[^"\\]*+)*+"')
#: Bytes scanned at a time by :func:`_json_shape` (its extra memory is a few times this).
_SCAN_BLOCK = 4 * 1024 * 1024


def _json_shape(text: str) -> tuple[int, int]:
    """``(deepest nesting of [/{, how many values)`` of JSON text, strings skipped (no recursion, bounded
    memory). Each list or object with k >= 1 items holds k - 1 commas, so the values are the commas
    plus the non-empty lists and objects plus one (the top-level value); exact for valid JSON."""
    bare = _JSON_STRING.sub('""', text).encode("utf-8", "surrogatepass")
    depth = deepest = values = 0
    last = 0  # the previous block's last byte that is not white space
    for start in range(0, len(bare), _SCAN_BLOCK):
        raw = np.frombuffer(bare, dtype=np.uint8, count=min(_SCAN_BLOCK, len(bare) - start), offset=start)
        raw = raw[~np.isin(raw, np.frombuffer(b" \t\r\n", dtype=np.uint8))]
        if not raw.size:
            continue
        opens = (raw == ord("[")) | (raw == ord("{"))
        closes = (raw == ord("]")) | (raw == ord("}"))
        levels = np.cumsum(opens.astype(np.int32) - closes, dtype=np.int64) + depth
        deepest, depth = max(deepest, int(levels.max())), int(levels[-1])
        empty = int(np.count_nonzero(opens[:-1] & closes[1:])) + (last in b"[{" and bool(closes[0]))
        values += int(np.count_nonzero(raw == ord(","))) + int(np.count_nonzero(opens)) - empty
        last = int(raw[-1])
    return deepest, values + 1


def parse_json(text: str, source: str) -> Any:
    """Parse JSON within the bounds above; a key repeated in one object is an error."""
    depth, values = _json_shape(text)
    if depth > MAX_DEPTH:
        raise DatasetError(f"{source}: nested more than {MAX_DEPTH} levels deep, refused")
    if values > MAX_NODES:  # 20 million empty objects ("{},", 3 bytes each) are 1.3 GB in Python
        raise DatasetError(f"{source}: more than {MAX_NODES} values, refused")

    def no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in pairs:
            if key in out:
                raise DatasetError(f"{source}: key {_quote(key)} appears twice in one JSON object")
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
        raise DatasetError(f"{source}: not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}") from None
    except RecursionError:  # the depth scan above makes this unreachable in practice
        raise DatasetError(f"{source}: nested too deeply") from None
    return data


def parse_yaml(text: str, source: str) -> Any:
    """Parse YAML (safe tags only) within the bounds above; aliases are counted as expanded."""
    import yaml

    depth = nodes = 0
    try:
        for event in yaml.parse(text, Loader=_LOADER_BASE):  # events: iterative, no recursion, one at a time
            if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    raise DatasetError(f"{source}: nested more than {MAX_DEPTH} levels deep, refused")
            elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
                continue
            nodes += isinstance(event, yaml.NodeEvent)
            if nodes > MAX_YAML_NODES:
                raise DatasetError(f"{source}: more than {MAX_YAML_NODES} values in a YAML file, refused "
                                   "(write data this large as JSON)")
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
        raise DatasetError(f"{source}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "syntax error"
        raise DatasetError(f"{source}: not valid YAML: {problem}{at}") from None
    except RecursionError:
        raise DatasetError(f"{source}: nested too deeply") from None
    return _bound_integers(data)


def parse_structured(text: str, path: str | os.PathLike[str], where: str | None = None) -> Any:
    """The text of file ``path`` parsed as JSON where its name ends in .json, else as YAML (JSON is
    YAML); messages start with ``where`` (default: the path)."""
    source = os.fspath(path)
    where = where or source
    return parse_json(text, where) if source.lower().endswith(".json") else parse_yaml(text, where)


def load_structured(path: str | os.PathLike[str], where: str | None = None) -> Any:
    """Read a JSON or YAML file once (:func:`read_text`) and parse it (:func:`parse_structured`)."""
    return parse_structured(read_text(path), path, where)


def resolve_path(path: str, base_dir: str) -> str:
    """``path`` (``~`` expanded) taken from ``base_dir`` where relative, normalised; links not resolved."""
    path = os.path.expanduser(path)
    return os.path.normpath(path if os.path.isabs(path) else os.path.join(base_dir, path))


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
            raise DatasetError(f"{source}: more than {MAX_NODES} values once its aliases are expanded, refused")
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


def _loader_base() -> Any:
    """libyaml's safe loader where PyYAML was built with it (30x faster than the pure-Python one), else that."""
    import yaml

    return getattr(yaml, "CSafeLoader", yaml.SafeLoader)


_LOADER_BASE = _loader_base()


def _make_loader() -> Any:
    import yaml

    class Loader(_LOADER_BASE):  # type: ignore[misc,valid-type]
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
    return short(value, limit)


# --------------------------------------------------------------------------------------------------
# Videos
# --------------------------------------------------------------------------------------------------


# FFmpeg's decoder threads log damaged frames ("[mpeg4 @ 0x...] header damaged") to fd 2 at any moment,
# also outside native_stderr; OpenCV reads this level once, when it first loads FFmpeg: quiet (-8) unless
# the user set one. A frame that cannot be decoded is reported per frame instead (vision/detect.py).
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")


def open_video(path: str, where: str) -> Any:
    """An opened ``cv2.VideoCapture`` whose frames are within MAX_IMAGE_PIXELS (from the container's
    header, before any frame is decoded); DatasetError otherwise. The caller releases it."""
    import cv2

    with native_stderr() as native:
        vc = cv2.VideoCapture(path)
    if not vc.isOpened():
        vc.release()
        raise DatasetError(f"{where}: cannot open the video (unknown or broken format){native.detail}")
    w, h = vc.get(cv2.CAP_PROP_FRAME_WIDTH), vc.get(cv2.CAP_PROP_FRAME_HEIGHT)
    if not (math.isfinite(w) and math.isfinite(h)) or w * h > MAX_IMAGE_PIXELS:
        vc.release()
        raise DatasetError(f"{where}: frames of {w:.0f} x {h:.0f} pixels are above the limit of {MAX_IMAGE_PIXELS} pixels")
    return vc


def video_frame_count(path: str, where: str) -> int:
    """The frame count a video's container reports, once a first frame was read (DatasetError otherwise)."""
    import cv2

    vc = open_video(path, where)
    try:
        with native_stderr() as native:
            ok, _ = vc.read()
        if not ok:
            raise DatasetError(f"{where}: cannot read a frame from the video{native.detail}")
        reported = vc.get(cv2.CAP_PROP_FRAME_COUNT)
        count = int(reported) if math.isfinite(reported) else 0
    finally:
        vc.release()
    if count <= 0:
        raise DatasetError(f"{where}: the video reports no frame count")
    return count


# --------------------------------------------------------------------------------------------------
# What native decoders write
# --------------------------------------------------------------------------------------------------


class NativeOutput:
    """What native code (libpng, libjpeg, FFmpeg, OpenCV) wrote to stderr inside :func:`native_stderr`."""

    def __init__(self) -> None:
        self.text = ""

    @property
    def problem(self) -> str:
        """The first line that is not marked as a mere warning (a decode error, corrupt data), short; ''."""
        for line in self.text.splitlines():
            if line.strip() and "warn" not in line.lower():
                return clip(line.strip())
        return ""

    @property
    def detail(self) -> str:
        """``": <problem>"`` to end a message with, or ''."""
        return f": {self.problem}" if self.problem else ""


@contextmanager
def native_stderr() -> Iterator[NativeOutput]:
    """Divert file descriptor 2 to a temporary file during native decoding; the text is kept, not printed.

    Native libraries write their own lines (``libpng error: IDAT: CRC error``) straight to fd 2, which
    would precede our one-line message. After the block, ``.text`` holds what they wrote (first 4 kB).
    When fd 2 cannot be duplicated (closed), nothing is diverted. Not thread-safe: fd 2 is per process.
    """
    out = NativeOutput()
    try:
        sys.stderr.flush()
    except (AttributeError, OSError, ValueError):
        pass
    try:
        saved = os.dup(2)
    except OSError:
        yield out
        return
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield out
            finally:
                os.dup2(saved, 2)
            tmp.seek(0)
            out.text = tmp.read(4096).decode("utf-8", "replace")
    finally:
        os.close(saved)
