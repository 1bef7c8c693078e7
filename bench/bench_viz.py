"""Bench: logging an evaluation to rerun (``log_evaluation``) vs the evaluation itself.

Builds bench_eval's synthetic scene-files-only dataset (default 10,000 images, one needle
each, 5 % duplicate estimates), evaluates it, then times ``log_evaluation``: scalars for every
frame (``send_columns``) plus silhouettes and meshes for the ``--max-frames`` image frames
(default: the module's rule, 100 worst + 100 uniform for 10,000 frames). The dataset has no
RGB files, so the JPEG cost is timed separately on a 640×480 image and added as an estimate.
Prints each time and the ratio logging / evaluation. Seeded.

    python bench/bench_viz.py [--frames 10000] [--max-frames N] [--out bench/out/viz]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_eval import build

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import load_results
from bopsurg.evaluation.runner import evaluate
from bopsurg.viz.rerun_log import frame_table, log_evaluation, select_image_frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--out", default="bench/out/viz")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    root = Path(args.out) / "dataset"
    results = build(root, args.frames, args.seed)
    dataset = BopDataset(root, "test")
    est = load_results(results)

    t0 = time.perf_counter()
    ev = evaluate(dataset, est, instance_metrics=("re", "te", "mssd", "mspd"))
    t_eval = time.perf_counter() - t0

    t0 = time.perf_counter()
    log_evaluation(dataset, est, ev, Path(args.out) / "scalars.rrd", max_frames=0)
    t_scalars = time.perf_counter() - t0

    t0 = time.perf_counter()
    rrd = log_evaluation(dataset, est, ev, Path(args.out) / "eval.rrd", max_frames=args.max_frames)
    t_log = time.perf_counter() - t0

    frames = frame_table(ev.errors, ev.gt_rows)
    n_img = len(select_image_frames(frames["mssd"].to_numpy(float), args.max_frames))
    rgb = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    rgb = cv2.GaussianBlur(rgb, (0, 0), 3)
    t0 = time.perf_counter()
    for _ in range(20):
        cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, 85])
    t_jpeg = (time.perf_counter() - t0) / 20 * n_img

    print(f"frames {len(frames)}, estimates {len(est)}, image frames {n_img}")
    print(f"evaluate (re, te, mssd, mspd + BOP19):   {t_eval:8.2f} s")
    print(f"log_evaluation, scalars only:            {t_scalars:8.2f} s")
    print(
        f"log_evaluation, + silhouettes, meshes:   {t_log:8.2f} s  "
        f"({rrd.stat().st_size / 1e6:.1f} MB)"
    )
    print(f"  + JPEG encoding of {n_img} RGB (est.):   {t_jpeg:8.2f} s")
    print(f"ratio scalars / eval: {t_scalars / t_eval:.3f}")
    print(f"ratio full log / eval: {(t_log + t_jpeg) / t_eval:.3f}")


if __name__ == "__main__":
    main()
