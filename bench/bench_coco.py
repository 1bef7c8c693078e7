"""Bench: bootstrap intervals of the COCO 2D scores against the pycocotools evaluation they
summarise, on a synthetic 10,000-image set.

One needle-like GT box per image (COCO small / medium sizes), a detection per GT jittered
around it (5 % missed, 5 % duplicated) and a false positive on every fifth image; seeded.
Times pycocotools' ``evaluate + accumulate + summarize`` (bbox), then collecting the samples
from ``evalImgs`` and N bootstrap replicates of all 12 stats, and prints the ratio (the goal:
at most 1 x the evaluation).

    python bench/bench_coco.py [--images 10000] [--replicates 500]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import time

import numpy as np

from bopsurg.evaluation.coco_bootstrap import CocoSamples, confidence_intervals
from bopsurg.evaluation.options import DEFAULT_REPLICATES


def build(n: int, seed: int) -> tuple[dict, list[dict]]:
    """COCO ground truth (dict) and detections of n images."""
    rng = np.random.default_rng(seed)
    side = rng.choice([20.0, 60.0], n) * rng.uniform(0.7, 1.3, n)
    xy = rng.uniform(0, 500, (n, 2))
    boxes = np.c_[xy, side, side * rng.uniform(0.3, 1.0, n)]
    images = [{"id": i, "width": 640, "height": 480} for i in range(n)]
    anns = [
        {"id": i + 1, "image_id": i, "category_id": 1, "bbox": boxes[i].tolist(),
         "area": float(boxes[i, 2] * boxes[i, 3]), "iscrowd": 0}
        for i in range(n)
    ]  # fmt: skip
    dets = []
    for i in range(n):
        copies = 0 if rng.random() < 0.05 else 1 + int(rng.random() < 0.05)
        for _ in range(copies):
            jitter = rng.normal(0, 0.1, 4) * boxes[i, [2, 3, 2, 3]]
            box = boxes[i] + jitter
            box[2:] = np.maximum(box[2:], 1.0)
            dets.append({"image_id": i, "category_id": 1, "bbox": box.tolist(),
                         "score": float(rng.uniform(0.3, 1.0))})  # fmt: skip
        if i % 5 == 0:
            dets.append({"image_id": i, "category_id": 1, "score": float(rng.uniform(0, 0.6)),
                         "bbox": [*rng.uniform(0, 500, 2).tolist(), 30.0, 20.0]})  # fmt: skip
    gt = {"images": images, "annotations": anns, "categories": [{"id": 1, "name": "needle"}]}
    return gt, dets


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--images", type=int, default=10_000, help="GT images")
    ap.add_argument(
        "--replicates", type=int, default=DEFAULT_REPLICATES, help="bootstrap replicates"
    )
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    gt, dets = build(args.images, args.seed)
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = gt
        coco_gt.createIndex()
        ev = COCOeval(coco_gt, coco_gt.loadRes(dets), "bbox")
        ev.params.imgIds = sorted(coco_gt.getImgIds())
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    t_eval = time.perf_counter() - t0
    t0 = time.perf_counter()
    samples = CocoSamples.from_cocoevals([("bbox", ev)], [(1, i) for i in ev.params.imgIds])
    t_collect = time.perf_counter() - t0
    t0 = time.perf_counter()
    ci = confidence_intervals(samples, args.replicates, seed=args.seed)
    t_boot = time.perf_counter() - t0
    lo, hi = ci["bop22_coco_bbox_AP"]
    print(f"{args.images} images, {len(dets)} detections, {args.replicates} replicates")
    print(f"pycocotools evaluate+accumulate+summarize  {t_eval:7.2f} s   AP {ev.stats[0]:.4f}")
    print(f"collect samples from evalImgs              {t_collect:7.2f} s")
    print(f"bootstrap, all 12 stats {t_boot:24.2f} s   AP CI [{lo:.4f}, {hi:.4f}]")
    print(f"bootstrap cost / evaluation: {(t_collect + t_boot) / t_eval:.2f} x (goal <= 1)")


if __name__ == "__main__":
    main()
