"""Bootstrap 95 % intervals of the paper's table and the absolute-threshold scores.

The same resampling as :mod:`bopsurg.evaluation.bootstrap` (images or scenes drawn with
replacement, one weight per unit and replicate), applied to the GT instances of
:func:`bopsurg.evaluation.summary.paper_summary` (``visib_fract ≥ min_visib``): weighted
means, population standard deviations, medians (the resampled set's middle order
statistics), recalls at absolute thresholds (missed instances fail) and ADD / ADD-S AUC,
all replicates at once. Min and max get no interval (a bootstrap cannot go beyond them).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from bopsurg.evaluation.bootstrap import percentile_interval, resample_weights
from bopsurg.evaluation.summary import ABS_THRESHOLDS, AUC_MAX_FRACTION, AUC_STEPS, TABLE_METRICS

F64 = NDArray[np.float64]


def _units(rows: pd.DataFrame, unit: str) -> NDArray[np.int64]:
    keys = ["scene_id"] if unit == "scene" else ["scene_id", "im_id"]
    return rows.groupby(keys, sort=True).ngroup().to_numpy(np.int64)


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


def summary_intervals(
    gt_rows: pd.DataFrame,
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
    sel = gt_rows[gt_rows["visib_fract"] >= min_visib]
    w = (
        resample_weights(_units(sel, unit), replicates, seed)
        if len(sel)
        else np.zeros((replicates, 0))
    )
    total = w.sum(axis=1)
    out: dict[str, Any] = {"table": {}, "recall": {}}
    with np.errstate(invalid="ignore", divide="ignore"):
        for m in TABLE_METRICS:
            v = sel[m].to_numpy(np.float64)
            ok = np.isfinite(v)
            wv, vv = w[:, ok], v[ok]
            n = wv.sum(axis=1)
            mean = wv @ vv / n
            std = np.sqrt(np.maximum(wv @ (vv * vv) / n - mean * mean, 0.0))
            out["table"][m] = {
                "mean": percentile_interval(mean),
                "std": percentile_interval(std),
                "median": percentile_interval(weighted_median(vv, wv)),
            }
        for col, th, label in ABS_THRESHOLDS:
            hit = sel[col].to_numpy(np.float64) < th  # NaN (missed) is no hit
            out["recall"][label] = percentile_interval(w @ hit / total)
        s = np.arange(1, AUC_STEPS + 1) / AUC_STEPS
        max_th = AUC_MAX_FRACTION * sel["diameter"].to_numpy(np.float64)
        for col in ("add", "adi"):
            if col not in sel:
                continue
            e = sel[col].to_numpy(np.float64)
            ratio = np.where(np.isnan(e), np.inf, e) / max_th
            per_row = (ratio[None, :] < s[:, None]).mean(axis=0)  # each instance's accuracy
            out[f"{col}_auc"] = percentile_interval(w @ per_row / total)
    return out
