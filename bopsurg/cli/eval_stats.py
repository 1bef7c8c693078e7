"""``bopsurg eval`` statistics: bootstrap 95 % intervals of the BOP24/BOP25 scores."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from bopsurg.atomic import write_text
from bopsurg.evaluation.bootstrap import (
    CI_UNITS,
    DEFAULT_REPLICATES,
    SAMPLES_FILENAME,
    DetectionSamples,
    confidence_intervals,
    intervals_json,
)
from bopsurg.evaluation.bop24 import DetectionEvaluation


def _replicates(text: str) -> int:
    """``--bootstrap`` value: a non-negative integer (argparse reports a bad one)."""
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"expected a number of replicates >= 0, got {text!r}")
    return n


def add_bootstrap_args(p: argparse.ArgumentParser) -> None:
    """The options of the bootstrap intervals (shared by ``eval`` and ``compare``)."""
    p.add_argument(
        "--bootstrap",
        type=_replicates,
        default=DEFAULT_REPLICATES,
        metavar="N",
        help=f"bootstrap replicates of the 95 %% intervals (default: {DEFAULT_REPLICATES}; "
        "0 = no intervals)",
    )
    p.add_argument(
        "--ci-unit",
        choices=CI_UNITS,
        default="image",
        help="what the bootstrap resamples: target images, or whole scenes when images of a "
        "scene are correlated (consecutive video frames) (default: image)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap (default: 0)")


def write_intervals(det: DetectionEvaluation, args: argparse.Namespace) -> None:
    """Save the bootstrap samples (for ``bopsurg compare``) and, with ``--bootstrap N``, add
    ``ci95`` and ``bootstrap`` to ``scores.json`` and print the intervals."""
    out = Path(args.out)
    samples = DetectionSamples.from_evaluation(det)
    samples.save(out / SAMPLES_FILENAME)
    if args.bootstrap == 0:
        return
    t0 = time.perf_counter()
    ci = confidence_intervals(samples, args.bootstrap, seed=args.seed, unit=args.ci_unit)
    path = out / "scores.json"
    scores = json.loads(path.read_text())
    scores["ci95"] = intervals_json(ci)
    scores["bootstrap"] = {"replicates": args.bootstrap, "unit": args.ci_unit, "seed": args.seed}
    write_text(path, json.dumps(scores, indent=2, allow_nan=False) + "\n")
    print(f"\nBOP24/BOP25 6D detection, 95 % interval ({args.bootstrap} x {args.ci_unit}s):")
    for key, (lo, hi) in ci.items():
        print(f"  {key:<34}{det.scores[key]:.4f}  [{lo:.4f}, {hi:.4f}]")
    print(f"  (bootstrap {time.perf_counter() - t0:.2f} s)")
