"""``bopsurg eval``: errors, the paper's table and BOP19 scores for a results CSV."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from bopsurg._version import __version__
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.targets import load_targets
from bopsurg.cli.inputs import (
    add_dataset_and_results,
    add_detections_arg,
    add_executor_args,
    load_dataset_and_results,
    load_detections_arg,
)
from bopsurg.errors import BopsurgError
from bopsurg.evaluation.runner import evaluate, evaluate_distributed, write_evaluation
from bopsurg.evaluation.summary import format_table
from bopsurg.executors import make_executor
from bopsurg.metrics.registry import METRICS, help_lines
from bopsurg.plugins import available_plugins, load_plugin

log = logging.getLogger(__name__)

HELP = "evaluate a BOP results CSV: errors.csv, the paper's table, BOP19 average recall"

DESCRIPTION = """\
Evaluate 6D pose estimates (a BOP19 results CSV) on a BOP dataset split.

Writes into --out:
  errors.csv    one row per estimate: scene_id, im_id, obj_id, gt_id (-1 = no GT left for
                it), score, visib_fract, one column per metric (below), tip_visible,
                tail_visible, view_angle_deg
  summary.json  the paper's table (N, mean, std, median, min, max of RE, TE, MSSD over GT
                instances with visib_fract >= --min-visib), missed instances, recall at
                MSSD < 1/2/5 mm and RE < 5/10 deg, ADD and ADD-S AUC (0-0.1 x diameter)
  scores.json   BOP19 scores with the reference toolkit's keys and rules:
                bop19_average_recall_mssd, _mspd, and with a depth renderer _vsd and
                bop19_average_recall; bop19_average_time_per_image; per-threshold details

Matching for errors.csv and the table: in each image, estimates in decreasing score order
take the not-yet-matched GT instance of their object with the smallest MSSD (no threshold).
The BOP scores use the reference's own rules (targets, valid GTs, strict thresholds).

Metrics (--metrics; bopsurg.metrics.registry):
{metrics}
"""


def register(sub: argparse._SubParsersAction) -> None:
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
    p.add_argument("--vsd-delta", type=float, default=15.0, help="VSD tolerance delta, mm")
    p.add_argument(
        "--rerun",
        metavar="FILE.rrd",
        default=None,
        help="also write a rerun recording for visual error analysis (needs bopsurg[rerun])",
    )
    add_detections_arg(p)
    add_executor_args(p, unit="scene")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p.set_defaults(func=run)


def _renderer(choice: str, dataset: BopDataset) -> object | None:
    if choice == "none":
        return None
    has_depth = any((dataset.split_dir / f"{s:06d}" / "depth").is_dir() for s in dataset.scene_ids)
    if choice == "auto":
        if not available_plugins("renderer"):
            log.info("AR_VSD skipped: no depth renderer plugin installed (bopsurg[sim] has one)")
            return None
        if not has_depth:
            log.info("AR_VSD skipped: the dataset has no depth images")
            return None
        try:
            return load_plugin("renderer")()
        except BopsurgError as err:
            log.warning("AR_VSD skipped: %s", err)
            return None
    if not has_depth:
        raise BopsurgError(f"VSD needs depth images; {dataset.split_dir} has no depth/ folders")
    return load_plugin("renderer", choice)()


def _renderer_name(renderer: object | None) -> str | None:
    if renderer is None:
        return None
    for name, ep in available_plugins("renderer").items():
        if ep.value.split(":")[-1] == type(renderer).__name__:
            return name
    raise BopsurgError(f"renderer {type(renderer).__name__} is not an installed plugin")


def run(args: argparse.Namespace) -> int:
    """Run the evaluation and print the table."""
    t0 = time.perf_counter()
    executor = None
    if args.executor != "local" or args.workers != 1:  # fail before any work if unavailable
        executor = make_executor(args.executor, workers=args.workers, ray_address=args.ray_address)
    dataset, est = load_dataset_and_results(args)
    boxes = load_detections_arg(args)  # early: a bad file fails before the evaluation
    targets = load_targets(args.targets) if args.targets else None
    renderer = _renderer(args.renderer, dataset)
    options = {
        "min_visib": args.min_visib,
        "vsd_delta": args.vsd_delta,
        "instance_metrics": [m.strip() for m in args.metrics.split(",") if m.strip()],
    }
    if executor is None:
        result = evaluate(
            dataset,
            est,
            targets=targets,
            renderer=renderer,
            progress=not args.no_progress,
            **options,
        )
    else:  # scenes in parallel: each worker loads the renderer plugin itself
        result = evaluate_distributed(
            dataset,
            est,
            executor=make_executor(
                args.executor, workers=args.workers, ray_address=args.ray_address
            ),
            targets=targets,
            renderer_name=_renderer_name(renderer),
            progress=not args.no_progress,
            **options,
        )
    meta = {
        "bopsurg_version": __version__,
        "dataset": str(Path(args.dataset).resolve()),
        "split": dataset.split_dir.name,
        "results": str(Path(args.results).resolve()),
    }
    write_evaluation(result, args.out, meta=meta)
    print(format_table(result.summary, result.scores))
    print(
        f"\nwrote {Path(args.out) / 'errors.csv'}, summary.json, scores.json "
        f"({len(est)} estimates, {time.perf_counter() - t0:.1f} s)"
    )
    if args.rerun:
        from bopsurg.viz import log_evaluation

        rrd = log_evaluation(dataset, est, result, args.rerun, detections=boxes)
        print(f"wrote {rrd}; open it with: rerun {rrd}")
    return 0
