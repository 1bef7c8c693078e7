r"""Bench: how fast ``bopsurg train detector|pose`` feeds a device, and what holds it back.

Runs the real trainer (shared sample cache, loader workers, batched augmentations, losses,
AdamW, EMA, export) for a few epochs of ``--steps`` steps on each device named, and prints
from each run's ``log.jsonl`` the training samples per second and ``data_wait``: the share
of the epoch's step loop spent waiting for the loader's next batch (the rest is the device's
work and the step's own CPU side). The first epoch decodes every image into the shared cache;
the steady rate is the median of the later epochs. Every exported checkpoint is then loaded
on the CPU, as a user without a GPU would load it, and run on one image.

On a GPU the batches are large and the learning rate scaled by sqrt(batch / recipe batch)
(AdamW), in bfloat16 (``recipe.precision``); on the CPU, fp32 at the recipe's batch.

A small split to carry to a GPU machine (164 frames, 34 MiB; about 4 min on 2 cores):

    bopsurg record --out bench/out/tdev/a.bag --seed 37 --duration 20
    bopsurg generate bench/out/tdev/a.bag --out bench/out/tdev/data --split train \
        --replays 4 --period 0.5 --seed 3 --rgb-format jpg --workers 2

On the GPU machine (carry bench/out/tdev/data; no pybullet needed), under 3 minutes:

    pip install -q --no-deps --no-build-isolation --ignore-requires-python -e . && \
    python bench/bench_train_device.py bench/out/tdev/data --devices cuda --workers 12

Targets there (#42): detector >= 2,000 samples/s, pose head >= 4,000, data_wait < 20 %.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

#: The recipes' own batch and learning rate (DetectorRecipe, PoseRecipe).
RECIPE = {"detector": (16, 2e-3), "pose": (32, 1e-3)}
#: Samples per second each model should reach on a GPU (#42).
TARGET = {"detector": 2000.0, "pose": 4000.0}


def run_training(
    model: str, dataset: Path, device: str, out: Path, args: argparse.Namespace
) -> dict[str, float]:
    """Train one model on one device; its first and steady epochs' rates and waits."""
    batch = args.batch[model] if device != "cpu" else RECIPE[model][0]
    lr = RECIPE[model][1] * math.sqrt(batch / RECIPE[model][0])
    precision = "bf16" if device.startswith("cuda") else "fp32"
    cmd = [
        sys.executable, "-m", "bopsurg.cli.main", "train", model, str(dataset),
        "--split", args.split, "--out", str(out), "--device", device,
        "--epochs", str(args.epochs), "--batch-size", str(batch), "--lr", f"{lr:.6g}",
        "--workers", str(args.workers), "--restart", "--no-progress",
        "--set", f"recipe.steps_per_epoch={args.steps}", "--set", f"recipe.precision={precision}",
        "--set", f"recipe.val_every={args.epochs}",
    ]  # fmt: skip
    if device == "cpu":
        cmd += ["--threads", str(args.threads)]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"{model} on {device} failed (rc {proc.returncode}):\n{proc.stderr[-3000:]}")
    log = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines() if x.strip()]
    rate = np.array([r["samples_per_s"] for r in log])
    wait = np.array([r["data_wait"] for r in log])
    later = slice(1, None) if len(log) > 1 else slice(None)
    return {
        "batch": batch, "lr": lr, "precision": precision, "first": float(rate[0]),
        "rate": float(np.median(rate[later])), "wait": float(np.median(wait[later])),
        "first_wait": float(wait[0]), "wall": wall,
    }  # fmt: skip


def check_on_cpu(runs: Path, dataset: Path, split: str, device: str) -> str:
    """Load a device's exported detector and pose head on the CPU; run the detector on one
    image and the pose head on its GT boxes (a short run's detector may find nothing)."""
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


def report(rows: list[tuple[str, str, dict[str, float]]], args: argparse.Namespace) -> None:
    """The table, and each run against its target."""
    print(f"\n{args.dataset} split {args.split}: {args.epochs} epochs of {args.steps} steps, "
          f"{args.workers} loader workers, {args.threads} CPU threads")  # fmt: skip
    print("| model | device | precision | batch | lr | 1st epoch samples/s (wait) "
          "| steady samples/s | data_wait | target |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for model, device, r in rows:
        ok = r["rate"] >= TARGET[model] and r["wait"] < 0.2
        target = ("met" if ok else "missed") if device != "cpu" else "(GPU only)"
        print(f"| {model} | {device} | {r['precision']} | {r['batch']:.0f} | {r['lr']:.3g} "
              f"| {r['first']:.0f} ({100 * r['first_wait']:.0f} %) | {r['rate']:.0f} "
              f"| {100 * r['wait']:.1f} % | {target} |")  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("--split", default="train")
    p.add_argument("--devices", default="cuda", help="comma-separated (cpu, cuda, ...)")
    p.add_argument("--models", default="detector,pose")
    p.add_argument("--epochs", type=int, default=3, help="the first fills the cache")
    p.add_argument("--steps", type=int, default=30, help="steps per epoch")
    p.add_argument("--batch-det", type=int, default=256, help="detector batch on a GPU")
    p.add_argument("--batch-pose", type=int, default=512, help="pose batch on a GPU")
    p.add_argument("--workers", type=int, default=max(1, min(12, (os.cpu_count() or 2) - 2)))
    p.add_argument("--threads", type=int, default=0, help="CPU threads (0: torch's default)")
    p.add_argument("--out", type=Path, default=Path("bench/out/train_device"))
    args = p.parse_args()
    args.batch = {"detector": args.batch_det, "pose": args.batch_pose}
    if args.threads == 0:
        import torch

        args.threads = torch.get_num_threads()
    rows = []
    for model in args.models.split(","):
        for device in args.devices.split(","):
            r = run_training(model, args.dataset, device, args.out / f"{model}_{device}", args)
            rows.append((model, device, r))
            print(f"{model} on {device}: {r['rate']:.0f} samples/s, data_wait "
                  f"{100 * r['wait']:.1f} % ({r['wall']:.0f} s)", flush=True)  # fmt: skip
    report(rows, args)
    if set(args.models.split(",")) == {"detector", "pose"}:
        for device in args.devices.split(","):
            print(f"{device}-trained weights on the CPU:",
                  check_on_cpu(args.out, args.dataset, args.split, device))  # fmt: skip


if __name__ == "__main__":
    main()
