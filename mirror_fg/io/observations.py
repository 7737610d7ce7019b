"""Hand-given pixel observations of a capture image (capture@1 ``images[].observations``): inline
``{name: [u, v]}``, or a file (JSON/YAML mapping, or ``name u v`` / ``u v`` lines in the order of the
target's fiducials)."""
from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from mirror_fg.core.errors import DatasetError
from mirror_fg.core.values import named_vectors, short, short_path
from mirror_fg.io.fileio import load_structured, resolve_path
from mirror_fg.io.target import Target

__all__ = ["observations_from"]


def observations_from(value: Any, target: Target, base_dir: str, where: str) -> dict[str, np.ndarray]:
    """Pixels ``{name: [u, v]}`` inline or from a file (JSON/YAML mapping, or ``name u v`` / ``u v`` lines,
    the latter in the order of ``target``'s fiducials); a relative path is taken from ``base_dir``."""
    if isinstance(value, str):
        path = resolve_path(value, base_dir)
        fwhere = f"{where}: observations file {short_path(value)!r}"
        if not os.path.isfile(path):
            raise DatasetError(f"{fwhere} not found")
        if path.lower().endswith((".json", ".yaml", ".yml")):
            value = load_structured(path, fwhere)
            where = fwhere
        else:
            return _observations_text(path, target, fwhere)
    if not isinstance(value, Mapping) or not value:
        raise DatasetError(f"{where}: observations must be a non-empty mapping {{name: [u, v]}} or a file, got {short(value)}")
    return named_vectors(value, 2, where, "point")


def _observations_text(path: str, target: Target, where: str) -> dict[str, np.ndarray]:
    try:
        with open(path, encoding="utf-8") as f:
            lines = [(n + 1, ln.split()) for n, ln in enumerate(f) if ln.strip() and not ln.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{where}: cannot read: {exc}") from None
    names = list(target.target_points())
    out: dict[str, np.ndarray] = {}
    unnamed = [ln for ln in lines if len(ln[1]) == 2]
    if unnamed and len(unnamed) != len(lines):
        raise DatasetError(f"{where}: mixes 'u v' and 'name u v' lines")
    if unnamed and len(lines) != len(names):
        raise DatasetError(
            f"{where}: has {len(lines)} 'u v' lines but the target has {len(names)} fiducials (one line each, in order)"
        )
    for k, (lineno, parts) in enumerate(lines):
        if len(parts) == 2:
            name, nums = names[k], parts
        elif len(parts) == 3:
            name, nums = parts[0], parts[1:]
        else:
            raise DatasetError(f"{where}: line {lineno}: expected 'u v' or 'name u v'")
        try:
            uv = np.array([float(x) for x in nums])
        except ValueError:
            raise DatasetError(f"{where}: line {lineno}: not numbers: {short(' '.join(nums))}") from None
        if not np.all(np.isfinite(uv)):
            raise DatasetError(f"{where}: line {lineno}: not finite")
        if name in out:
            raise DatasetError(f"{where}: line {lineno}: point {short(name)} given twice")
        out[name] = uv
    if not out:
        raise DatasetError(f"{where}: no observations in the file")
    return out
