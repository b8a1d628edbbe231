"""Checked values of scenario tables: one-line errors that name the key and what is expected.

Every reader of a scenario table (the loader and each sensor kind) takes its numbers,
vectors and intervals through these functions, which raise
:class:`~dfusion.errors.ValidationError` naming the key; the loader prefixes the file
and the table.
"""
from __future__ import annotations

import difflib
import math
from typing import Any, Iterable, Mapping

import numpy as np

from dfusion.errors import ValidationError
from dfusion.geometry import WaypointPath
from dfusion.linalg import Array

__all__ = ["number", "integer", "vector", "intervals", "check_keys", "suggest", "waypoint_path"]

_REQUIRED = object()


def suggest(word: str, choices: Iterable[str]) -> str:
    """``" (did you mean 'x'?)"`` for the closest of ``choices``, or ``""``."""
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def check_keys(table: Mapping[str, Any], allowed: Iterable[str], what: str) -> None:
    """Raise for the first key of ``table`` not in ``allowed``, suggesting the closest one."""
    allowed = set(allowed)
    for key in table:
        if key not in allowed:
            raise ValidationError(f"unknown key {key!r}{suggest(key, allowed)}; {what} takes "
                                  f"{', '.join(sorted(allowed))}")


def number(table: Mapping[str, Any], key: str, default: Any = _REQUIRED, *, positive: bool = False,
           nonneg: bool = False) -> float:
    """``table[key]`` (or ``default``) as a finite float; with ``positive`` / ``nonneg`` its sign checked."""
    v = table.get(key, default)
    if v is _REQUIRED:
        raise ValidationError(f"{key} is required")
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValidationError(f"{key} must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise ValidationError(f"{key} must be positive, got {v!r}")
    if nonneg and v < 0:
        raise ValidationError(f"{key} must be non-negative, got {v!r}")
    return float(v)


def integer(table: Mapping[str, Any], key: str, default: Any = _REQUIRED, *, minimum: int | None = None) -> int:
    """``table[key]`` (or ``default``) as an integer of at least ``minimum``."""
    v = table.get(key, default)
    if v is _REQUIRED:
        raise ValidationError(f"{key} is required")
    if isinstance(v, bool) or not isinstance(v, int) or (minimum is not None and v < minimum):
        bound = f" >= {minimum}" if minimum is not None else ""
        raise ValidationError(f"{key} must be an integer{bound}, got {v!r}")
    return int(v)


def vector(table: Mapping[str, Any], key: str, sizes: tuple[int, ...]) -> Array:
    """``table[key]`` as a float vector whose length is one of ``sizes``."""
    v = table.get(key)
    if not (isinstance(v, list) and len(v) in sizes and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in v)):
        raise ValidationError(f"{key} must be a list of {' or '.join(map(str, sizes))} finite numbers, got {v!r}")
    return np.asarray(v, dtype=float)


def intervals(value: Any, key: str) -> list[tuple[float, float]]:
    """A list of ``[start, end]`` pairs with ``end >= start``."""
    if not isinstance(value, list):
        raise ValidationError(f"{key} must be a list of [start, end] pairs")
    out = []
    for i, iv in enumerate(value):
        if not (isinstance(iv, list) and len(iv) == 2):
            raise ValidationError(f"{key}[{i}] must be a [start, end] pair")
        a, b = (number({f"{key}[{i}]": x}, f"{key}[{i}]") for x in iv)
        if b < a:
            raise ValidationError(f"{key}[{i}]: end {b} before start {a}")
        out.append((a, b))
    return out


def waypoint_path(table: Mapping[str, Any]) -> WaypointPath | None:
    """The path of a moving node (keys ``path``, ``speed``, ``loop``, ``path_start``), or None without ``path``."""
    if "path" not in table:
        for key in ("speed", "loop", "path_start"):
            if key in table:
                raise ValidationError(f"{key} needs a path = [[x, y], ...]")
        return None
    pts = table["path"]
    if not (isinstance(pts, list) and len(pts) >= 2 and all(
            isinstance(p, list) and len(p) == 2 and all(
                isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in p) for p in pts)):
        raise ValidationError(f"path must be a list of at least two [x, y] waypoints, got {pts!r}")
    loop = table.get("loop", False)
    if not isinstance(loop, bool):
        raise ValidationError(f"loop must be true or false, got {loop!r}")
    return WaypointPath(pts, number(table, "speed", positive=True), number(table, "path_start", 0.0, nonneg=True), loop)
