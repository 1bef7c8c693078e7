"""Bootstrap 95 % intervals of the paper's table and the absolute-threshold scores.

The same resampling as :mod:`bopsurg.evaluation.bootstrap` (images or scenes drawn with
replacement, one weight per unit and replicate), applied to the GT instances of
:func:`bopsurg.evaluation.summary.paper_summary` (``visib_fract ≥ min_visib``): weighted
means, population standard deviations, medians (the resampled set's middle order
statistics), recalls at absolute thresholds (missed instances fail) and ADD / ADD-S AUC,
all replicates at once. Min and max get no interval (a bootstrap cannot go beyond them).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, overload

import numpy as np
from numpy.typing import NDArray

from bopsurg.atomic import atomic_path
from bopsurg.errors import BopsurgError, InputError
from bopsurg.evaluation.bootstrap import (
    Comparison,
    paired_comparisons,
    percentile_interval,
    resample_weights,
)
from bopsurg.evaluation.columns import (
    Columns,
    as_columns,
    group_labels,
    n_rows,
    take,
    to_frame,
)
from bopsurg.evaluation.summary import (
    ABS_THRESHOLDS,
    AUC_MAX_FRACTION,
    AUC_STEPS,
    recall_label,
)
from bopsurg.metrics.registry import METRICS, table_metrics

if TYPE_CHECKING:  # pandas for the rows compare reads (load_table_rows) only
    import pandas as pd

F64 = NDArray[np.float64]


def _units(rows: Columns, unit: str) -> NDArray[np.int64]:
    keys = ["scene_id"] if unit == "scene" else ["scene_id", "im_id"]
    return group_labels(*(np.asarray(rows[k]) for k in keys))


def weighted_median(values: F64, weights: F64) -> F64:
    """(B,) medians of ``values`` (N,) repeated by integer ``weights`` (B, N), as
    ``np.median`` of the repeated values (mean of the two middle ones for an even count)."""
    b, n = weights.shape
    if n == 0:
        return np.full(b, np.nan)
    order = np.argsort(values, kind="stable")
    v = values[order]
    cum = np.cumsum(weights[:, order], axis=1).astype(np.int64)  # (B, N), whole counts
    total = cum[:, -1]
    lo, hi = (total - 1) // 2, total // 2  # 0-based positions of the middle elements
    span = int(total.max()) + 2
    rows = np.arange(b, dtype=np.int64)[:, None] * span
    keys = (cum + rows).ravel()
    # Element at position p: the first sorted index whose cumulative count exceeds p.
    idx = np.searchsorted(keys, (np.c_[lo, hi] + rows).ravel(), side="right").reshape(b, 2)
    idx = np.minimum(idx - np.arange(b)[:, None] * n, n - 1)
    med = v[idx].mean(axis=1)
    return np.where(total > 0, med, np.nan)


#: Columns of the GT rows the table's replicates need (what ``bopsurg compare`` keeps).
#: Columns of a GT row that the intervals read: its image, and every registered metric.
ID_COLUMNS = ("scene_id", "im_id", "gt_id", "visib_fract", "diameter")


def _sample_columns() -> tuple[str, ...]:
    return (*ID_COLUMNS, *METRICS)  # read when called: a metric added to the registry counts


@overload
def table_rows(gt_rows: Columns, min_visib: float) -> Columns: ...
@overload
def table_rows(gt_rows: pd.DataFrame, min_visib: float) -> pd.DataFrame: ...
def table_rows(gt_rows: Columns | pd.DataFrame, min_visib: float) -> Columns | pd.DataFrame:
    """The GT instances of the table (``visib_fract ≥ min_visib``), columns it needs (as the
    rows given: columns or a DataFrame)."""
    cols = as_columns(gt_rows)
    keep = cols["visib_fract"] >= min_visib
    rows = take({c: cols[c] for c in _sample_columns() if c in cols}, keep)
    return rows if isinstance(gt_rows, dict) else to_frame(rows)


def summary_replicates(rows: Columns | pd.DataFrame, weights: F64) -> dict[str, F64]:
    """The table's numbers under each row of instance weights (B, R): ``{metric}_{mean|std|
    median}``, ``recall_{label}``, ``{add|adi}_auc``; (B,) each."""
    rows = as_columns(rows)
    total = weights.sum(axis=1)
    out: dict[str, F64] = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        for m in (t.name for t in table_metrics()):
            v = np.asarray(rows[m], dtype=np.float64)
            ok = np.isfinite(v)
            wv, vv = weights[:, ok], v[ok]
            n = wv.sum(axis=1)
            mean = wv @ vv / n
            out[f"{m}_mean"] = mean
            out[f"{m}_std"] = np.sqrt(np.maximum(wv @ (vv * vv) / n - mean * mean, 0.0))
            out[f"{m}_median"] = weighted_median(vv, wv)
        for col, th in ABS_THRESHOLDS:
            hit = np.asarray(rows[col], dtype=np.float64) < th  # NaN (missed) is no hit
            out[f"recall_{recall_label(col, th)}"] = weights @ hit / total
        s = np.arange(1, AUC_STEPS + 1) / AUC_STEPS
        max_th = AUC_MAX_FRACTION * np.asarray(rows["diameter"], dtype=np.float64)
        for col in (m.name for m in METRICS.values() if m.auc):
            if col in rows:
                e = np.asarray(rows[col], dtype=np.float64)
                ratio = np.where(np.isnan(e), np.inf, e) / max_th
                per_row = (ratio[None, :] < s[:, None]).mean(axis=0)  # each one's accuracy
                out[f"{col}_auc"] = weights @ per_row / total
    return out


def row_weights(rows: Columns | pd.DataFrame, replicates: int, seed: int, unit: str) -> F64:
    """(replicates, R) bootstrap weights of the rows, by their image or scene."""
    cols = as_columns(rows)
    if n_rows(cols) == 0:
        return np.zeros((replicates, 0))
    return resample_weights(_units(cols, unit), replicates, seed)


def summary_intervals(
    gt_rows: Columns | pd.DataFrame,
    min_visib: float,
    replicates: int,
    seed: int = 0,
    unit: str = "image",
) -> dict[str, Any]:
    """95 % intervals of ``summary.json``'s numbers: ``{"table": {metric: {"mean", "std",
    "median"}}, "recall": {label}, "add_auc", "adi_auc"}``, each ``(low, high)``.

    Args:
        gt_rows: The evaluation's GT rows (``scene_id``, ``im_id``, ``visib_fract``,
            ``diameter`` and the matched errors, NaN when missed).
        min_visib: Visibility threshold of the table.
        replicates: Bootstrap replicates.
        seed: Generator seed.
        unit: ``"image"`` or ``"scene"``.
    """
    rows = table_rows(as_columns(gt_rows), min_visib)
    reps = summary_replicates(rows, row_weights(rows, replicates, seed, unit))
    out: dict[str, Any] = {"table": {}, "recall": {}}
    for m in (t.name for t in table_metrics()):
        out["table"][m] = {
            k: percentile_interval(reps[f"{m}_{k}"]) for k in ("mean", "std", "median")
        }
    for col, th in ABS_THRESHOLDS:
        label = recall_label(col, th)
        out["recall"][label] = percentile_interval(reps[f"recall_{label}"])
    for col in (m.name for m in METRICS.values() if m.auc):
        if f"{col}_auc" in reps:
            out[f"{col}_auc"] = percentile_interval(reps[f"{col}_auc"])
    return out


#: File in an evaluation folder with the table's GT rows (for ``bopsurg compare``).
TABLE_SAMPLES_FILENAME = "bootstrap_table.npz"


def save_table_rows(path: Path, rows: Columns | pd.DataFrame) -> None:
    """Write the table's rows (npz, atomically)."""
    arrays: dict[str, Any] = as_columns(rows)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)


def load_table_rows(path: Path) -> pd.DataFrame:
    """Read rows written by :func:`save_table_rows`.

    Raises:
        InputError: Missing or unreadable file.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            return to_frame({c: z[c] for c in z.files})
    except FileNotFoundError:
        raise InputError(f"{path}: missing (evaluate again with this bopsurg)") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not table samples of bopsurg eval ({exc})") from None


def compare_tables(
    a: Columns | pd.DataFrame,
    b: Columns | pd.DataFrame,
    replicates: int,
    seed: int = 0,
    unit: str = "image",
) -> dict[str, Comparison]:
    """Paired bootstrap comparison of the table's numbers of two evaluations of the same GT.

    Raises:
        BopsurgError: The evaluations are not on the same GT instances.
    """
    cols_a, cols_b = as_columns(a), as_columns(b)
    n_a, n_b = n_rows(cols_a), n_rows(cols_b)
    key = ("scene_id", "im_id", "gt_id")
    if n_a != n_b or not all(np.array_equal(cols_a[k], cols_b[k]) for k in key):
        raise BopsurgError(
            f"the evaluations' tables cover different GT instances ({n_a} vs {n_b}): "
            "compare needs the same dataset split and --min-visib"
        )
    ones = np.ones((1, n_a))
    weights = row_weights(cols_a, replicates, seed, unit)
    return paired_comparisons(
        summary_replicates(cols_a, ones),
        summary_replicates(cols_b, ones),
        summary_replicates(cols_a, weights),
        summary_replicates(cols_b, weights),
    )
