"""``bopsurg eval`` statistics: bootstrap 95 % intervals of the paper's table, its recalls
and AUCs (summary.json) and of the BOP24/BOP25 scores (scores.json)."""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bopsurg.atomic import write_text
from bopsurg.evaluation.bootstrap import (
    BOP19_SAMPLES_FILENAME,
    SAMPLES_FILENAME,
    DetectionSamples,
    bop19_intervals,
    confidence_intervals,
    json_strict,
    save_bop19_counts,
)
from bopsurg.evaluation.bop19 import RecallCurve
from bopsurg.evaluation.bop24 import DetectionEvaluation
from bopsurg.evaluation.columns import Columns
from bopsurg.evaluation.summary_ci import (
    TABLE_SAMPLES_FILENAME,
    save_table_rows,
    summary_intervals,
    table_rows,
)


@dataclass(frozen=True)
class EarlyIntervals:
    """The intervals that need no BOP19 recall curve, computed while VSD renders
    (:func:`early_intervals`); None where not asked for.

    Attributes:
        samples: The BOP24 bootstrap samples.
        table: :func:`~bopsurg.evaluation.summary_ci.summary_intervals`' result.
        detection: The BOP24/BOP25 keys' intervals.
        seconds: Time they took.
    """

    samples: DetectionSamples | None
    table: dict[str, Any] | None
    detection: dict[str, tuple[float, float]] | None
    seconds: float


def early_intervals(
    gt_rows: Columns,
    det: DetectionEvaluation | None,
    args: argparse.Namespace,
    min_visib: float,
) -> EarlyIntervals:
    """The table's and BOP24's intervals (``--bootstrap N``; none with 0) and BOP24's samples."""
    t0 = time.perf_counter()
    samples = DetectionSamples.from_evaluation(det) if det is not None else None
    if args.bootstrap == 0:
        return EarlyIntervals(samples, None, None, 0.0)
    table = summary_intervals(gt_rows, min_visib, args.bootstrap, args.seed, args.ci_unit)
    detection = None
    if samples is not None:
        detection = confidence_intervals(samples, args.bootstrap, seed=args.seed, unit=args.ci_unit)
    return EarlyIntervals(samples, table, detection, time.perf_counter() - t0)


def write_intervals(
    gt_rows: Columns,
    det: DetectionEvaluation | None,
    args: argparse.Namespace,
    curves: dict[str, RecallCurve] | None = None,
    early: EarlyIntervals | None = None,
) -> None:
    """Save the BOP24 bootstrap samples (for ``bopsurg compare``) and, with ``--bootstrap N``,
    add ``ci95`` and ``bootstrap`` to ``summary.json`` (the paper's table) and ``scores.json``
    (BOP19 ARs from ``curves``, BOP24/BOP25 keys) and print the intervals; those of ``early``
    (the same evaluation's) are not computed again."""
    out = Path(args.out)
    summary = json.loads((out / "summary.json").read_text())
    min_visib = float(summary["min_visib"])
    if early is None:
        early = early_intervals(gt_rows, det, args, min_visib)
    samples = early.samples
    # none of an earlier run into the same folder: compare must not read another task's samples
    (out / SAMPLES_FILENAME).unlink(missing_ok=True)
    (out / BOP19_SAMPLES_FILENAME).unlink(missing_ok=True)
    if samples is not None:
        samples.save(out / SAMPLES_FILENAME)
    if curves:
        save_bop19_counts(out / BOP19_SAMPLES_FILENAME, curves)
    save_table_rows(out / TABLE_SAMPLES_FILENAME, table_rows(gt_rows, min_visib))
    if args.bootstrap == 0 or early.table is None:
        return
    t0 = time.perf_counter() - early.seconds
    meta = {"replicates": args.bootstrap, "unit": args.ci_unit, "seed": args.seed}
    _add_to_json(out / "summary.json", {"ci95": json_strict(early.table), "bootstrap": meta})
    _print_table_intervals(summary, early.table, args)
    scores_ci: dict[str, tuple[float, float]] = {}
    if curves:  # (given only when the BOP19 task ran: its keys are in scores.json)
        bop19_ci = bop19_intervals(curves, args.bootstrap, seed=args.seed, unit=args.ci_unit)
        scores = json.loads((out / "scores.json").read_text())
        print("  BOP19 6D localization:")
        for key, (lo, hi) in bop19_ci.items():
            print(f"    {key:<32}{scores[key]:.4f}  [{lo:.4f}, {hi:.4f}]")
        scores_ci.update(bop19_ci)
    if early.detection is not None and det is not None:
        ci = early.detection
        print("  BOP24/BOP25 6D detection:")
        for key, (lo, hi) in ci.items():
            print(f"    {key:<32}{det.scores[key]:.4f}  [{lo:.4f}, {hi:.4f}]")
        scores_ci.update(ci)
    if scores_ci:
        _add_to_json(out / "scores.json", {"ci95": json_strict(scores_ci), "bootstrap": meta})
    print(f"  (bootstrap {time.perf_counter() - t0:.2f} s)")


def _print_table_intervals(
    summary: dict[str, Any], table_ci: dict[str, Any], args: argparse.Namespace
) -> None:
    """The intervals of the paper's table and of its recalls."""
    print(f"\n95 % intervals ({args.bootstrap} bootstrap replicates by {args.ci_unit}):")
    for m, stats in table_ci["table"].items():
        text = ", ".join(
            f"{k} {_num(summary['table'][m][k], 2)} [{_num(lo, 2)}, {_num(hi, 2)}]"
            for k, (lo, hi) in stats.items()
        )
        print(f"  {m.upper():<6}{text}")
    print(
        "  recall "
        + ", ".join(
            f"{k} {_num(summary['recall'][k], 3)} [{_num(lo, 3)}, {_num(hi, 3)}]"
            for k, (lo, hi) in table_ci["recall"].items()
        )
    )


def _num(value: float | None, digits: int) -> str:
    """A number for the printed intervals; n/a for a missing one (no instance)."""
    if value is None or math.isnan(value):
        return "n/a"
    return f"{value:.{digits}f}"


def _add_to_json(path: Path, extra: dict[str, Any]) -> None:
    """Add keys to a JSON object file written by the evaluation (atomically)."""
    content = json.loads(path.read_text())
    content.update(extra)
    write_text(path, json.dumps(content, indent=2, allow_nan=False) + "\n")
