"""Bench: what ``bopsurg predict`` costs per image, against its networks alone.

On a BOP split, in one run and one process, times three configurations of the ``gdrnet``
estimator at each batch size asked for:

- networks alone: detector, pose head (``refine.segmenter=none``, ``ends.classifier=none``);
- RGB: the default estimator, no depth images (``--no-depth``);
- RGB-D: the default estimator with the split's depth images.

Each is ``bopsurg predict``'s own timing (the CSV's ``time`` column: a batch's time divided by
its images; image decoding excluded): the mean over the images after the warm-up batches
(excluded). With ``--rounds`` > 1 the three run in turn that many times and the median round
is printed with the range: on a shared machine the ratios of one round are the figure to
trust, since the three ran back to back under the same load. Prints ms per image and the
ratio of each to the networks alone, and the machine.

    python bench/bench_predict_speed.py /work/exp/s38/testsplit --images 60 --batch-size 1 8

``--threads 1`` on a machine shared with other jobs: torch's threads wait for each other
there, and the times say more about the load than about the code.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from bench_metrics import machine

from bopsurg import prediction
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import load_results
from bopsurg.estimation import load_estimator
from bopsurg.prediction import predict_dataset

#: name -> (options over gdrnet's defaults, give depth images)
CONFIGS: dict[str, tuple[dict[str, Any], bool]] = {
    "networks alone": ({"refine": {"segmenter": None}, "ends": {"classifier": None}}, False),
    "RGB": ({}, False),
    "RGB-D": ({}, True),
}


def time_per_image(
    ds: BopDataset, config: str, device: str, batch: int, images: int, warmup: int, out: Path
) -> float:
    """Mean ms per image of one configuration over ``images`` images after ``warmup``."""
    options, depth = CONFIGS[config]
    est = load_estimator("gdrnet", {"device": device, **options})
    csv = out / f"{config.replace(' ', '_')}_{batch}.csv"
    csv.unlink(missing_ok=True)
    # batch 1 without the keyword: the bench also times a bopsurg from before --batch-size
    batching = {} if batch == 1 else {"batch_size": batch}
    predict_dataset(
        ds, est, csv, max_images=warmup + images, progress=False, depth=depth, **batching
    )
    res = load_results(csv)
    seen: dict[tuple[int, int], float] = {}
    for s, i, t in zip(res.scene_id.tolist(), res.im_id.tolist(), res.time.tolist(), strict=True):
        seen.setdefault((s, i), t)
    times = list(seen.values())[warmup:]
    if not times:
        raise SystemExit(f"{config}: no estimates after the {warmup} warm-up images")
    return 1000.0 * float(np.mean(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="BOP dataset root (e.g. /work/exp/s38/testsplit)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--images", type=int, default=60, help="images timed per configuration")
    ap.add_argument("--batch-size", type=int, nargs="+", default=[8], help="one or more")
    ap.add_argument("--warmup", type=int, default=8, help="images excluded first (rounded up "
                    "to whole batches)")  # fmt: skip
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--cpu-time",
        action="store_true",
        help="time the CPU time of predict's thread, not the wall time (with --threads 1 and "
        "OMP_NUM_THREADS=1: the work done, whatever else runs on the machine)",
    )
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--json", help="also write the median ms per image here, by batch size")
    args = ap.parse_args()
    if args.threads is not None:  # one thread: a machine shared with other jobs times fairly
        torch.set_num_threads(args.threads)
    if args.cpu_time:  # predict's clock becomes its thread's CPU time
        prediction.time = SimpleNamespace(perf_counter=time.thread_time)  # type: ignore[assignment]
    ds = BopDataset(args.dataset, args.split)
    print(f"machine: {machine()}; torch {torch.__version__}, {torch.get_num_threads()} threads")
    medians: dict[int, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for batch in args.batch_size:
            warmup = -(-args.warmup // batch) * batch
            ms = {c: [] for c in CONFIGS}  # type: dict[str, list[float]]
            for _ in range(args.rounds):
                for c in CONFIGS:
                    ms[c].append(
                        time_per_image(ds, c, args.device, batch, args.images, warmup, Path(tmp))
                    )
            clock = "CPU time of predict's thread" if args.cpu_time else "wall time"
            print(
                f"batch {batch}, {args.images} images timed after {warmup} warm-up, "
                f"device {args.device}, {args.rounds} round(s), {clock}:"
            )
            medians[batch] = {c: float(np.median(v)) for c, v in ms.items()}
            base = np.array(ms["networks alone"])
            for c, vals in ms.items():
                v = np.array(vals)
                ratio = v / base
                print(
                    f"  {c:15s} {np.median(v):7.1f} ms/image (range {v.min():.1f}-{v.max():.1f})"
                    f"  x{np.median(ratio):.2f} the networks alone "
                    f"(range {ratio.min():.2f}-{ratio.max():.2f})"
                )
    if args.json:
        Path(args.json).write_text(json.dumps({"images": args.images, "ms_per_image": medians}))


if __name__ == "__main__":
    main()
