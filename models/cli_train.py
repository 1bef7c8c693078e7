"""``bopsurg train detector|pose``: train the built-in estimators on a BOP dataset."""

from __future__ import annotations

import argparse
import logging
import time
from typing import Any

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
resumes after the last finished epoch and ends with the same weights. Validation: one
scene in 10 of --split, drawn with a fixed seed, is held out (or --val-split). Presets:
detector cpu (default; width 0.25, depth 0.33, input 320x256 = 640x480 letterboxed at 1/2),
tiny, s, test; pose cpu (ResNet-18 layout at half width, ROI 128 -> 32x32 maps, 32
regions), paper (ResNet-34 layout, ROI 256, 64 regions), test. Seeded: the same command
gives the same weights on the same machine and device, whatever --workers.

Images are read from disk and decoded when first needed; each set (training, validation)
keeps its decoded samples in memory up to loader.cache_mb MiB (default 4096, in each
process that reads it: the training process and each of --workers N's background
processes), so a set that fits is decoded once, a larger one streams (least recently used
samples out first). Neither changes the weights.

--config FILE (YAML or JSON) sets every field of the model config (sizes, loss weights, DZI
jitter ...), the recipe (epochs, lr, batch_size, hsv/flip/scale augmentations ...), the
photometric augmentations (blur, noise, gamma, colour, JPEG; off unless configured, the
'domain' preset turns them all on) and the loader. Flags given on the command line override
the file. The resolved configuration is written to OUT/config.yaml (a valid --config file);
resuming with a different configuration is refused. Print a preset's full defaults with
--dump-config.
"""

EPILOG = """\
a config file (pose.yaml; every key optional, unknown keys are errors):
  preset: cpu            # model preset the 'pose' section modifies
  seed: 0
  pose:                  # PoseConfig fields ('detector:' with DetectorConfig fields)
    z_unit_mm: 100
    roi_in: 160
    w_region: 0.5
  recipe:                # PoseRecipe / DetectorRecipe fields
    epochs: 60
    lr: 5.0e-4
    batch_size: 16
  augment:               # photometric augmentations, per sample
    preset: domain       # off (default) or domain, then overrides:
    blur_p: 0.5
    blur_sigma: [0.5, 2.0]
  loader:                # how samples are read (never changes the weights)
    num_workers: 1       # background reader processes
    cache_mb: 4096       # decoded samples kept, MiB per set and process (0: decode each time)

examples:
  bopsurg train pose --dump-config --preset paper > pose.yaml
  bopsurg train pose data/needle --out runs/pose --config pose.yaml --epochs 80
  bopsurg train detector data/needle --split train --out runs/det --epochs 24
  bopsurg train pose data/needle --split train --out runs/pose --epochs 40
  bopsurg train pose data/needle --split train,train_wide --out runs/pose_ft \\
      --init models/weights/pose.pt --epochs 6 --lr 3e-4     # fine-tune on two splits
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
    p.add_argument("dataset", nargs="?", help="BOP dataset root")
    p.add_argument(
        "--split",
        default="train",
        help="training split, or several comma-separated (train,train_wide) read as one "
        "(default: train)",
    )
    p.add_argument(
        "--val-split",
        default=None,
        help="validation split (default: one scene in 10 held out, a seeded draw)",
    )
    p.add_argument("--out", metavar="DIR", help="run folder (created / resumed); required")
    p.add_argument(
        "--config", metavar="FILE", help="YAML/JSON file of model, recipe, augment, loader settings"
    )
    p.add_argument(
        "--dump-config", action="store_true", help="print the resolved configuration and exit"
    )
    p.add_argument("--preset", default=None, help="model size preset (default: cpu)")
    p.add_argument("--epochs", type=int, default=None, help="epochs (default: 24 det, 40 pose)")
    p.add_argument("--batch-size", type=int, default=None, help="batch size (16 det, 32 pose)")
    p.add_argument("--lr", type=float, default=None, help="peak learning rate (2e-3 / 1e-3)")
    p.add_argument("--seed", type=int, default=None, help="seed of every random choice (default 0)")
    p.add_argument(
        "--init",
        metavar="PT",
        default=None,
        help="fine-tune: start from this exported checkpoint (e.g. models/weights/pose.pt; same "
        "kind and config) instead of random weights (recipe.init in --config)",
    )
    p.add_argument(
        "--workers", type=int, default=None, help="background loader processes (default 0)"
    )
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
    if args.epochs is not None and args.epochs < 1:
        raise BopsurgError(f"--epochs must be >= 1, got {args.epochs}")
    obj_ids = _ids(args.obj_ids)
    if args.model == "pose" and obj_ids and len(obj_ids) > 1:
        raise BopsurgError("--obj-ids: a pose head is trained for one object; run one per object")
    conf = resolve(args, len(obj_ids) if obj_ids else 1)
    if args.dump_config:
        from bopsurg.models.run_config import dump_yaml, resolved

        print(dump_yaml(resolved(args.model, *conf)), end="")
        return 0
    if not args.dataset or not args.out:
        raise BopsurgError("the dataset and --out are required (except with --dump-config)")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    preset, seed, cfg, recipe, loader = conf
    t0 = time.perf_counter()
    if args.model == "detector":
        from bopsurg.models.train_detector import train_detector

        path = train_detector(
            args.dataset, args.out, split=args.split, val_split=args.val_split,
            preset=preset, recipe=recipe, seed=seed, device=args.device, restart=args.restart,
            progress=not args.no_progress, obj_ids=obj_ids, config=cfg, loader=loader,
        )  # fmt: skip
    else:
        from bopsurg.models.train_pose import train_pose

        path = train_pose(
            args.dataset, args.out, split=args.split, val_split=args.val_split,
            obj_id=obj_ids[0] if obj_ids else None, preset=preset, recipe=recipe,
            seed=seed, device=args.device, restart=args.restart,
            progress=not args.no_progress, config=cfg, loader=loader,
        )  # fmt: skip
    print(f"trained {args.model} in {time.perf_counter() - t0:.0f} s -> {path}")
    return 0


def resolve(args: argparse.Namespace, num_classes: int) -> tuple[str, int, Any, Any, Any]:
    """``(preset, seed, model config, recipe, loader)``: defaults, then the ``--config`` file,
    then the flags given on the command line.

    Raises:
        BopsurgError: A bad file, section, key or value (one line naming the file and key).
    """
    from dataclasses import replace

    from bopsurg.models.run_config import LoaderConfig, augment_config, build, read_config_file

    kind = args.model
    data = read_config_file(args.config) if args.config else {}
    where = f"--config {args.config}"
    other = "pose" if kind == "detector" else "detector"
    if other in data:
        raise BopsurgError(f"{where}: section {other!r} configures a {other}, not a {kind} run")
    preset = str(args.preset or data.get("preset") or "cpu")
    seed = args.seed if args.seed is not None else data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise BopsurgError(f"{where}: seed: expected an integer, got {seed!r}")
    recipe_data = data.get("recipe") or {}
    if isinstance(recipe_data, dict) and "augment" in recipe_data:
        raise BopsurgError(f"{where}: recipe.augment: use the top-level 'augment' section")
    model_data = data.get(kind)
    if kind == "detector":
        from bopsurg.models.detector import DetectorConfig
        from bopsurg.models.train_detector import DetectorRecipe

        _check_preset(DetectorConfig.preset, preset)
        base = DetectorConfig.preset(preset, num_classes=num_classes).to_dict()
        cfg: Any = build(DetectorConfig, base, model_data, f"{where}: {kind}")
        recipe: Any = build(DetectorRecipe, {}, recipe_data, f"{where}: recipe")
    else:
        from bopsurg.models.pose.config import PoseConfig
        from bopsurg.models.train_pose import PoseRecipe

        _check_preset(PoseConfig.preset, preset)
        base = PoseConfig.preset(preset).to_dict()
        cfg = build(PoseConfig, base, model_data, f"{where}: {kind}")
        recipe = build(PoseRecipe, {}, recipe_data, f"{where}: recipe")
        if args.symmetric or recipe.symmetric or cfg.symmetric:
            cfg, recipe = replace(cfg, symmetric=True), replace(recipe, symmetric=True)
    overrides = {
        k: v
        for k, v in (
            ("epochs", args.epochs),
            ("batch_size", args.batch_size),
            ("lr", args.lr),
            ("init", args.init),
        )
        if v is not None
    }
    recipe = replace(recipe, augment=augment_config(data.get("augment"), f"{where}: augment"))
    recipe = replace(recipe, **overrides)
    loader = build(LoaderConfig, {}, data.get("loader"), f"{where}: loader")
    if args.workers is not None:
        if args.workers < 0:
            raise BopsurgError(f"--workers must be >= 0, got {args.workers}")
        loader = replace(loader, num_workers=args.workers)
    return preset, seed, cfg, recipe, loader


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
