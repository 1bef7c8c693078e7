r"""Bench: training throughput of the two ``gdrnet`` models on each device, in one run.

Runs the real ``bopsurg train detector|pose`` (loader, augmentations, losses, AdamW, EMA,
validation, export) for a few epochs on every device named, reads the per-epoch wall-clock
seconds from each run's ``log.jsonl`` and prints samples per second and the speed-up of each
device over the first one. The first epoch decodes the images (the loader then keeps them
in memory) and the last one validates, so the steady rate is the median of the epochs in
between. Every exported checkpoint is then loaded on the CPU, as a user on a machine
without a GPU would load it, and runs the estimator on one image.

    python bench/bench_train_device.py DATASET --split train --devices cpu,cuda \
        --epochs 6 --out bench/out/train_device

DATASET: any BOP dataset of the needle with depth (the pose head's coordinate targets come
from it), e.g. a few scenes of the model card's training split.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def run_training(
    model: str, dataset: Path, split: str, device: str, out: Path, args: argparse.Namespace
) -> dict[str, float]:
    """Train one model on one device; its sample count and per-epoch seconds."""
    cmd = [
        sys.executable, "-m", "bopsurg.cli.main", "train", model, str(dataset),
        "--split", split, "--out", str(out), "--device", device, "--epochs", str(args.epochs),
        "--batch-size", str(args.batch_size[model]), "--workers", str(args.workers),
        "--restart", "--no-progress",
    ]  # fmt: skip
    if device == "cpu":
        cmd += ["--threads", str(args.threads)]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"{model} on {device} failed (rc {proc.returncode}):\n{proc.stderr[-2000:]}")
    found = re.search(r"(\d+) train (?:instances|images)", proc.stderr)
    if found is None:
        sys.exit(f"{model} on {device}: no sample count in the log:\n{proc.stderr[-2000:]}")
    n = int(found.group(1))
    seconds = [json.loads(line)["seconds"] for line in (out / "log.jsonl").read_text().split("\n")
               if line.strip()]  # fmt: skip
    epochs = np.diff([0.0, *seconds])
    steady = float(np.median(epochs[1:-1])) if len(epochs) > 2 else float(epochs[-1])
    steps = max(1, n // args.batch_size[model])
    used = steps * args.batch_size[model]
    return {"n": n, "first": float(epochs[0]), "steady": steady, "rate": used / steady,
            "wall": wall}  # fmt: skip


def check_on_cpu(runs: Path, dataset: Path, split: str, device: str) -> str:
    """Load a device's exported detector and pose head on the CPU; run the detector on one
    image and the pose head on its GT boxes (a few epochs' detector may find nothing)."""
    import torch

    from bopsurg.bop.dataset import BopDataset
    from bopsurg.bop.detections import gt_detections
    from bopsurg.bop.images import load_rgb
    from bopsurg.estimation import load_estimator

    options = {
        "detector": str(runs / f"detector_{device}" / "detector.pt"),
        "pose": str(runs / f"pose_{device}" / "pose.pt"),
        "device": "cpu",
        "refine": {"segmenter": None},
        "ends": {"classifier": None},
    }
    est = load_estimator("gdrnet", options)
    ds = BopDataset(dataset, split)
    scene = ds.scene(ds.scene_ids[0])
    im_id = scene.im_ids[0]
    rgb, K = load_rgb(scene.rgb_path(im_id)), scene.camera[im_id].K
    boxes = gt_detections(ds)[(ds.scene_ids[0], im_id)]
    with torch.inference_mode():
        found = len(est.detect(rgb))
        pred = est.predict(rgb, K, boxes=boxes)
    if len(pred) == 0:
        sys.exit(f"{device}-trained pose head gave no pose on the GT boxes")
    finite = all(np.isfinite(p).all() for p in (pred.R, pred.t))
    return f"detector {found} box(es); pose head {len(pred)} pose(s), all finite: {finite}"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("--split", default="train")
    p.add_argument("--devices", default="cpu,cuda", help="comma-separated; the first is 1.0x")
    p.add_argument("--models", default="detector,pose")
    p.add_argument("--epochs", type=int, default=6)
    p.add_argument("--batch-det", type=int, default=16)
    p.add_argument("--batch-pose", type=int, default=32)
    p.add_argument("--workers", type=int, default=4)
    p.add_argument("--threads", type=int, default=0, help="CPU threads (0: torch's default)")
    p.add_argument("--out", type=Path, default=Path("bench/out/train_device"))
    args = p.parse_args()
    args.batch_size = {"detector": args.batch_det, "pose": args.batch_pose}
    devices = args.devices.split(",")
    models = args.models.split(",")
    if args.threads == 0:
        import torch

        args.threads = torch.get_num_threads()
    rows = []
    for model in models:
        base = None
        for device in devices:
            out = args.out / f"{model}_{device}"
            r = run_training(model, args.dataset, args.split, device, out, args)
            base = base or r["rate"]
            rows.append((model, device, r, r["rate"] / base))
            print(f"{model} on {device}: {r['rate']:.1f} samples/s", flush=True)
    print(f"\n{args.dataset} split {args.split}, {args.epochs} epochs, {args.workers} loader "
          f"workers, {args.threads} CPU threads")  # fmt: skip
    print("| model | device | samples | batch | 1st epoch s | steady epoch s | samples/s | "
          "speed-up |\n|---|---|---|---|---|---|---|---|")  # fmt: skip
    for model, device, r, ratio in rows:
        print(f"| {model} | {device} | {r['n']} | {args.batch_size[model]} | {r['first']:.1f} | "
              f"{r['steady']:.2f} | {r['rate']:.1f} | {ratio:.1f}x |")  # fmt: skip
    if set(models) == {"detector", "pose"}:
        for device in devices:
            print(f"{device}-trained weights on the CPU:",
                  check_on_cpu(args.out, args.dataset, args.split, device))  # fmt: skip


if __name__ == "__main__":
    main()
