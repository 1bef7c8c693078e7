"""Figures of an evaluation for papers: PNG and PDF through matplotlib (optional extra).

- Fig. 2 of the paper: distributions of the GT camera distance (mm) and visible fraction;
- Fig. 4 of the paper: histograms of RE (deg), TE (mm) and MSSD (mm) over the matched GT
  instances with ``visib_fract ≥ min_visib``, medians drawn;
- recall-vs-threshold curves: fraction of those GT instances whose matched estimate has an
  error below the threshold, per metric (RE, TE, MSSD, MSPD);
- precision-recall curves of the BOP24 6D-detection task, per error type and object, at
  the first, middle and last threshold.

The error histograms, recall curves and precision-recall curves take one evaluation or
several (a mapping name → evaluation, ``bopsurg compare --figures``): several are drawn on
the same axes, one series per evaluation in its own colour, with a legend.

Every function takes plain arrays or the evaluation's outputs and returns the written paths,
so a notebook draws the same figures. matplotlib is imported on use
(``pip install 'bopsurg[figures]'``).
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from bopsurg.atomic import atomic_path
from bopsurg.bop.dataset import BopDataset
from bopsurg.errors import BopsurgError
from bopsurg.evaluation.bootstrap import DetectionSamples
from bopsurg.evaluation.bop24 import DetectionEvaluation, interpolated_ap

if TYPE_CHECKING:
    from bopsurg.viz.evals import EvalFolder

log = logging.getLogger(__name__)

#: Metrics of the error histograms (Fig. 4) and recall curves: errors.csv column, label.
ERROR_LABELS = {"re": "RE [deg]", "te": "TE [mm]", "mssd": "MSSD [mm]", "mspd": "MSPD [px]"}

#: errors.csv of one evaluation, or of several by name (drawn on the same axes).
Errors: TypeAlias = pd.DataFrame | Mapping[str, pd.DataFrame]
#: The BOP24 results of one evaluation, or of several by name.
Detections: TypeAlias = DetectionEvaluation | Mapping[str, DetectionEvaluation | DetectionSamples]


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


def _by_method(errors: Errors) -> dict[str, pd.DataFrame]:
    """One evaluation as ``{"": errors}``; several as given (at least one)."""
    if isinstance(errors, pd.DataFrame):
        return {"": errors}
    if not errors:
        raise BopsurgError("figures: no evaluation to draw")
    return dict(errors)


def _finite(values: pd.Series) -> NDArray[np.float64]:
    v: NDArray[np.float64] = values.to_numpy(np.float64)
    return v[np.isfinite(v)]


def error_histograms(errors: Errors, min_visib: float, stem: Path) -> list[Path]:
    """Fig. 4 written to ``stem.png`` and ``stem.pdf`` (:func:`plot_error_histograms`)."""
    return save_figure(plot_error_histograms(errors, min_visib), stem)


def plot_error_histograms(errors: Errors, min_visib: float) -> Any:
    """Fig. 4: histograms of RE (deg), TE (mm) and MSSD (mm) with their medians (errors.csv
    rows matched to GT instances with ``visib_fract ≥ min_visib``); the figure.

    Several evaluations (a mapping name → errors.csv) share each panel's bins and are drawn
    as outlines, one per evaluation in its colour, with its median as a dashed line of the
    same colour and in the legend ("name, median x").
    """
    plt = _pyplot()
    methods = _by_method(errors)
    single = len(methods) == 1
    fig, axes = plt.subplots(1, 3, figsize=(10, 3) if single else (11, 3.4))
    for ax, col in zip(axes, ("re", "te", "mssd"), strict=True):
        values = {
            name: _finite(matched_errors(e, min_visib)[col]) if col in e else np.zeros(0)
            for name, e in methods.items()
        }
        pooled = np.concatenate(list(values.values()))
        bins = np.histogram_bin_edges(pooled, bins=40) if pooled.size else 40
        for i, (name, v) in enumerate(values.items()):
            med = float(np.median(v)) if v.size else float("nan")
            if single:
                ax.hist(v, bins=bins, color="C0")
                if v.size:
                    ax.axvline(med, color="C3", lw=1.5)
                    ax.text(
                        med, ax.get_ylim()[1] * 0.95, f" median {med:.2f}", color="C3", va="top"
                    )
                continue
            label = f"{name}, median {med:.2f}" if v.size else f"{name}, no values"
            ax.hist(v, bins=bins, histtype="step", lw=1.5, color=f"C{i}", label=label)
            if v.size:
                ax.axvline(med, color=f"C{i}", lw=1.2, ls="--")
        if not single:
            ax.legend(fontsize=7)
        ax.set_xlabel(ERROR_LABELS[col])
    axes[0].set_ylabel(f"GT instances (visib ≥ {min_visib:g})")
    fig.tight_layout()
    return fig


def recall_curves(errors: Errors, n_gt: int, min_visib: float, stem: Path) -> list[Path]:
    """Recall curves written to ``stem.png`` and ``stem.pdf`` (:func:`plot_recall_curves`)."""
    return save_figure(plot_recall_curves(errors, n_gt, min_visib), stem)


def plot_recall_curves(errors: Errors, n_gt: int, min_visib: float) -> Any:
    """Recall (fraction of the ``n_gt`` GT instances with ``visib_fract ≥ min_visib`` whose
    matched estimate's error is below the threshold) against the threshold (RE deg, TE mm,
    MSSD mm, MSPD px), one panel per metric, one curve per evaluation; the figure."""
    plt = _pyplot()
    methods = _by_method(errors)
    rows = {name: matched_errors(e, min_visib) for name, e in methods.items()}
    cols = [c for c in ERROR_LABELS if any(c in r for r in rows.values())]
    fig, axes = plt.subplots(1, len(cols), figsize=(3.2 * len(cols), 3), squeeze=False)
    for ax, col in zip(axes[0], cols, strict=True):
        right = 0.0
        for i, (name, r) in enumerate(rows.items()):
            values = np.sort(_finite(r[col])) if col in r else np.zeros(0)
            recall = np.arange(1, values.size + 1) / max(n_gt, 1)
            ax.step(
                np.r_[0.0, values], np.r_[0.0, recall], where="post", color=f"C{i}",
                label=name or None,
            )  # fmt: skip
            if values.size:
                right = max(right, float(np.percentile(values, 95)) * 1.2)
        ax.set_xlabel(ERROR_LABELS[col] + " threshold")
        ax.set_ylim(0, 1)
        if right > 0:
            ax.set_xlim(0, right)
        if len(rows) > 1:
            ax.legend(fontsize=7, loc="lower right")
    axes[0, 0].set_ylabel("recall")
    fig.tight_layout()
    return fig


@dataclass(frozen=True)
class PrRun:
    """The ranked estimates behind one precision-recall curve.

    Attributes:
        obj_id: The object (None when the samples predate stored object ids: ``obj_index``).
        obj_index: The object's position among the evaluated objects.
        threshold: The correctness threshold θ (the error type's unit: diameter fraction,
            mm, or px).
        tp: (N,) TP flags of the non-ignored estimates in ranking order.
        targets: Number of targets of the object (the recall's denominator).
    """

    obj_id: int | None
    obj_index: int
    threshold: float
    tp: NDArray[np.bool_]
    targets: int

    def curve(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(recall, precision) along the ranking."""
        tp_cum = np.cumsum(self.tp)
        rec = tp_cum / max(self.targets, 1)
        pre = tp_cum / np.arange(1, self.tp.size + 1)
        return rec.astype(np.float64), pre.astype(np.float64)

    def object_name(self) -> str:
        """``obj 3``, or ``obj #1`` (1-based position) when the id is not known."""
        return f"obj {self.obj_id}" if self.obj_id is not None else f"obj #{self.obj_index + 1}"


def _drawn_thresholds(n_th: int) -> list[int]:
    return sorted({0, n_th // 2, n_th - 1})


def pr_runs(det: DetectionEvaluation | DetectionSamples) -> dict[str, list[PrRun]]:
    """Per error type, the ranked runs of each object at the first, middle and last threshold.

    Returns:
        ``{error_type: [PrRun, ...]}`` in object, then threshold order.
    """
    out: dict[str, list[PrRun]] = {}
    if isinstance(det, DetectionEvaluation):
        for name, c in det.curves.items():
            n_th = len(c.thresholds)
            out[name] = [
                PrRun(o, k, c.thresholds[j], c.ranked[k * n_th + j][1], c.targets_count[k])
                for k, o in enumerate(c.obj_ids)
                for j in _drawn_thresholds(n_th)
            ]
        return out
    run = 0
    n_obj = det.targets.shape[1]
    counts = det.targets.sum(axis=0)
    for name, thresholds in det.error_types.items():
        n_th = len(thresholds)
        runs = []
        for k in range(n_obj):
            obj = None if det.obj_ids is None else int(det.obj_ids[k])
            for j in _drawn_thresholds(n_th):
                lo, hi = det.offsets[run + k * n_th + j], det.offsets[run + k * n_th + j + 1]
                runs.append(PrRun(obj, k, thresholds[j], det.est_tp[lo:hi], int(counts[k])))
        out[name] = runs
        run += n_obj * n_th
    return out


def mean_aps(det: DetectionEvaluation | DetectionSamples) -> dict[str, float]:
    """Per error type, the mean over objects (with targets) and thresholds of the AP."""
    if isinstance(det, DetectionEvaluation):
        return {name: c.mean_ap for name, c in det.curves.items()}
    out: dict[str, float] = {}
    counts = det.targets.sum(axis=0)
    run = 0
    for name, thresholds in det.error_types.items():
        per_obj = []
        for k in range(det.targets.shape[1]):
            aps = []
            for _ in thresholds:
                tp = det.est_tp[det.offsets[run] : det.offsets[run + 1]]
                run += 1
                if counts[k] and tp.size:
                    tp_cum = np.cumsum(tp)
                    rec, pre = tp_cum / counts[k], tp_cum / np.arange(1, tp.size + 1)
                    aps.append(interpolated_ap(rec, pre))
                else:
                    aps.append(0.0)
            if counts[k]:
                per_obj.append(float(np.mean(aps)))
        out[name] = float(np.mean(per_obj)) if per_obj else float("nan")
    return out


def detection_pr_curves(det: Detections, stem: Path) -> list[Path]:
    """PR curves written to ``stem.png`` and ``stem.pdf`` (:func:`plot_pr_curves`)."""
    return save_figure(plot_pr_curves(det), stem)


def plot_pr_curves(det: Detections) -> Any:
    """Precision-recall curves of the BOP24 task per error type and object, at the first,
    middle and last correctness threshold (the AP is the area the 101-point rule takes); the
    figure. Several evaluations (name → evaluation or its ``bootstrap_bop24.npz`` samples)
    share each error type's panel: one colour per evaluation, one line style per threshold,
    each one's mAP in the title."""
    plt = _pyplot()
    methods: Mapping[str, DetectionEvaluation | DetectionSamples] = (
        {"": det} if isinstance(det, DetectionEvaluation) else det
    )
    if not methods:
        raise BopsurgError("figures: no evaluation to draw")
    runs = {name: pr_runs(d) for name, d in methods.items()}
    maps = {name: mean_aps(d) for name, d in methods.items()}
    names = list(next(iter(runs.values())))
    single = len(methods) == 1
    styles = ("-", "--", ":")
    fig, axes = plt.subplots(
        1, len(names), figsize=(3.6 * len(names), 3.2 if single else 3.8), squeeze=False
    )
    for ax, name in zip(axes[0], names, strict=True):
        for i, (method, by_type) in enumerate(runs.items()):
            ths = sorted({r.threshold for r in by_type.get(name, [])})
            for r in by_type.get(name, []):
                rec, pre = r.curve()
                label = f"{r.object_name()}, θ={r.threshold:g}"
                if single:
                    ax.plot(rec, pre, label=label)
                else:
                    style = styles[min(ths.index(r.threshold), len(styles) - 1)]
                    ax.plot(rec, pre, color=f"C{i}", ls=style, label=f"{method}: {label}")
        aps = [(m, maps[m].get(name, float("nan"))) for m in runs]
        title = ", ".join(f"{m} {ap:.3f}".strip() for m, ap in aps)
        ax.set_title(f"{name}: mAP {title}", fontsize=10 if single else 8)
        ax.set_xlabel("recall")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.legend(fontsize=6 if single else 5)
    axes[0, 0].set_ylabel("precision")
    fig.tight_layout()
    return fig


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
    from bopsurg.viz.evals import gt_distributions_of

    out = Path(out)
    errors = pd.read_csv(out / "errors.csv")
    summary = json.loads((out / "summary.json").read_text())
    distance, visib = gt_distributions_of(dataset)
    return write_figures(out, errors, summary, distance, visib, det)


def write_comparison_figures(
    folders: Sequence[EvalFolder],
    figures_dir: Path,
    gt: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> list[Path]:
    """The figures of a comparison (``bopsurg compare --figures``) into ``figures_dir``: the
    evaluations overlaid in Fig. 4 (``fig4_error_histograms``), the recall curves
    (``recall_curves``) and, for those evaluated with the bop24 task, the PR curves
    (``bop24_pr_curves``); Fig. 2 (``fig2_gt_distributions``) once, from ``gt`` (GT camera
    distances mm, visible fractions; :func:`bopsurg.viz.evals.comparison_gt`), the test set
    being the same. PNG and PDF each; returns the written files.

    Raises:
        BopsurgError: matplotlib is missing.
    """
    d = Path(figures_dir)
    base = folders[0].summary
    min_visib, n_gt = float(base["min_visib"]), int(base["gt_instances"])
    errors = {f.label: f.errors for f in folders}
    paths: list[Path] = []
    if gt is not None:
        paths += gt_distributions(gt[0], gt[1], d / "fig2_gt_distributions")
    paths += error_histograms(errors, min_visib, d / "fig4_error_histograms")
    paths += recall_curves(errors, n_gt, min_visib, d / "recall_curves")
    dets = {f.label: f.detections for f in folders if f.detections is not None}
    if dets:
        if len(dets) < len(folders):
            log.info("BOP24 PR curves: only %s were evaluated with the bop24 task", ", ".join(dets))
        paths += detection_pr_curves(dets, d / "bop24_pr_curves")
    return paths
