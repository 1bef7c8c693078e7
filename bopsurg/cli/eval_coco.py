"""``bopsurg eval`` on a BOP COCO results JSON: the 2D detection / segmentation tasks."""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from bopsurg._version import __version__
from bopsurg.atomic import write_text
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.targets import load_image_targets
from bopsurg.evaluation.bootstrap import json_strict
from bopsurg.evaluation.coco_bootstrap import COCO_SAMPLES_FILENAME, confidence_intervals
from bopsurg.evaluation.coco_eval import evaluate_coco_samples, load_coco_results
from bopsurg.evaluation.tasks import resolve_tasks


def run_coco(args: argparse.Namespace) -> int:
    """Evaluate ``args.results`` (COCO JSON) and write ``scores.json`` (with 95 % bootstrap
    intervals under ``ci95`` when ``args.bootstrap`` > 0) and the bootstrap samples
    (``bootstrap_coco.npz``, for ``bopsurg compare``) into ``args.out``."""
    t0 = time.perf_counter()
    dataset = BopDataset(
        args.dataset, args.split, split_type=args.split_type, name=args.dataset_name
    )
    results = load_coco_results(args.results)
    present = []
    if any(r.get("bbox") for r in results):
        present.append("coco-bbox")
    if any(r.get("segmentation") for r in results):
        present.append("coco-segm")
    every = "all" in args.task.split(",")  # what the file holds; a named task must be there
    tasks = resolve_tasks(args.task, "coco", present if every else None)
    targets = load_image_targets(args.targets_bop24) if args.targets_bop24 else None
    scores, samples = evaluate_coco_samples(dataset, results, tasks, targets)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    extra: dict[str, object] = {}
    ci: dict[str, tuple[float, float]] = {}
    (out / COCO_SAMPLES_FILENAME).unlink(missing_ok=True)  # none of an earlier run
    if samples is not None:
        samples.save(out / COCO_SAMPLES_FILENAME)
        if args.bootstrap:
            ci = confidence_intervals(samples, args.bootstrap, seed=args.seed, unit=args.ci_unit)
            extra = {
                "ci95": json_strict(ci),
                "bootstrap": {
                    "replicates": args.bootstrap,
                    "unit": args.ci_unit,
                    "seed": args.seed,
                },
            }
    meta = {
        "bopsurg_version": __version__,
        "dataset": str(Path(args.dataset).resolve()),
        "split": dataset.split_dir.name,
        "results": str(Path(args.results).resolve()),
        "tasks": list(tasks),
    }
    content = {**scores, **extra, "meta": meta}
    write_text(out / "scores.json", json.dumps(content, indent=2, allow_nan=False) + "\n")
    width = max(len(k) for k in scores)
    for k, v in scores.items():
        lo, hi = ci.get(k, (None, None))
        finite = lo is not None and hi is not None and math.isfinite(lo) and math.isfinite(hi)
        interval = f"  [{lo:.4f}, {hi:.4f}]" if finite else ""
        print(f"{k:<{width}}  {v:.4f}{interval}")
    if ci:
        print(f"(95 % intervals: {args.bootstrap} bootstrap replicates by {args.ci_unit})")
    if getattr(args, "figures", False):
        print("(--figures draws pose results only: nothing to draw for a COCO results JSON)")
    print(
        f"\nwrote {out / 'scores.json'} ({len(results)} results, {time.perf_counter() - t0:.1f} s)"
    )
    return 0
