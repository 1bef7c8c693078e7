"""Schema checks shared by the BOP file parsers: raise at the first problem, or collect all.

Loaders raise the first problem (:class:`Issues` with ``collect=False``); ``check_dataset``
collects every problem of a file and goes on (``collect=True``), parsing the entries that
are fine and skipping the others.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from bopsurg.errors import DatasetError, InputError

T = TypeVar("T")


class Issues:
    """Where the problems of one file go.

    Args:
        path: The file being parsed (named in every message).
        collect: Collect problems in :attr:`items` instead of raising the first one.
        error: The :class:`~bopsurg.errors.InputError` subclass to raise.
    """

    def __init__(
        self, path: str | Path, *, collect: bool = False, error: type[InputError] = DatasetError
    ) -> None:
        self.path = str(path)
        self.collect = collect
        self.error = error
        self.items: list[tuple[str | None, str]] = []

    def __call__(self, reason: str, field: str | None = None) -> None:
        """Report a problem: raise it, or remember it as ``(field, reason)``."""
        if not self.collect:
            raise self.error(reason, path=self.path, field=field)
        self.items.append((field, reason))

    def __len__(self) -> int:
        return len(self.items)


def describe(value: Any) -> str:
    """A short description of a JSON value for messages."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def is_number(value: Any) -> bool:
    """Whether ``value`` is a JSON number (bool is not, although it is an int in Python)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def get_int(value: Any, field: str, issues: Issues, *, minimum: int | None = None) -> int | None:
    """``value`` as an int (integral floats such as ``3.0`` accepted), else report and None."""
    if type(value) is int or (
        isinstance(value, float) and math.isfinite(value) and value.is_integer()
    ):
        out = int(value)
        if minimum is not None and out < minimum:
            issues(f"must be >= {minimum}, got {out}", field)
            return None
        return out
    issues(f"expected an integer, got {describe(value)}", field)
    return None


def get_float(value: Any, field: str, issues: Issues) -> float | None:
    """``value`` as a finite float, else report and None."""
    if is_number(value):
        out = float(value)
        if math.isfinite(out):
            return out
        issues(f"must be finite, got {out}", field)
        return None
    issues(f"expected a number, got {describe(value)}", field)
    return None


def get_floats(
    value: Any, n: int, field: str, issues: Issues, *, what: str = ""
) -> NDArray[np.float64] | None:
    """``value`` as ``n`` finite floats (a flat list), else report and None."""
    if not isinstance(value, list) or len(value) != n:
        got = f"{len(value)} values" if isinstance(value, list) else describe(value)
        issues(f"expected a list of {n} numbers{what}, got {got}", field)
        return None
    # Plain Python checks: much faster than numpy for a handful of values per entry.
    if not all(type(v) is float or type(v) is int for v in value):
        bad = next((v for v in value if not is_number(v)), None)
        if bad is not None:
            issues(f"expected numbers, got {describe(bad)}", field)
            return None
    if not all(math.isfinite(v) for v in value):
        issues("contains NaN or inf", field)
        return None
    return np.array(value, dtype=np.float64)


def trusted(cls: type[T], **fields: Any) -> T:
    """An instance of the frozen dataclass ``cls`` built from already validated fields,
    skipping ``__post_init__`` (the parsers validate every value themselves)."""
    obj = object.__new__(cls)
    for name, value in fields.items():
        object.__setattr__(obj, name, value)
    return obj


def get_dict(value: Any, field: str | None, issues: Issues, what: str) -> dict[Any, Any] | None:
    """``value`` if it is a JSON object, else report and None."""
    if isinstance(value, dict):
        return value
    issues(f"expected {what} (a JSON object), got {type(value).__name__}", field)
    return None


def get_list(value: Any, field: str | None, issues: Issues, what: str) -> list[Any] | None:
    """``value`` if it is a JSON array, else report and None."""
    if isinstance(value, list):
        return value
    issues(f"expected {what} (a JSON array), got {type(value).__name__}", field)
    return None


def id_key(key: Any, field: str | None, issues: Issues, what: str = "image id") -> int | None:
    """A top-level key that must be a non-negative integer id (after ``keys_to_int``)."""
    if isinstance(key, int) and not isinstance(key, bool) and key >= 0:
        return key
    issues(f"{what} must be a non-negative integer, got {describe(key)}", field)
    return None
