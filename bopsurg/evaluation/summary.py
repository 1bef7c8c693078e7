"""The paper's error table and the absolute-threshold scores useful for small instruments.

The paper (Table I) reports, over GT instances with ``visib_fract ≥ 0.3``, the mean, standard
deviation, median, minimum and maximum of RE (deg), TE (mm) and MSSD (mm): the registered
metrics with ``in_table`` (:mod:`bopsurg.metrics.registry`). bopsurg adds the
number of GT instances without any estimate (they cannot enter the statistics, so they are
counted apart), recalls at absolute thresholds (MSSD < 1/2/5 mm, RE < 5/10°) where a missed
instance counts as a failure, and the ADD / ADD-S AUC.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from bopsurg.evaluation.columns import Columns, as_columns, n_rows, take
from bopsurg.metrics.registry import METRICS, table_metrics

if TYPE_CHECKING:
    import pandas as pd

#: Absolute-threshold recalls: (metric, threshold in the metric's unit), reported as
#: ``"{metric}<{threshold}{unit}"``, e.g. ``mssd<1mm``.
ABS_THRESHOLDS: tuple[tuple[str, float], ...] = (
    ("mssd", 1.0),
    ("mssd", 2.0),
    ("mssd", 5.0),
    ("re", 5.0),
    ("re", 10.0),
)

#: ADD(-S) AUC: accuracy integrated over thresholds 0 … AUC_MAX_FRACTION × diameter.
AUC_MAX_FRACTION = 0.1
AUC_STEPS = 100


def recall_label(metric: str, threshold: float) -> str:
    """The key of an absolute-threshold recall, e.g. ``mssd<1mm``."""
    return f"{metric}<{threshold:g}{METRICS[metric].unit}"


def describe(values: np.ndarray) -> dict[str, float]:
    """N, mean, std (population, ddof = 0), median, min and max of finite values."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        nan = float("nan")
        return {"n": 0, "mean": nan, "std": nan, "median": nan, "min": nan, "max": nan}
    return {
        "n": int(v.size),
        "mean": float(v.mean()),
        "std": float(v.std()),
        "median": float(np.median(v)),
        "min": float(v.min()),
        "max": float(v.max()),
    }


def auc(errors: np.ndarray, max_threshold: np.ndarray, steps: int = AUC_STEPS) -> float:
    """Area under the accuracy–threshold curve, normalised to [0, 1].

    Accuracy at threshold ``s × max_threshold`` (s in (0, 1], ``steps`` values) is the
    fraction of instances with ``error < s × max_threshold``; missed instances carry
    ``error = inf``. Thresholds scale per instance (``max_threshold`` = 0.1 × its object's
    diameter), the usual choice for objects of different sizes.
    """
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        return float("nan")
    e = np.where(np.isnan(e), np.inf, e)
    ratio = e / np.asarray(max_threshold, dtype=np.float64)
    s = np.arange(1, steps + 1) / steps
    acc = (ratio[None, :] < s[:, None]).mean(axis=1)
    return float(acc.mean())


def paper_summary(gt_rows: Columns | pd.DataFrame, *, min_visib: float = 0.3) -> dict[str, object]:
    """The paper's table and the extra scores over GT instances with visibility ≥ min_visib.

    Args:
        gt_rows: One row per GT instance with columns ``visib_fract``, ``diameter`` and the
            matched estimate's values of the registered metrics
            (:data:`~bopsurg.metrics.registry.METRICS`; NaN when the instance has no estimate).
        min_visib: Visibility threshold (the paper: 0.3).

    Returns:
        ``{"min_visib", "gt_instances", "with_estimate", "missed", "table": {metric: stats},
        "recall": {label: value}, "{metric}_auc" for each metric with ``auc`` (``add_auc``,
        ``adi_auc``)}``.
    """
    rows = as_columns(gt_rows)
    sel = take(rows, rows["visib_fract"] >= min_visib)
    has_est = ~np.isnan(sel["re"])
    table = {m.name: {"unit": m.unit, **describe(sel[m.name][has_est])} for m in table_metrics()}
    n = n_rows(sel)
    recall: dict[str, float] = {}
    for name, th in ABS_THRESHOLDS:
        v = np.asarray(sel[name], dtype=np.float64)
        recall[recall_label(name, th)] = float(np.count_nonzero(v < th) / n) if n else float("nan")
    max_th = AUC_MAX_FRACTION * np.asarray(sel["diameter"], dtype=np.float64)
    out: dict[str, object] = {
        "min_visib": min_visib,
        "gt_instances": int(n),
        "with_estimate": int(has_est.sum()),
        "missed": int(n - has_est.sum()),
        "table": table,
        "recall": recall,
    }
    for m in METRICS.values():
        if m.auc:
            out[f"{m.name}_auc"] = auc(np.asarray(sel[m.name], dtype=np.float64), max_th)
    return out


def format_table(summary: dict[str, object], scores: dict[str, float] | None = None) -> str:
    """Render the summary (and BOP scores) as the plain-text table printed by ``bopsurg eval``."""
    table = summary["table"]
    assert isinstance(table, dict)
    lines = [
        f"GT instances with visib_fract >= {summary['min_visib']}: {summary['gt_instances']} "
        f"({summary['with_estimate']} with an estimate, {summary['missed']} missed)",
        "",
        f"{'':<12}{'N':>7}{'mean':>10}{'std':>10}{'median':>10}{'min':>10}{'max':>10}",
    ]
    for metric, stats in table.items():
        name = METRICS[metric].heading()
        lines.append(
            f"{name:<12}{stats['n']:>7d}{stats['mean']:>10.2f}{stats['std']:>10.2f}"
            f"{stats['median']:>10.2f}{stats['min']:>10.2f}{stats['max']:>10.2f}"
        )
    recall = summary["recall"]
    assert isinstance(recall, dict)
    lines += ["", "Recall: " + ", ".join(f"{k} {v:.3f}" for k, v in recall.items())]
    aucs = [f"{m.label} {summary[m.name + '_auc']:.3f}" for m in METRICS.values() if m.auc]
    lines.append(f"AUC (0-{AUC_MAX_FRACTION:g} x diameter): " + ", ".join(aucs))
    splits = summary.get("splits")
    if isinstance(splits, dict) and splits:
        # one median column per table metric, at least 9 wide and 2 more than its title
        cols = [(m.name, f"{m.label} med", max(9, len(m.label) + 6)) for m in table_metrics()]
        head = "".join(f"{title:>{w}}" for _, title, w in cols)
        lines += ["", f"{'split':<28}{'N':>6}{head}"]
        for split, groups in splits.items():
            for label, st in groups.items():
                if st["n"] == 0:
                    continue
                cells = "".join(f"{st[name + '_median']:>{w}.2f}" for name, _, w in cols)
                lines.append(f"{split + ': ' + label:<28}{st['n']:>6d}{cells}")
    if scores:
        lines += ["", "BOP19 (reference toolkit semantics):"]
        for key, value in scores.items():
            if key.startswith("bop19_"):
                lines.append(f"  {key:<34}{value:.4f}")
    return "\n".join(lines)
