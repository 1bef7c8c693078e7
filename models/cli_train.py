"""``bopsurg train detector|pose``: train the built-in estimators on a BOP dataset."""

from __future__ import annotations

import argparse
import logging
import time

import torch

from bopsurg.errors import BopsurgError

log = logging.getLogger(__name__)

HELP = "train the built-in detector or pose head on a BOP dataset (CPU or GPU)"

DESCRIPTION = """\
Train one of the two models of the built-in 'gdrnet' estimator on a BOP dataset split:

  detector   YOLOX-like 2D detector (CSPDarknet + PAFPN + decoupled anchor-free head,
             SimOTA), trained on the bbox_visib boxes of scene_gt_info.json
  pose       GDR-Net-like pose head (dynamic zoom-in crops, visible mask, dense
             normalised coordinates, surface regions, Patch-PnP with allocentric 6D
             rotation and SITE translation), trained on the GT poses; coordinate
             targets come from the depth images and GT poses on the fly

Writes into --out: MODEL.pt + MODEL.json (the exported EMA weights, float16, and their
config, loaded with weights_only=True), log.jsonl (losses and validation per epoch),
train_state.pt/.json (to resume). Rerun the same command after an interruption: it
resumes after the last finished epoch and ends with the same weights. Validation: every
10th scene of --split is held out (or --val-split). Presets: detector cpu (default; width
0.25, depth 0.33, input 320x256 = 640x480 letterboxed at 1/2), tiny, s, test; pose cpu
(ResNet-18 layout at half width, ROI 128 -> 32x32 maps, 32 regions), paper (ResNet-34
layout, ROI 256, 64 regions), test. Seeded: the same command gives the same weights on the
same machine and device.
"""

EPILOG = """\
examples:
  bopsurg train detector data/needle --split train --out runs/det --epochs 24
  bopsurg train pose data/needle --split train --out runs/pose --epochs 40
  bopsurg train pose data/needle --out runs/pose_gpu --preset paper --device cuda
  bopsurg predict data/needle --split test --out results.csv \\
      --detector runs/det/detector.pt --pose runs/pose/pose.pt
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "train",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("model", choices=("detector", "pose"), help="which model to train")
    p.add_argument("dataset", help="BOP dataset root")
    p.add_argument("--split", default="train", help="training split (default: train)")
    p.add_argument(
        "--val-split", default=None, help="validation split (default: every 10th scene held out)"
    )
    p.add_argument("--out", required=True, metavar="DIR", help="run folder (created / resumed)")
    p.add_argument("--preset", default="cpu", help="model size preset (default: cpu)")
    p.add_argument("--epochs", type=int, default=None, help="epochs (default: 24 det, 40 pose)")
    p.add_argument("--batch-size", type=int, default=None, help="batch size (16 det, 32 pose)")
    p.add_argument("--lr", type=float, default=None, help="peak learning rate (2e-3 / 1e-3)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    p.add_argument("--device", default="auto", help="cpu, cuda, cuda:1 ... (default: auto)")
    p.add_argument(
        "--obj-ids",
        default=None,
        metavar="ID[,ID...]",
        help="detector: objects to detect, one class each; pose: the one object of the head "
        "(default: the dataset's first object, e.g. the needle)",
    )
    p.add_argument(
        "--symmetric",
        action="store_true",
        help="pose: treat the object as symmetric (models_info symmetries, or the needle's "
        "2-fold tip/tail symmetry) in the point-matching loss; default non-symmetric",
    )
    p.add_argument("--threads", type=int, default=None, help="CPU threads (default: torch's)")
    p.add_argument("--restart", action="store_true", help="discard a previous run in --out")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Execute the subcommand."""
    from dataclasses import replace

    if args.epochs is not None and args.epochs < 1:
        raise BopsurgError(f"--epochs must be >= 1, got {args.epochs}")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    overrides = {
        k: v
        for k, v in (("epochs", args.epochs), ("batch_size", args.batch_size), ("lr", args.lr))
        if v is not None
    }
    obj_ids = _ids(args.obj_ids)
    if args.model == "pose" and obj_ids and len(obj_ids) > 1:
        raise BopsurgError("--obj-ids: a pose head is trained for one object; run one per object")
    t0 = time.perf_counter()
    if args.model == "detector":
        from bopsurg.models.detector import DetectorConfig
        from bopsurg.models.train_detector import DetectorRecipe, train_detector

        _check_preset(DetectorConfig.preset, args.preset)
        path = train_detector(
            args.dataset, args.out, split=args.split, val_split=args.val_split,
            preset=args.preset, recipe=replace(DetectorRecipe(), **overrides),
            seed=args.seed, device=args.device, restart=args.restart,
            progress=not args.no_progress, obj_ids=obj_ids,
        )  # fmt: skip
    else:
        from bopsurg.models.pose.config import PoseConfig
        from bopsurg.models.train_pose import PoseRecipe, train_pose

        _check_preset(PoseConfig.preset, args.preset)
        recipe = replace(PoseRecipe(symmetric=args.symmetric), **overrides)
        path = train_pose(
            args.dataset, args.out, split=args.split, val_split=args.val_split,
            obj_id=obj_ids[0] if obj_ids else None, preset=args.preset, recipe=recipe,
            seed=args.seed, device=args.device, restart=args.restart,
            progress=not args.no_progress,
        )  # fmt: skip
    print(f"trained {args.model} in {time.perf_counter() - t0:.0f} s -> {path}")
    return 0


def _check_preset(preset, name: str) -> None:
    try:
        preset(name)
    except (ValueError, KeyError) as err:
        raise BopsurgError(f"--preset: {err}") from err


def _ids(text: str | None) -> list[int] | None:
    if not text:
        return None
    try:
        return [int(v) for v in text.split(",")]
    except ValueError as err:
        raise BopsurgError(f"--obj-ids: expected integers like 1,2, got {text!r}") from err
