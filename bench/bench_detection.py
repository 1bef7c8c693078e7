"""Bench: the BOP24 task and its bootstrap intervals on a 10,000-image dataset.

Reuses the dataset of ``bench_eval.py`` (one needle per image, 5 % duplicate estimates,
scenes of 1,000 images) and times, in this process: ``bopsurg eval --task all`` end to end
(BOP19 + BOP24, no VSD) without and with the bootstrap intervals (paper's table and
BOP24 keys), the BOP24 evaluation alone, and the bootstrap of its scores with
N replicates by images and by scenes. Prints the bootstrap's cost relative to the
evaluation it summarises (the goal: at most 1 x eval) and to the BOP24 stage alone. Seeded.

    python bench/bench_detection.py [--images 10000] [--replicates 500] [--out bench/out/det]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import time
from pathlib import Path

from bench_eval import build

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import load_results
from bopsurg.cli.main import main as cli
from bopsurg.evaluation.bootstrap import DEFAULT_REPLICATES, DetectionSamples, confidence_intervals
from bopsurg.evaluation.bop24 import evaluate_bop24


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--images", type=int, default=10_000, help="GT images")
    ap.add_argument(
        "--replicates", type=int, default=DEFAULT_REPLICATES, help="bootstrap replicates"
    )
    ap.add_argument("--out", default="bench/out/det", help="working folder")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    root = Path(args.out) / "dataset"
    results = root / "bench_needle-test.csv"
    if not results.exists():
        build(root, args.images, args.seed)

    t0 = time.perf_counter()
    argv = ["-q", "eval", str(root), str(results), "--out", str(Path(args.out) / "eval")]
    with contextlib.redirect_stdout(io.StringIO()):
        cli([*argv, "--task", "all", "--renderer", "none", "--bootstrap", "0", "--no-progress"])
    t_cli = time.perf_counter() - t0
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        cli([*argv, "--task", "all", "--renderer", "none", "--no-progress"])
    t_cli_ci = time.perf_counter() - t0

    ds, est = BopDataset(root, "test"), load_results(results)
    t0 = time.perf_counter()
    det = evaluate_bop24(ds, est)
    t_bop24 = time.perf_counter() - t0
    samples = DetectionSamples.from_evaluation(det)
    t_boot = {}
    for unit in ("image", "scene"):
        t0 = time.perf_counter()
        ci = confidence_intervals(samples, args.replicates, seed=args.seed, unit=unit)
        t_boot[unit] = time.perf_counter() - t0
    n_runs = samples.est_image.size
    print(f"images: {len(samples.images)}, estimates: {len(est)}, ranked runs: {n_runs}")
    print(f"  eval --task all (no VSD), end to end   {t_cli:8.2f} s")
    label = f"the same with every interval (x{DEFAULT_REPLICATES})"
    print(f"  {label:<39}{t_cli_ci:8.2f} s")
    print(f"  BOP24 evaluation alone                 {t_bop24:8.2f} s")
    for unit, t in t_boot.items():
        label = f"bootstrap x{args.replicates} by {unit}"
        print(f"  {label:<39}{t:8.2f} s  ({t / t_cli:.2f} x eval, {t / t_bop24:.1f} x BOP24)")
    lo, hi = ci["bop24_mAP"]
    print(f"bop24_mAP {det.scores['bop24_mAP']:.4f}, 95 % interval by scene [{lo:.4f}, {hi:.4f}]")


if __name__ == "__main__":
    main()
