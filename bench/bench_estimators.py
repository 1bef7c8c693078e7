"""Bench: train the built-in detector and pose head from scratch, predict, print the paper's table.

Steps (each a `bopsurg` command, resumed when its output already exists, so a killed bench
picks up where it stopped):

  1. record --train-bags episodes (seeds 1..) and --test-bags episodes (seeds 101..), 30 s each
  2. generate the train split (--train-replays viewpoints per bag, seed 0) and the test split
     (--test-replays per bag, seed 1) into one BOP dataset: other episodes, other viewpoints;
     one frame every --period s, so the data has many viewpoints (a replay is one viewpoint)
  3. train detector (--det-epochs), then pose head (--pose-epochs), seed 0, on --device
  4. predict the test split (direct decoding, then PnP-RANSAC decoding), evaluate both
  5. time CPU inference per 640x480 image (detector + pose head, 2 threads)

It prints the dataset and model sizes, the training times and the evaluation tables (the
networks alone: no refinement, no end check), and writes OUT/bench_estimators.json. With
--ship DIR it also copies the trained weights there. The defaults are the first shipped
model's recipe (6,088 training frames; detector 10 and pose head 24 epochs).

    python bench/bench_estimators.py --out runs/bench [--device cuda] [--quick]
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.detections import gt_detections
from bopsurg.bop.images import load_rgb
from bopsurg.bop.results import load_results
from bopsurg.cli.main import main as bopsurg
from bopsurg.estimation import load_estimator
from bopsurg.evaluation.summary import format_table
from bopsurg.prediction import predict_dataset


def run(argv: list[str]) -> float:
    """One bopsurg command; returns its wall time in s."""
    t0 = time.perf_counter()
    code = bopsurg(argv)
    if code:
        raise SystemExit(f"bopsurg {' '.join(argv)} failed with exit code {code}")
    return time.perf_counter() - t0


def params(path: Path) -> int:
    state = torch.load(path, map_location="cpu", weights_only=True)
    return int(sum(v.numel() for v in state.values() if v.is_floating_point()))


def axis_errors(
    ds: BopDataset, results: Path, errors: Path, min_visib: float
) -> tuple[float, float, float]:
    """Median |Δx|, |Δy|, |Δz| (camera frame, mm) of the matched estimates whose GT has
    visib_fract >= min_visib (the table's instances): which axis the TE comes from.

    Expects at most one estimate per image and object (the gdrnet default), so an estimate is
    found by (scene_id, im_id, obj_id)."""
    est = load_results(results)
    t = pd.DataFrame(est.t, columns=["x", "y", "z"])
    t[["scene_id", "im_id", "obj_id"]] = np.stack([est.scene_id, est.im_id, est.obj_id], 1)
    err = pd.read_csv(errors)
    err = err[(err["gt_id"] >= 0) & (err["visib_fract"] >= min_visib)]
    rows = err.merge(t, on=["scene_id", "im_id", "obj_id"], how="left", validate="one_to_one")
    scene_gt = {s: ds.scene(s).gt for s in rows.scene_id.unique()}  # one read per scene
    keys = zip(rows.scene_id, rows.im_id, rows.gt_id, strict=True)
    gt = np.array([scene_gt[s][i][g].t for s, i, g in keys])
    d = np.abs(rows[["x", "y", "z"]].to_numpy() - gt.reshape(-1, 3))
    return tuple(float(v) for v in np.median(d, axis=0))


def inference_ms(dataset: Path, options: dict, n: int = 40) -> dict[str, float]:
    """Median and p90 wall time of estimator.predict on n test images, 2 CPU threads."""
    torch.set_num_threads(2)
    est = load_estimator("gdrnet", {**options, "device": "cpu"})
    ds = BopDataset(dataset, "test")
    keys = [(s, i) for s in ds.scene_ids for i in ds.scene(s).im_ids][:n]
    times = []
    for k, (s, i) in enumerate(keys):
        scene = ds.scene(s)
        rgb, K = load_rgb(scene.rgb_path(i)), scene.camera[i].K
        t0 = time.perf_counter()
        est.predict(rgb, K)
        if k >= 3:  # warm-up
            times.append(1000 * (time.perf_counter() - t0))
    return {"median": float(np.median(times)), "p90": float(np.percentile(times, 90))}


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", required=True, help="work folder (resumed)")
    ap.add_argument("--train-bags", type=int, default=4)
    ap.add_argument("--test-bags", type=int, default=2)
    ap.add_argument("--train-replays", type=int, default=100)
    ap.add_argument("--test-replays", type=int, default=16)
    ap.add_argument(
        "--period", type=float, default=2.0, help="s between frames: many viewpoints, fewer frames"
    )
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--det-epochs", type=int, default=10)
    ap.add_argument("--pose-epochs", type=int, default=24)
    ap.add_argument(
        "--detector",
        default=None,
        help="use this trained detector (.pt + .json) instead of training one: the pose head "
        "alone is retrained on the same data (the detector's own recipe is in its JSON)",
    )
    ap.add_argument("--device", default="auto")
    ap.add_argument("--workers", type=int, default=2, help="generation worker processes")
    ap.add_argument("--quick", action="store_true", help="tiny everything (a smoke run)")
    ap.add_argument("--ship", default=None, help="copy the trained weights here")
    args = ap.parse_args()
    if args.quick:
        args.train_bags, args.test_bags, args.train_replays, args.test_replays = 1, 1, 2, 1
        args.period = 0.5
        args.duration, args.det_epochs, args.pose_epochs = 6.0, 2, 2
    return args


def make_data(args: argparse.Namespace, out: Path, report: dict) -> Path:
    """Record the episodes and generate the train and test splits (resumed); the dataset."""
    data = out / "data"
    train_bags = [out / "bags" / f"train{s}.bag" for s in range(1, args.train_bags + 1)]
    test_bags = [out / "bags" / f"test{s}.bag" for s in range(101, 101 + args.test_bags)]
    for bag in train_bags + test_bags:
        if not bag.exists():
            seed = bag.stem.removeprefix("train").removeprefix("test")
            run(
                [
                    "-q",
                    "record",
                    "--out",
                    str(bag),
                    "--seed",
                    seed,
                    "--duration",
                    f"{args.duration}",
                ]
            )
    gen = ["--period", f"{args.period:g}", "--workers", str(args.workers), "--no-progress"]
    splits = (
        ("train", train_bags, args.train_replays, "0"),
        ("test", test_bags, args.test_replays, "1"),
    )
    report["generate_s"] = 0.0
    for split, bags, replays, seed in splits:
        report["generate_s"] += run(
            ["generate", *map(str, bags), "--out", str(data), "--split", split,
             "--replays", str(replays), "--seed", seed, *gen]
        )  # fmt: skip
        ds = BopDataset(data, split)
        report[f"{split}_images"] = sum(len(ds.scene(s).im_ids) for s in ds.scene_ids)
    return data


def train(args: argparse.Namespace, out: Path, data: Path, report: dict) -> tuple[Path, Path]:
    """Train (or take) the detector, train the pose head; their checkpoints."""
    det, pose = out / "runs" / "det" / "detector.pt", out / "runs" / "pose" / "pose.pt"
    common = ["--seed", "0", "--device", args.device, "--no-progress"]
    if args.detector:
        given = Path(args.detector)
        det = out / "runs" / "det_given" / "detector.pt"
        det.parent.mkdir(parents=True, exist_ok=True)
        for src in (given, given.with_suffix(".json")):
            shutil.copy(src, det.parent / src.name)
        args.det_epochs = json.loads(det.with_suffix(".json").read_text())["meta"]["epoch"]
    else:
        run(["train", "detector", str(data), "--out", str(det.parent),
             "--epochs", str(args.det_epochs), *common])  # fmt: skip
    run(["train", "pose", str(data), "--out", str(pose.parent),
         "--epochs", str(args.pose_epochs), *common])  # fmt: skip
    for name, path in (("detector", det), ("pose", pose)):
        meta = json.loads(path.with_suffix(".json").read_text())["meta"]
        report[f"{name}_train_s"] = meta["train_seconds"]
        report[f"{name}_device"] = meta["device"]
        report[f"{name}_params"] = params(path)
        report[f"{name}_mb"] = path.stat().st_size / 2**20
        report[f"{name}_validation"] = meta["validation"]
        report[f"{name}_settings"] = meta["settings"]
    return det, pose


def evaluate_runs(args, out: Path, data: Path, det: Path, pose: Path, report: dict) -> None:
    """Predict the test split (direct, PnP-RANSAC, direct on GT boxes; network only) and
    score each run."""
    test_ds = BopDataset(data, "test")
    # (decoding, boxes): our detector's boxes, then the oracle GT boxes (the detector's share)
    runs = {"direct": ("direct", None), "pnp": ("pnp", None)}
    runs["gt_boxes"] = ("direct", gt_detections(test_ds))
    for name, (decode, boxes) in runs.items():
        results = out / f"results_{name}.csv"
        results.unlink(missing_ok=True)
        est = load_estimator("gdrnet", network_only(args, det, pose, decode))
        t0 = time.perf_counter()
        predict_dataset(test_ds, est, results, boxes=boxes, progress=False)
        report[f"predict_{name}_s"] = time.perf_counter() - t0
        ev = out / f"eval_{name}"
        run(["-q", "eval", str(data), str(results), "--out", str(ev),
             "--metrics", "re,te,mssd,mspd,add", "--no-progress"])  # fmt: skip
        summary = json.loads((ev / "summary.json").read_text())
        scores = json.loads((ev / "scores.json").read_text())
        axes = axis_errors(test_ds, results, ev / "errors.csv", summary["min_visib"])
        report[f"eval_{name}"] = {"summary": summary, "scores": scores, "axes_mm": axes}
        print(f"\n== {name} ({decode} decoding) ==\n{format_table(summary, scores)}")
        print("median |dx|, |dy|, |dz| (camera frame): " + ", ".join(f"{v:.2f}" for v in axes))
        if decode == "pnp":  # how many ROIs PnP solved: a silent fallback would copy 'direct'
            st = est.head.stats  # type: ignore[attr-defined]
            report["pnp_solved"], report["pnp_fallback"] = st.pnp_solved, st.pnp_fallback
            print(f"PnP-RANSAC solved {st.pnp_solved} ROIs, {st.pnp_fallback} fell back")


def network_only(args, det: Path, pose: Path, decode: str = "direct") -> dict:
    """``gdrnet`` options of the networks alone (no refinement, no end check)."""
    options: dict = {"detector": str(det), "pose": str(pose), "device": args.device}
    options |= {"head": {"decode": decode}, "refine": {"segmenter": None}}
    options["ends"] = {"classifier": None}
    if args.quick:  # two epochs find no box above the default threshold: take the best
        options["detect"] = {"conf": 0.0}
    return options


def main() -> None:
    args = parse_args()
    out = Path(args.out)
    report: dict = {"args": vars(args), "machine": platform.machine(), "torch": torch.__version__}
    t_all = time.perf_counter()
    data = make_data(args, out, report)
    det, pose = train(args, out, data, report)
    evaluate_runs(args, out, data, det, pose, report)
    report["cpu_inference_ms"] = inference_ms(data, network_only(args, det, pose))
    report["total_s"] = time.perf_counter() - t_all
    (out / "bench_estimators.json").write_text(json.dumps(report, indent=2, default=str) + "\n")
    print(
        f"\ndataset: {report['train_images']} train / {report['test_images']} test images; "
        f"detector {report['detector_params'] / 1e6:.2f} M params, {args.det_epochs} epochs, "
        f"{report['detector_train_s'] / 60:.1f} min; pose head {report['pose_params'] / 1e6:.2f} M "
        f"params, {args.pose_epochs} epochs, {report['pose_train_s'] / 60:.1f} min "
        f"({report['pose_device']})"
    )
    print(
        f"CPU inference (detector + pose head, 640x480, 2 threads): "
        f"median {report['cpu_inference_ms']['median']:.1f} ms, "
        f"p90 {report['cpu_inference_ms']['p90']:.1f} ms per image"
    )
    if args.ship:
        ship(Path(args.ship), det, pose)


def ship(dest: Path, det: Path, pose: Path) -> None:
    """Copy the weights to ``dest`` (MODEL_CARD.md there is written by hand from the numbers
    this bench prints)."""
    dest.mkdir(parents=True, exist_ok=True)
    for path in (det, pose):
        shutil.copy(path, dest / path.name)
        shutil.copy(path.with_suffix(".json"), dest / path.with_suffix(".json").name)
    print(f"shipped to {dest}")


if __name__ == "__main__":
    main()
