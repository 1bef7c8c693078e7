"""``bopsurg eval`` on a BOP COCO results JSON: the 2D detection / segmentation tasks."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from bopsurg._version import __version__
from bopsurg.atomic import write_text
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.targets import load_image_targets
from bopsurg.evaluation.coco_eval import evaluate_coco, load_coco_results
from bopsurg.evaluation.tasks import resolve_tasks


def run_coco(args: argparse.Namespace) -> int:
    """Evaluate ``args.results`` (COCO JSON) and write ``scores.json`` into ``args.out``."""
    t0 = time.perf_counter()
    dataset = BopDataset(args.dataset, args.split, split_type=args.split_type)
    results = load_coco_results(args.results)
    present = []
    if any(r.get("bbox") for r in results):
        present.append("coco-bbox")
    if any(r.get("segmentation") for r in results):
        present.append("coco-segm")
    tasks = resolve_tasks(args.task, "coco", present if args.task == "all" else None)
    targets = load_image_targets(args.targets_bop24) if args.targets_bop24 else None
    scores = evaluate_coco(dataset, results, tasks, targets)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "bopsurg_version": __version__,
        "dataset": str(Path(args.dataset).resolve()),
        "split": dataset.split_dir.name,
        "results": str(Path(args.results).resolve()),
        "tasks": list(tasks),
    }
    write_text(out / "scores.json", json.dumps({**scores, "meta": meta}, indent=2) + "\n")
    width = max(len(k) for k in scores)
    print("\n".join(f"{k:<{width}}  {v:.4f}" for k, v in scores.items()))
    if getattr(args, "bootstrap", 0):
        print("(no 95 % intervals for the COCO keys: --bootstrap resamples pose results only)")
    if getattr(args, "figures", False):
        print("(--figures draws pose results only: nothing to draw for a COCO results JSON)")
    print(
        f"\nwrote {out / 'scores.json'} ({len(results)} results, {time.perf_counter() - t0:.1f} s)"
    )
    return 0
