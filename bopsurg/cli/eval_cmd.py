"""``bopsurg eval``: errors, the paper's table and BOP19 scores for a results CSV."""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of
from bopsurg.cli.inputs import (
    add_bootstrap_args,
    add_dataset_and_results,
    add_detections_arg,
    add_executor_args,
    load_dataset_and_results,
    load_detections_arg,
)
from bopsurg.cli.progress import add_progress_arg
from bopsurg.errors import BopsurgError
from bopsurg.evaluation.options import TASK_CHOICES
from bopsurg.metrics.registry import METRICS, help_lines
from bopsurg.plugins import DepthRenderer, available_plugins, load_plugin

if TYPE_CHECKING:
    from importlib.metadata import EntryPoint

    from bopsurg.bop.dataset import BopDataset
    from bopsurg.bop.results import PoseEstimates
    from bopsurg.bop.targets import ImageTarget, Target
    from bopsurg.cli.commands import Subparsers
    from bopsurg.estimation import Detections
    from bopsurg.evaluation.vsd_pairs import StartedVsd
    from bopsurg.evaluation.vsd_worker import VsdWorker
    from bopsurg.executors import Executor

log = logging.getLogger(__name__)

HELP = help_of("eval")

DESCRIPTION = """\
Evaluate 6D pose estimates (a BOP19 results CSV) on a BOP dataset split, or 2D detections
(a BOP COCO results JSON, as 'bopsurg predict --detections-out' writes) with pycocotools:
the results file is recognised by its content.

Writes into --out:
  errors.csv    one row per estimate: scene_id, im_id, obj_id, gt_id (-1 = no GT left for
                it), score, visib_fract, one column per metric (below), tip_visible,
                tail_visible, view_angle_deg
  summary.json  the paper's table (N, mean, std, median, min, max of RE, TE, MSSD over GT
                instances with visib_fract >= --min-visib), missed instances, recall at
                MSSD < 1/2/5 mm and RE < 5/10 deg, ADD and ADD-S AUC (0-0.1 x diameter);
                ci95: 95 % bootstrap intervals of the means, stds, medians, recalls, AUCs
  scores.json   BOP19 scores with the reference toolkit's keys and rules:
                bop19_average_recall_mssd, _mspd, and with a depth renderer _vsd and
                bop19_average_recall; bop19_average_time_per_image; per-threshold details;
                BOP24/25 6D-detection AP (--task bop24): bop24_mAP_mssd, bop24_mAP_mssd_mm
                (MSSD 2-20 mm), bop24_mAP_mspd, bop24_mAP, bop25_mAP, bop25_mAP_mm;
                ci95: 95 % bootstrap intervals of the BOP19 ARs and BOP24/25 keys
                (--bootstrap N, --ci-unit image|scene)
  bootstrap_table.npz, bootstrap_bop19.npz, bootstrap_bop24.npz  what the intervals are
                computed from (the table's GT instances, BOP19 hits per image, the BOP24
                rankings), for 'bopsurg compare'
For a COCO results JSON instead: scores.json with bop22_coco_{{bbox,bbox_modal,segm}}_{{AP,
AP50, AP75, AP_small, _medium, _large, AR1, AR10, AR100, AR_small, _medium, _large}}
(pycocotools' numbers) and their ci95, and bootstrap_coco.npz (per-image matches).

Matching for errors.csv and the table: in each image, estimates in decreasing score order
take the not-yet-matched GT instance of their object with the smallest MSSD (no threshold).
The BOP scores use the reference's own rules (targets, valid GTs, strict thresholds).

Metrics (--metrics; bopsurg.metrics.registry):
{metrics}
"""


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "eval",
        help=HELP,
        description=DESCRIPTION.format(metrics="\n".join(help_lines("  "))),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_dataset_and_results(p)
    p.add_argument("--out", required=True, help="output folder (created)")
    p.add_argument(
        "--targets",
        default=None,
        help="targets JSON (default: DATASET/test_targets_bop19.json, else enumerated from GT)",
    )
    p.add_argument(
        "--task",
        type=_task_list,
        default="all",
        metavar="{" + ",".join(TASK_CHOICES) + "}",
        help="bop19 (6D localization AR), bop24 (6D detection AP, BOP 2023-2025) for a pose "
        "CSV; coco-bbox, coco-segm (COCO AP via pycocotools) for a BOP COCO results JSON "
        "(.json or .json.gz); several joined by commas (bop19,bop24); all (default: every "
        "task the results allow)",
    )
    p.add_argument(
        "--targets-bop24",
        default=None,
        help="BOP24 targets JSON (default: DATASET/test_targets_bop24.json, else every image "
        "with GT)",
    )
    p.add_argument(
        "--min-visib",
        type=float,
        default=0.3,
        help="visibility threshold of the paper's table (default: 0.3, as in the paper)",
    )
    p.add_argument(
        "--renderer",
        default="auto",
        help="depth renderer plugin for VSD: a name, 'auto' (first installed, if the dataset "
        "has depth images) or 'none' (default: auto)",
    )
    p.add_argument(
        "--metrics",
        default=",".join(METRICS),
        help="comma-separated metrics of errors.csv, listed above (default: all; mssd is "
        "always computed: it decides the matching)",
    )
    p.add_argument(
        "--vsd-delta",
        type=float,
        default=None,
        help="VSD tolerance delta, mm (default: the dataset's, 5 for itodd, else 15)",
    )
    p.add_argument(
        "--rerun",
        metavar="FILE.rrd",
        default=None,
        help="also write a rerun recording for visual error analysis (needs bopsurg[rerun])",
    )
    add_detections_arg(p)
    add_bootstrap_args(p)
    p.add_argument(
        "--figures",
        action="store_true",
        help="also write OUT/figures/: GT distributions (Fig. 2), error histograms (Fig. 4), "
        "recall-vs-threshold and BOP24 precision-recall curves, PNG + PDF (needs matplotlib)",
    )
    add_executor_args(p, unit="scene")
    p.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="where MSSD, MSPD and ADD are computed: cpu (numpy), cuda (torch; same values to "
        "1e-9), auto (cuda for large batches when torch sees a GPU, else cpu; default)",
    )
    add_progress_arg(p)
    p.set_defaults(func=run)


def _task_list(text: str) -> str:
    """``--task`` value: task names joined by commas, each one of ``TASK_CHOICES``."""
    names = [t.strip() for t in text.split(",")]
    unknown = [t for t in names if t not in TASK_CHOICES]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown task(s) {', '.join(map(repr, unknown))}; choose from "
            f"{', '.join(TASK_CHOICES)}, several joined by commas"
        )
    return ",".join(names)


def _renderer(
    choice: str, dataset: BopDataset, installed: dict[str, EntryPoint] | None = None
) -> DepthRenderer | None:
    """The renderer ``--renderer`` names (``installed``: the renderer plugins, if known)."""
    if choice == "none":
        return None
    if installed is None:
        installed = available_plugins("renderer")
    has_depth = any((dataset.split_dir / f"{s:06d}" / "depth").is_dir() for s in dataset.scene_ids)
    if choice == "auto":
        if not dataset.evaluates_vsd:  # the reference has no VSD for HOT3D, IPD, XYZ-IBD ...
            log.info("AR_VSD skipped: not evaluated on %s", dataset.spec and dataset.spec.name)
            return None
        if not installed:
            log.info("AR_VSD skipped: no depth renderer plugin installed (bopsurg[vsd] has one)")
            return None
        if not has_depth:
            log.info("AR_VSD skipped: the dataset has no depth images")
            return None
        try:
            renderer: DepthRenderer = load_plugin("renderer", installed=installed)()
            return renderer
        except BopsurgError as err:
            log.warning("AR_VSD skipped: %s", err)
            return None
    if not has_depth:
        raise BopsurgError(f"VSD needs depth images; {dataset.split_dir} has no depth/ folders")
    chosen: DepthRenderer = load_plugin("renderer", choice, installed=installed)()
    return chosen


def _renderer_name(renderer: DepthRenderer | None, installed: dict[str, EntryPoint]) -> str | None:
    if renderer is None:
        return None
    for name, ep in installed.items():
        if ep.value.split(":")[-1] == type(renderer).__name__:
            return name
    raise BopsurgError(f"renderer {type(renderer).__name__} is not an installed plugin")


@dataclass(frozen=True)
class _Inputs:
    """What ``eval`` loads before it evaluates (bad files fail before any work)."""

    tasks: tuple[str, ...]
    dataset: BopDataset
    est: PoseEstimates
    image_targets: list[ImageTarget] | None
    boxes: dict[tuple[int, int], Detections] | None
    targets: list[Target] | None


def run(args: argparse.Namespace) -> int:
    """Run the evaluation and print the table."""
    t0 = time.perf_counter()
    executor = None
    if args.executor != "local" or args.workers != 1:  # fail before any work if unavailable
        from bopsurg.executors import make_executor

        executor = make_executor(args.executor, workers=args.workers, ray_address=args.ray_address)
    if executor is None and "numpy" not in sys.modules:
        # One BLAS thread (read when numpy is imported): the VSD worker takes the other core,
        # and the evaluation's small matrix products cost several times more CPU split over
        # threads that wait for each other.
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    # The VSD worker starts first, before this process imports numpy, and is closed below if
    # VSD does not run after all (a COCO file, no depth images ...).
    installed = {} if args.renderer == "none" else available_plugins("renderer")
    worker = _early_worker(args.renderer, installed) if executor is None else None
    try:
        return _run(args, executor, worker, installed, t0)
    finally:
        if worker is not None:
            worker.close()


def _early_worker(choice: str, installed: dict[str, EntryPoint]) -> VsdWorker | None:
    """A VSD worker for the renderer that ``--renderer`` would load, if one is installed."""
    if choice == "none":
        return None
    from bopsurg.evaluation.vsd_worker import VsdWorker

    name = choice
    if choice == "auto":  # the plugin load_plugin("renderer") loads
        if not installed:
            return None
        name = sorted(installed)[0]
    ep = installed.get(name)
    return VsdWorker.start(name, "" if ep is None else f"{ep.module}:{ep.attr}")


def _run(
    args: argparse.Namespace,
    executor: Executor | None,
    worker: VsdWorker | None,
    installed: dict[str, EntryPoint],
    t0: float,
) -> int:
    """:func:`run` once the executor and the VSD worker are started."""
    from bopsurg.bop.targets import load_image_targets, load_targets
    from bopsurg.evaluation.coco_eval import is_coco_results
    from bopsurg.evaluation.tasks import resolve_tasks

    if is_coco_results(args.results):  # 2D tasks: a COCO JSON, recognised by its content
        from bopsurg.cli.eval_coco import run_coco

        return run_coco(args)
    tasks = resolve_tasks(args.task)
    dataset, est = load_dataset_and_results(args)
    inputs = _Inputs(
        tasks,
        dataset,
        est,
        load_image_targets(args.targets_bop24) if args.targets_bop24 else None,
        load_detections_arg(args),  # early: a bad file fails before the evaluation
        load_targets(args.targets) if args.targets else None,
    )
    renderer = _renderer(args.renderer, dataset, installed)
    # VSD's pairs go to the worker before this process imports the evaluation (pandas,
    # scipy) and runs the rest of it.
    name = _renderer_name(renderer, installed)
    started = None
    if renderer is not None and executor is None:
        same = worker is not None and worker.renderer_name == name
        started = _start_vsd(args, inputs, renderer, worker if same else None)
    if worker is not None and (started is None or started.inputs.worker is not worker):
        worker.close()  # not needed: its imports stop taking a core from this process
    return _evaluate_and_write(args, inputs, (renderer, name), executor, started, t0)


def _start_vsd(
    args: argparse.Namespace,
    inputs: _Inputs,
    renderer: DepthRenderer,
    worker: VsdWorker | None,
) -> StartedVsd:
    """VSD of the BOP19 pairs, sent to ``worker`` when it renders with ``renderer``'s plugin
    (else pending in this process)."""
    from bopsurg.evaluation.pair_errors import ModelCache
    from bopsurg.evaluation.vsd_pairs import VsdInputs, start_vsd_early

    dataset = inputs.dataset
    vsd = VsdInputs(dataset, renderer, _vsd_delta(args, dataset), not args.no_progress, worker)
    return start_vsd_early(
        inputs.est,
        dataset.targets() if inputs.targets is None else inputs.targets,
        ModelCache(dataset, max_sym_disc_step=0.01),
        vsd,
    )


def _vsd_delta(args: argparse.Namespace, dataset: BopDataset) -> float:
    """VSD's δ, mm: ``--vsd-delta``, else the dataset's."""
    delta: float = dataset.vsd_delta_mm if args.vsd_delta is None else args.vsd_delta
    return delta


def _evaluate_and_write(
    args: argparse.Namespace,
    inputs: _Inputs,
    renderer_and_name: tuple[DepthRenderer | None, str | None],
    executor: Executor | None,
    started: StartedVsd | None,
    t0: float,
) -> int:
    """The evaluation, its outputs and what it prints, once the inputs are loaded (with the
    renderer and its plugin's name, if any)."""
    from bopsurg._version import __version__
    from bopsurg.cli.eval_stats import early_intervals, write_intervals
    from bopsurg.evaluation.device import metric_device
    from bopsurg.evaluation.runner import begin_evaluation, evaluate_distributed, write_evaluation
    from bopsurg.evaluation.summary import format_table
    from bopsurg.evaluation.tasks import detection_evaluation, merge_task_scores

    tasks, dataset, est, targets = inputs.tasks, inputs.dataset, inputs.est, inputs.targets
    renderer, renderer_name = renderer_and_name
    options = {
        "min_visib": args.min_visib,
        "vsd_delta": _vsd_delta(args, dataset),
        "instance_metrics": [m.strip() for m in args.metrics.split(",") if m.strip()],
    }
    early = None
    with metric_device(args.device):  # MSSD, MSPD, ADD on the CPU or a GPU
        if executor is None:
            in_progress = begin_evaluation(
                dataset,
                est,
                targets=targets,
                renderer=renderer,
                progress=not args.no_progress,
                started=started,
                **options,
            )
            # while VSD renders on its worker: BOP24 and the intervals that need no VSD
            det = detection_evaluation(tasks, dataset, est, inputs.image_targets)
            early = early_intervals(in_progress.gt_rows, det, args, in_progress.min_visib)
            result = in_progress.finish()
        else:  # scenes in parallel: each worker loads the renderer plugin itself
            result = evaluate_distributed(
                dataset,
                est,
                executor=executor,
                targets=targets,
                renderer_name=renderer_name,
                progress=not args.no_progress,
                **options,
            )
            det = detection_evaluation(tasks, dataset, est, inputs.image_targets)
        merge_task_scores(result.scores, tasks, det)
    meta: dict[str, object] = {
        "bopsurg_version": __version__,
        "dataset": str(Path(args.dataset).resolve()),
        "split": dataset.split_dir.name,
        "results": str(Path(args.results).resolve()),
    }
    write_evaluation(result, args.out, meta=meta)
    print(format_table(result.summary, result.scores))
    curves = result.curves if "bop19" in tasks else None  # BOP19 keys only with its task
    write_intervals(result.gt_columns, det, args, curves, early)  # intervals, compare's samples
    if args.figures:
        from bopsurg.viz.figures import figures_of_evaluation

        print(f"wrote {len(figures_of_evaluation(Path(args.out), dataset, det))} figure files")
    print(
        f"\nwrote {Path(args.out) / 'errors.csv'}, summary.json, scores.json "
        f"({len(est)} estimates, {time.perf_counter() - t0:.1f} s)"
    )
    if args.rerun:
        from bopsurg.viz import log_evaluation

        rrd = log_evaluation(dataset, est, result, args.rerun, detections=inputs.boxes)
        print(f"wrote {rrd}; open it with: rerun {rrd}")
    return 0
