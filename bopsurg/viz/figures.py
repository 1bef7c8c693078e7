"""Figures of an evaluation for papers: PNG and PDF through matplotlib (optional extra).

- Fig. 2 of the paper: distributions of the GT camera distance (mm) and visible fraction;
- Fig. 4 of the paper: histograms of RE (deg), TE (mm) and MSSD (mm) over the matched GT
  instances with ``visib_fract ≥ min_visib``, medians drawn;
- recall-vs-threshold curves: fraction of those GT instances whose matched estimate has an
  error below the threshold, per metric (RE, TE, MSSD, MSPD);
- precision-recall curves of the BOP24 6D-detection task, per error type and object, at
  the first, middle and last threshold.

Every function takes plain arrays or the evaluation's outputs and returns the written paths,
so a notebook draws the same figures. matplotlib is imported on use
(``pip install 'bopsurg[figures]'``).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from bopsurg.atomic import atomic_path
from bopsurg.bop.dataset import BopDataset
from bopsurg.errors import BopsurgError
from bopsurg.evaluation.bop24 import DetectionEvaluation
from bopsurg.evaluation.tables import load_gt_table

#: Metrics of the error histograms (Fig. 4) and recall curves: errors.csv column, label.
ERROR_LABELS = {"re": "RE [deg]", "te": "TE [mm]", "mssd": "MSSD [mm]", "mspd": "MSPD [px]"}


def _pyplot() -> Any:
    try:
        import matplotlib

        if "matplotlib.pyplot" not in sys.modules:  # headless, unless a notebook chose already
            matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise BopsurgError("figures need matplotlib: pip install 'bopsurg[figures]'") from None
    return plt


def save_figure(fig: Any, stem: Path) -> list[Path]:
    """Write ``stem.png`` (150 dpi) and ``stem.pdf`` atomically; close the figure."""
    paths = []
    for fmt in ("png", "pdf"):
        path = stem.with_suffix(f".{fmt}")
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=fmt, dpi=150)
        paths.append(path)
    _pyplot().close(fig)
    return paths


def gt_distributions(distance_mm: ArrayLike, visib_fract: ArrayLike, stem: Path) -> list[Path]:
    """Fig. 2 written to ``stem.png`` and ``stem.pdf`` (:func:`plot_gt_distributions`)."""
    return save_figure(plot_gt_distributions(distance_mm, visib_fract), stem)


def plot_gt_distributions(distance_mm: ArrayLike, visib_fract: ArrayLike) -> Any:
    """Fig. 2: histograms of the GT camera distance (mm) and visible fraction; the figure."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(8, 3))
    axes[0].hist(np.asarray(distance_mm, float), bins=30, color="C0")
    axes[0].set_xlabel("camera distance [mm]")
    axes[0].set_ylabel("GT instances")
    axes[1].hist(np.asarray(visib_fract, float), bins=np.linspace(0, 1, 21), color="C1")
    axes[1].set_xlabel("visible fraction")
    fig.tight_layout()
    return fig


def matched_errors(errors: pd.DataFrame, min_visib: float) -> pd.DataFrame:
    """The rows of errors.csv matched to a GT instance with ``visib_fract ≥ min_visib``."""
    return errors[(errors["gt_id"] >= 0) & (errors["visib_fract"] >= min_visib)]


def error_histograms(errors: pd.DataFrame, min_visib: float, stem: Path) -> list[Path]:
    """Fig. 4 written to ``stem.png`` and ``stem.pdf`` (:func:`plot_error_histograms`)."""
    return save_figure(plot_error_histograms(errors, min_visib), stem)


def plot_error_histograms(errors: pd.DataFrame, min_visib: float) -> Any:
    """Fig. 4: histograms of RE, TE and MSSD with their medians (errors.csv rows matched to
    GT instances with ``visib_fract ≥ min_visib``); the figure."""
    plt = _pyplot()
    rows = matched_errors(errors, min_visib)
    fig, axes = plt.subplots(1, 3, figsize=(10, 3))
    for ax, col in zip(axes, ("re", "te", "mssd"), strict=True):
        values = rows[col].to_numpy(float)
        values = values[np.isfinite(values)]
        ax.hist(values, bins=40, color="C0")
        if values.size:
            med = float(np.median(values))
            ax.axvline(med, color="C3", lw=1.5)
            ax.text(med, ax.get_ylim()[1] * 0.95, f" median {med:.2f}", color="C3", va="top")
        ax.set_xlabel(ERROR_LABELS[col])
    axes[0].set_ylabel(f"GT instances (visib ≥ {min_visib:g})")
    fig.tight_layout()
    return fig


def recall_curves(errors: pd.DataFrame, n_gt: int, min_visib: float, stem: Path) -> list[Path]:
    """Recall (fraction of the ``n_gt`` GT instances with ``visib_fract ≥ min_visib`` whose
    matched estimate's error is below the threshold) against the threshold, per metric."""
    plt = _pyplot()
    rows = matched_errors(errors, min_visib)
    cols = [c for c in ERROR_LABELS if c in rows]
    fig, axes = plt.subplots(1, len(cols), figsize=(3.2 * len(cols), 3), squeeze=False)
    for ax, col in zip(axes[0], cols, strict=True):
        values = np.sort(rows[col].to_numpy(float))
        values = values[np.isfinite(values)]
        recall = np.arange(1, values.size + 1) / max(n_gt, 1)
        ax.step(np.r_[0.0, values], np.r_[0.0, recall], where="post")
        ax.set_xlabel(ERROR_LABELS[col] + " threshold")
        ax.set_ylim(0, 1)
        if values.size:
            ax.set_xlim(0, float(np.percentile(values, 95)) * 1.2 or 1.0)
    axes[0, 0].set_ylabel("recall")
    fig.tight_layout()
    return save_figure(fig, stem)


def detection_pr_curves(det: DetectionEvaluation, stem: Path) -> list[Path]:
    """Precision-recall curves of the BOP24 task per error type and object, at the first,
    middle and last correctness threshold (the AP is the area the 101-point rule takes)."""
    plt = _pyplot()
    curves = det.curves
    fig, axes = plt.subplots(1, len(curves), figsize=(3.6 * len(curves), 3.2), squeeze=False)
    for ax, (name, curve) in zip(axes[0], curves.items(), strict=True):
        n_th = len(curve.thresholds)
        for k, obj_id in enumerate(curve.obj_ids):
            for j in sorted({0, n_th // 2, n_th - 1}):
                _, tp = curve.ranked[k * n_th + j]
                tp_cum = np.cumsum(tp)
                rec = tp_cum / curve.targets_count[k]
                pre = tp_cum / np.arange(1, tp.size + 1)
                ax.plot(rec, pre, label=f"obj {obj_id}, θ={curve.thresholds[j]:g}")
        ax.set_title(f"{name}: mAP {curve.mean_ap:.3f}")
        ax.set_xlabel("recall")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.legend(fontsize=6)
    axes[0, 0].set_ylabel("precision")
    fig.tight_layout()
    return save_figure(fig, stem)


def write_figures(
    out: Path,
    errors: pd.DataFrame,
    summary: Mapping[str, Any],
    gt_distance_mm: Sequence[float] | NDArray[np.float64],
    gt_visib: Sequence[float] | NDArray[np.float64],
    det: DetectionEvaluation | None = None,
) -> list[Path]:
    """Every figure of an evaluation into ``out/figures/``; returns the written files."""
    d = Path(out) / "figures"
    min_visib = float(summary["min_visib"])
    paths = gt_distributions(gt_distance_mm, gt_visib, d / "fig2_gt_distributions")
    paths += error_histograms(errors, min_visib, d / "fig4_error_histograms")
    paths += recall_curves(errors, int(summary["gt_instances"]), min_visib, d / "recall_curves")
    if det is not None:
        paths += detection_pr_curves(det, d / "bop24_pr_curves")
    return paths


def figures_of_evaluation(
    out: Path, dataset: BopDataset, det: DetectionEvaluation | None = None
) -> list[Path]:
    """The figures of an evaluation folder written by ``bopsurg eval`` (its errors.csv and
    summary.json, and the dataset's GT)."""
    out = Path(out)
    errors = pd.read_csv(out / "errors.csv")
    summary = json.loads((out / "summary.json").read_text())
    gt = load_gt_table(dataset, need_gt_info=False)
    distance = np.linalg.norm(gt.t, axis=1)
    visib = gt.visib_fract[np.isfinite(gt.visib_fract)]
    return write_figures(out, errors, summary, distance, visib, det)
