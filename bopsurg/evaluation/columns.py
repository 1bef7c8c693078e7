"""Tables as named numpy columns: what ``bopsurg eval`` computes on, without pandas.

Importing pandas costs more than the whole evaluation of a small split, so the evaluation
keeps its per-estimate and per-GT rows as :data:`Columns` (an ordered ``{name: (N,)
array}``), joins and groups them with sorting and searching, and writes ``errors.csv``
itself, byte for byte as ``DataFrame.to_csv`` does. DataFrames are built on request only
(:func:`to_frame`), e.g. by :attr:`bopsurg.evaluation.runner.Evaluation.errors`.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    import pandas as pd

#: A table: equal-length (N,) arrays by column name, in column order.
Columns = dict[str, NDArray[Any]]
I64 = NDArray[np.int64]


def n_rows(cols: Mapping[str, NDArray[Any]]) -> int:
    """N, the length of the columns (0 without columns)."""
    return int(next(iter(cols.values())).shape[0]) if cols else 0


def take(cols: Mapping[str, NDArray[Any]], rows: NDArray[Any]) -> Columns:
    """The rows ``rows`` (indices or a boolean mask) of every column."""
    return {name: col[rows] for name, col in cols.items()}


def concat(parts: list[Columns]) -> Columns:
    """Rows of ``parts`` one after another (the columns of the first part)."""
    if not parts:
        return {}
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def to_frame(cols: Mapping[str, NDArray[Any]]) -> pd.DataFrame:
    """A DataFrame of the columns (imports pandas)."""
    import pandas as pd

    return pd.DataFrame(dict(cols))


def from_frame(frame: pd.DataFrame) -> Columns:
    """The columns of a DataFrame."""
    return {str(c): frame[c].to_numpy() for c in frame.columns}


class FrameField:
    """A dataclass field kept as :data:`Columns` and read as a DataFrame (built on first
    read, then kept): set it to either; :meth:`columns` gives the columns without pandas."""

    def __set_name__(self, owner: type, name: str) -> None:
        self._name = name

    def __get__(self, obj: object, objtype: type | None = None) -> pd.DataFrame:
        if obj is None:
            raise AttributeError(self._name)  # (a dataclass field without a default)
        cache = vars(obj).setdefault("_frames", {})
        if self._name not in cache:
            cache[self._name] = to_frame(vars(obj)["_columns"][self._name])
        frame: pd.DataFrame = cache[self._name]
        return frame

    def __set__(self, obj: object, value: Columns | pd.DataFrame) -> None:
        vars(obj).setdefault("_columns", {})[self._name] = as_columns(value)
        vars(obj).setdefault("_frames", {}).pop(self._name, None)

    @staticmethod
    def columns(obj: object, name: str) -> Columns:
        """The columns of field ``name`` of ``obj``."""
        cols: Columns = vars(obj)["_columns"][name]
        return cols


def as_columns(rows: Columns | pd.DataFrame) -> Columns:
    """``rows`` as columns: a DataFrame's (public functions take either), columns as they are."""
    if isinstance(rows, dict):
        return rows
    return from_frame(rows)


def group_labels(*keys: NDArray[Any]) -> I64:
    """(N,) group of each row of equal ``keys``: 0, 1, … in the keys' sorted order (as
    ``DataFrame.groupby(keys, sort=True).ngroup()``)."""
    if not keys or keys[0].shape[0] == 0:
        return np.zeros(0 if not keys else keys[0].shape[0], dtype=np.int64)
    order = np.lexsort(keys[::-1])
    new = np.zeros(order.size, dtype=bool)
    new[0] = True
    for k in keys:
        ks = k[order]
        new[1:] |= ks[1:] != ks[:-1]
    labels = np.empty(order.size, dtype=np.int64)
    labels[order] = np.cumsum(new) - 1
    return labels


def match_rows(left: tuple[NDArray[Any], ...], right: tuple[NDArray[Any], ...]) -> I64:
    """For each row of ``left`` keys, the row of ``right`` with equal keys (-1 if none).

    The rows of ``right`` must have distinct keys.
    """
    n_left = left[0].shape[0]
    labels = group_labels(*(np.concatenate([a, b]) for a, b in zip(left, right, strict=True)))
    lab_l, lab_r = labels[:n_left], labels[n_left:]
    where = np.full(int(labels.max(initial=-1)) + 1, -1, dtype=np.int64)
    where[lab_r] = np.arange(lab_r.size, dtype=np.int64)
    out: I64 = where[lab_l] if n_left else np.zeros(0, dtype=np.int64)
    return out


def join_pairs(
    left: tuple[NDArray[Any], ...], right: tuple[NDArray[Any], ...], right_order: NDArray[Any]
) -> tuple[I64, I64]:
    """Every (left row, right row) with equal keys, by left row, then ``right_order``, then
    right row (an inner ``merge`` sorted by the left row and ``right_order``, stably)."""
    n_left = left[0].shape[0]
    labels = group_labels(*(np.concatenate([a, b]) for a, b in zip(left, right, strict=True)))
    lab_l, lab_r = labels[:n_left], labels[n_left:]
    by_key = np.lexsort((right_order, lab_r))
    sorted_r = lab_r[by_key]
    lo = np.searchsorted(sorted_r, lab_l, side="left")
    counts = np.searchsorted(sorted_r, lab_l, side="right") - lo
    li = np.repeat(np.arange(n_left, dtype=np.int64), counts)
    within = np.arange(li.size) - np.repeat(np.cumsum(counts) - counts, counts)
    ri: I64 = by_key[np.repeat(lo, counts) + within].astype(np.int64)
    return li, ri


def pick(values: NDArray[Any], rows: I64, fill: float = np.nan) -> NDArray[Any]:
    """``values[rows]``, ``fill`` where ``rows`` is -1 (a row of :func:`match_rows` without
    a match)."""
    if values.size == 0:
        return np.full(rows.shape, fill)
    return np.where(rows >= 0, values[np.maximum(rows, 0)], fill)


def csv_text(cols: Mapping[str, NDArray[Any]], float_format: str = "%.9g") -> str:
    """The columns as ``DataFrame.to_csv(index=False, float_format=...)`` writes them:
    integers in full, floats with ``float_format``, NaN empty, booleans ``True``/``False``."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(list(cols))
    cells = [_cells(col, float_format) for col in cols.values()]
    writer.writerows(zip(*cells, strict=True))
    return buf.getvalue()


def _cells(col: NDArray[Any], float_format: str) -> list[str]:
    if col.dtype.kind == "f":
        return ["" if math.isnan(v) else float_format % v for v in col.tolist()]
    return [str(v) for v in col.tolist()]
