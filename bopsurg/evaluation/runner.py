"""``bopsurg eval``: from a BOP dataset and a results CSV to errors, the paper's table and AR.

Two matchings are made, each for its purpose:

1. **Per-instance errors** (``errors.csv``, the paper's table): within each image and object,
   estimates in decreasing score order take the not-yet-matched GT instance with the smallest
   MSSD, with no threshold, over all GT instances (whatever their visibility). Each estimate
   gets at most one GT and each GT at most one estimate; estimates left over are written with
   ``gt_id = -1`` and empty errors; GT instances left over are "missed". The table then
   describes the GT instances with ``visib_fract ≥ --min-visib``.
2. **BOP19 scores** (``scores.json``): exactly the reference toolkit's rule
   (:mod:`bopsurg.evaluation.bop19`).

Errors in ``errors.csv`` are the plain metric values (no +inf shortcut); the reference's
shortcut only enters the BOP scores, where it decides nothing that the threshold would not.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.atomic import write_text
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import PoseEstimates, average_time_per_image
from bopsurg.bop.targets import Target
from bopsurg.errors import BopsurgError
from bopsurg.evaluation import bop19
from bopsurg.evaluation.ambiguity import AMBIGUITY_COLUMNS, ambiguity_splits, instance_ambiguity
from bopsurg.evaluation.bop19_pairs import KeptPairs, kept_pairs_of_targets
from bopsurg.evaluation.columns import (
    Columns,
    FrameField,
    concat,
    csv_text,
    group_labels,
    pick,
    take,
)
from bopsurg.evaluation.matching import greedy_match
from bopsurg.evaluation.pair_errors import ModelCache, candidate_pair_indices, pair_errors
from bopsurg.evaluation.summary import paper_summary
from bopsurg.evaluation.tables import GtTable, load_gt_table, rank_in_groups
from bopsurg.evaluation.vsd_pairs import PendingVsd, StartedVsd, VsdInputs, start_vsd
from bopsurg.metrics.registry import METRICS
from bopsurg.plugins import DepthRenderer, load_plugin

if TYPE_CHECKING:  # only a type here: the default (local) run loads no multiprocessing
    from bopsurg.executors import Executor

log = logging.getLogger(__name__)

I64 = NDArray[np.int64]

#: The leading columns of errors.csv: the estimate and the GT instance it was matched to.
ID_COLUMNS = ("scene_id", "im_id", "obj_id", "gt_id", "score", "visib_fract")


def error_columns() -> tuple[str, ...]:
    """Columns of errors.csv, in order: ids, every registered metric
    (:data:`bopsurg.metrics.registry.METRICS`), the GT instance's ambiguity."""
    return (*ID_COLUMNS, *METRICS, *AMBIGUITY_COLUMNS)


@dataclass
class Evaluation:
    """Everything ``bopsurg eval`` computes.

    Attributes:
        errors: errors.csv rows (one per estimate; ``gt_id = -1`` when unmatched).
        gt_rows: One row per GT instance of the split with its matched estimate's errors.
        summary: The paper's table and extra scores
            (:func:`~bopsurg.evaluation.summary.paper_summary`).
        scores: BOP19 scores under the reference toolkit's key names.
        curves: Recall curves per BOP error type.

    ``errors`` and ``gt_rows`` are kept as numpy columns (:attr:`error_columns`,
    :attr:`gt_columns`); reading them as DataFrames imports pandas (given either).
    """

    summary: dict[str, object]
    scores: dict[str, float]
    curves: dict[str, bop19.RecallCurve]
    # descriptors, not shared defaults: each instance keeps its own columns (required fields)
    errors: FrameField = FrameField()  # noqa: RUF009
    gt_rows: FrameField = FrameField()  # noqa: RUF009

    @property
    def error_columns(self) -> Columns:
        """errors.csv rows as numpy columns."""
        return FrameField.columns(self, "errors")

    @property
    def gt_columns(self) -> Columns:
        """The per-GT rows as numpy columns."""
        return FrameField.columns(self, "gt_rows")


def _instance_matching(
    est: PoseEstimates, gt: GtTable, models: ModelCache, which: Sequence[str]
) -> tuple[Columns, Columns, Columns, I64]:
    """Matching 1 (see the module docstring): errors.csv rows, per-GT rows, the MSSD of
    every candidate pair (columns e, g, mssd) for the BOP scores to reuse, and the GT row
    of each errors.csv row (-1: none)."""
    rank, _ = rank_in_groups(group_labels(est.scene_id, est.im_id, est.obj_id), est.score)
    e_idx, g_idx = candidate_pair_indices(est, gt)
    mssd_all = pair_errors(est, gt, e_idx, g_idx, models, ("mssd",))["mssd"]
    matched_by = greedy_match(
        rank[e_idx], e_idx, g_idx, mssd_all, np.inf, np.ones(len(gt), dtype=bool)
    )
    gt_ok = np.flatnonzero(matched_by >= 0)
    p = matched_by[gt_ok]
    m_e, m_g = e_idx[p], g_idx[p]
    rest = [m for m in which if m != "mssd"]
    errs = pair_errors(est, gt, m_e, m_g, models, rest)
    errs["mssd"] = mssd_all[p]  # always computed: it decides the matching

    n_est = len(est)
    gt_of_est = np.full(n_est, -1, dtype=np.int64)
    gt_of_est[m_e] = m_g
    matched = gt_of_est >= 0
    rows: Columns = {
        "scene_id": est.scene_id,
        "im_id": est.im_id,
        "obj_id": est.obj_id,
        "gt_id": np.where(matched, gt.gt_id[np.maximum(gt_of_est, 0)], -1),
        "score": est.score,
        "visib_fract": np.where(matched, gt.visib_fract[np.maximum(gt_of_est, 0)], np.nan),
    }
    for name in METRICS:
        col = np.full(n_est, np.nan)
        if name in errs:
            col[m_e] = errs[name]
        rows[name] = col
    order = np.lexsort((rows["gt_id"], est.obj_id, est.im_id, est.scene_id))  # stable

    est_row = np.full(len(gt), -1, dtype=np.int64)
    est_row[m_g] = m_e
    gt_rows: Columns = {
        "scene_id": gt.scene_id,
        "im_id": gt.im_id,
        "gt_id": gt.gt_id,
        "obj_id": gt.obj_id,
        "visib_fract": gt.visib_fract,
        "diameter": models.diameters(gt.obj_id),
        "est_row": est_row,
    }
    for name in METRICS:
        col = np.full(len(gt), np.nan)
        if name in errs:
            col[m_g] = errs[name]
        gt_rows[name] = col
    pair_mssd: Columns = {"e": e_idx, "g": g_idx, "mssd": mssd_all}
    return take(rows, order), gt_rows, pair_mssd, gt_of_est[order]


def begin_evaluation(
    dataset: BopDataset,
    estimates: PoseEstimates,
    *,
    targets: Sequence[Target] | None = None,
    min_visib: float = 0.3,
    renderer: DepthRenderer | None = None,
    vsd_delta: float = bop19.VSD_DELTA_MM,
    max_sym_disc_step: float = 0.01,
    instance_metrics: Sequence[str] | None = None,
    scene_ids: Sequence[int] | None = None,
    progress: bool = False,
    started: StartedVsd | None = None,
) -> EvaluationInProgress:
    """:func:`evaluate` up to VSD's errors: the rest needs them
    (:meth:`EvaluationInProgress.finish`), so that a caller can work while VSD renders on a
    worker process. Arguments as for :func:`evaluate`.
    """
    if instance_metrics is None:
        instance_metrics = tuple(METRICS)
    unknown = set(instance_metrics) - set(METRICS)
    if unknown:
        raise BopsurgError(f"unknown metric(s) {sorted(unknown)}; choose from {', '.join(METRICS)}")
    models = ModelCache(dataset, max_sym_disc_step)
    if targets is None:
        targets = dataset.targets()
    vsd_inputs = None if renderer is None else VsdInputs(dataset, renderer, vsd_delta, progress)
    if started is not None:  # VSD already under way: its GT table and pairs are ours
        if scene_ids is not None:
            raise BopsurgError("VSD started early evaluates the whole split, not scene_ids")
        gt, kept, vsd_inputs = started.gt, started.kept, started.inputs
        pending: PendingVsd | None = started.errors
    else:
        gt = load_gt_table(dataset, scene_ids)
        if scene_ids is not None:
            keep = set(scene_ids)
            targets = [t for t in targets if t.scene_id in keep]
            estimates = estimates.subset(np.isin(estimates.scene_id, sorted(keep)))
        kept = kept_pairs_of_targets(estimates, gt, targets, models.diameters)
        pending = None if vsd_inputs is None else start_vsd(estimates, gt, kept, vsd_inputs)
    errors, gt_rows, pair_mssd, gt_of_row = _instance_matching(
        estimates, gt, models, instance_metrics
    )
    amb = instance_ambiguity(dataset, gt_rows, gt.R, gt.t, gt.K)
    gt_rows.update(amb)
    # errors.csv rows carry the ambiguity of the GT they were matched to
    for name, col in amb.items():
        errors[name] = pick(col, gt_of_row)
    return EvaluationInProgress(
        estimates, gt, targets, models, kept, vsd_inputs, pending, errors, gt_rows, pair_mssd,
        min_visib,
    )  # fmt: skip


@dataclass
class EvaluationInProgress:
    """An evaluation with everything but what needs VSD's errors (:func:`begin_evaluation`);
    :meth:`finish` waits for VSD and completes it. The per-GT rows are final already."""

    estimates: PoseEstimates
    gt: GtTable
    targets: Sequence[Target]
    models: ModelCache
    kept: KeptPairs
    vsd_inputs: VsdInputs | None
    vsd: PendingVsd | None
    errors: Columns
    gt_rows: Columns
    pair_mssd: Columns
    min_visib: float

    def finish(self) -> Evaluation:
        """The BOP19 recall curves (waiting for VSD's errors), scores and summary."""
        curves = bop19.recall_curves(
            self.estimates,
            self.gt,
            self.targets,
            self.models,
            pair_mssd=self.pair_mssd,
            vsd_inputs=self.vsd_inputs,
            kept=self.kept,
            vsd=self.vsd,
        )
        return _assemble(self.errors, self.gt_rows, curves, self.estimates, self.min_visib)


def evaluate(
    dataset: BopDataset,
    estimates: PoseEstimates,
    *,
    targets: Sequence[Target] | None = None,
    min_visib: float = 0.3,
    renderer: DepthRenderer | None = None,
    vsd_delta: float = bop19.VSD_DELTA_MM,
    max_sym_disc_step: float = 0.01,
    instance_metrics: Sequence[str] | None = None,
    scene_ids: Sequence[int] | None = None,
    progress: bool = False,
    started: StartedVsd | None = None,
) -> Evaluation:
    """Evaluate pose estimates on a BOP dataset split.

    Args:
        dataset: The dataset (its split holds the GT).
        estimates: Results, e.g. from :func:`bopsurg.bop.load_results`. They must already be
            checked against the dataset (:func:`bopsurg.bop.check_results_against_dataset`).
        targets: BOP19 targets; default: the dataset's ``test_targets_bop19.json``.
        min_visib: Visibility threshold of the paper's table.
        renderer: A depth renderer for VSD; without one AR_VSD and the overall AR are absent.
        vsd_delta: VSD visibility tolerance δ, mm.
        max_sym_disc_step: Discretisation of continuous symmetries (BOP: 0.01).
        instance_metrics: Metrics of errors.csv (names of registered metrics, None = all;
            MSSD is always computed since it decides the matching; left-out columns stay
            empty).
        scene_ids: Evaluate only these scenes (their GT, estimates and targets).
        progress: Show progress bars.
        started: VSD already started on these estimates and targets with ``renderer``
            (:func:`~bopsurg.evaluation.vsd_pairs.start_vsd_early`, maybe on a worker
            process); its GT table and pairs are used.

    Returns:
        The :class:`Evaluation`.
    """
    return begin_evaluation(
        dataset,
        estimates,
        targets=targets,
        min_visib=min_visib,
        renderer=renderer,
        vsd_delta=vsd_delta,
        max_sym_disc_step=max_sym_disc_step,
        instance_metrics=instance_metrics,
        scene_ids=scene_ids,
        progress=progress,
        started=started,
    ).finish()


def _assemble(
    errors: Columns,
    gt_rows: Columns,
    curves: dict[str, bop19.RecallCurve],
    estimates: PoseEstimates,
    min_visib: float,
) -> Evaluation:
    """Scores and summary from the per-instance rows and the recall curves."""
    scores: dict[str, float] = {}
    for name in ("vsd", "mssd", "mspd"):
        if name in curves:
            scores[f"bop19_average_recall_{name}"] = curves[name].average_recall
    if "vsd" in curves:
        scores["bop19_average_recall"] = float(
            np.mean([scores[f"bop19_average_recall_{n}"] for n in ("vsd", "mssd", "mspd")])
        )
    scores["bop19_average_time_per_image"] = average_time_per_image(estimates)
    summary = paper_summary(gt_rows, min_visib=min_visib)
    summary["splits"] = ambiguity_splits(take(gt_rows, gt_rows["visib_fract"] >= min_visib))
    summary["estimates"] = len(estimates)
    summary["unmatched_estimates"] = int((errors["gt_id"] < 0).sum())
    return Evaluation(summary, scores, curves, errors=errors, gt_rows=gt_rows)


@dataclass(frozen=True)
class EvalUnit:
    """A group of scenes evaluated on its own (a unit for :mod:`bopsurg.executors`)."""

    root: str
    split: str
    split_type: str | None
    scene_ids: tuple[int, ...]
    estimates: PoseEstimates
    targets: tuple[Target, ...] | None
    options: dict[str, Any]
    #: The registered dataset the worker applies (``"none"``: none), as the caller's.
    dataset_name: str = "none"


def _eval_unit(unit: EvalUnit, report: Callable[[int], None]) -> Evaluation:
    dataset = BopDataset(unit.root, unit.split, split_type=unit.split_type, name=unit.dataset_name)
    opts = dict(unit.options)
    renderer_name = opts.pop("renderer_name", None)
    renderer = load_plugin("renderer", renderer_name)() if renderer_name else None
    result = evaluate(
        dataset,
        unit.estimates,
        targets=unit.targets,
        scene_ids=unit.scene_ids,
        renderer=renderer,
        **opts,
    )
    report(len(unit.scene_ids))
    return result


def evaluate_distributed(
    dataset: BopDataset,
    estimates: PoseEstimates,
    *,
    executor: Executor,
    targets: Sequence[Target] | None = None,
    renderer_name: str | None = None,
    scenes_per_unit: int = 1,
    progress: bool = False,
    **options: object,
) -> Evaluation:
    """:func:`evaluate`, split into groups of scenes run by ``executor``, then merged.

    Matching is per image and recall is micro-averaged (Σ TP / Σ targets), so the merged
    result equals :func:`evaluate`'s, number for number. Renderers do not travel between
    processes: VSD workers load the renderer plugin ``renderer_name`` themselves.
    """
    if scenes_per_unit < 1:
        raise BopsurgError("scenes_per_unit must be >= 1")
    all_targets = list(targets) if targets is not None else dataset.targets()
    ids = dataset.scene_ids
    groups = [tuple(ids[i : i + scenes_per_unit]) for i in range(0, len(ids), scenes_per_unit)]
    units = []
    for g in groups:
        keep = np.isin(estimates.scene_id, g)
        units.append(
            EvalUnit(
                root=str(dataset.root),
                split=dataset.split,
                split_type=dataset.split_type,
                scene_ids=g,
                estimates=estimates.subset(keep),
                targets=tuple(t for t in all_targets if t.scene_id in set(g)),
                options={**options, "renderer_name": renderer_name},
                dataset_name="none" if dataset.spec is None else dataset.spec.name,
            )
        )
    from tqdm import tqdm

    with tqdm(total=len(ids), unit="scene", desc="eval", disable=not progress) as bar:
        parts: list[Evaluation] = executor.map(_eval_unit, units, on_progress=bar.update)
    curves: dict[str, bop19.RecallCurve] = {}
    for name in parts[0].curves if parts else ():
        first = parts[0].curves[name]
        tps = np.sum([p.curves[name].tp_counts for p in parts], axis=0).tolist()
        targets_count = int(sum(p.curves[name].targets_count for p in parts))
        recalls = [tp / float(targets_count) if targets_count > 0 else 0.0 for tp in tps]
        curves[name] = bop19.RecallCurve(
            name,
            first.thresholds,
            recalls,
            [int(t) for t in tps],
            targets_count,
            first.taus,
            first.extra,
        )
        bop19.merge_image_counts(curves[name], [p.curves[name] for p in parts])
    errors = concat([p.error_columns for p in parts])
    gt_rows = concat([p.gt_columns for p in parts])
    min_visib = float(options.get("min_visib", 0.3))  # type: ignore[arg-type]
    return _assemble(errors, gt_rows, curves, estimates, min_visib)


def _json_safe(value: object) -> object:
    """NaN/inf become null, so the files are standard JSON that every parser reads."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def write_evaluation(
    result: Evaluation, out_dir: str | Path, *, meta: dict[str, object] | None = None
) -> None:
    """Write ``errors.csv``, ``summary.json`` and ``scores.json`` into ``out_dir`` atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    columns = {name: result.error_columns[name] for name in error_columns()}
    write_text(out / "errors.csv", csv_text(columns, float_format="%.9g"))
    summary = {**(meta or {}), **result.summary}
    text = json.dumps(_json_safe(summary), indent=2, allow_nan=False)
    write_text(out / "summary.json", text + "\n")
    details = {
        name: {
            "thresholds": c.thresholds,
            "taus": c.taus,
            "recalls": c.recalls,
            "tp_counts": c.tp_counts,
            "targets_count": c.targets_count,
            **c.extra,
        }
        for name, c in result.curves.items()
    }
    scores = {**result.scores, "details": details}
    write_text(
        out / "scores.json", json.dumps(_json_safe(scores), indent=2, allow_nan=False) + "\n"
    )
