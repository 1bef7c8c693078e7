"""``bopsurg train detector|pose|seg|ends``: train the built-in estimator's models on a BOP
dataset, all on the one epoch loop of :mod:`bopsurg.models.training`."""

from __future__ import annotations

import argparse
import importlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import torch

from bopsurg.errors import BopsurgError

log = logging.getLogger(__name__)

HELP = "train the built-in detector, pose head, needle segmenter or end classifier"

DESCRIPTION = """\
Train one of the four models of the built-in 'gdrnet' estimator on a BOP dataset split:

  detector   YOLOX-like 2D detector (CSPDarknet + PAFPN + decoupled anchor-free head,
             SimOTA), trained on the bbox_visib boxes of scene_gt_info.json
  pose       GDR-Net-like pose head (dynamic zoom-in crops, visible mask, dense
             normalised coordinates, surface regions, Patch-PnP with allocentric 6D
             rotation and SITE translation), trained on the GT poses; coordinate
             targets come from the depth images and GT poses on the fly
  seg        the needle segmenter of the refinement (a small U-Net: visible and, with
             seg.amodal, full masks at about 1 px, on jittered crops of the GT needles)
  ends       the needle-end classifier (which end is the tip: patches of both ends at
             the GT pose, turned, scaled and recoloured)

seg and ends count their run in steps: recipe.epochs x recipe.steps_per_epoch batches drawn
from shuffles of the training set (an epoch is the unit of validation and resuming).

Writes into --out: MODEL.pt + MODEL.json (the exported EMA weights, float16, and their
config, loaded with weights_only=True), log.jsonl (losses and validation per epoch),
validated/eNNN/MODEL.pt + .json (the export after each validated epoch, to choose the epoch
on validation splits afterwards), train_state.pt/.json (to resume). Rerun the same command
after an interruption: it resumes after the last finished epoch and ends with the same
weights. Validation: one scene in 10 of --split, drawn with a fixed seed, is held out (or
--val-split). Presets:
detector cpu (default; width 0.25, depth 0.33, input 320x256 = 640x480 letterboxed at 1/2),
tiny, s, test; pose cpu (ResNet-18 layout at half width, ROI 128 -> 32x32 maps, 32
regions), paper (ResNet-34 layout, ROI 256, 64 regions), test; seg cpu (visible mask,
3 stages), amodal (the shipped layout: full mask too, 4 stages), test; ends cpu, test.
Seeded: the same command gives the same weights on the same machine and device, whatever
--workers.

Images are read from disk and decoded when first needed; each detector or pose set
(training, validation) keeps its decoded samples, at the training resolution, in one
memory-mapped file that the training process and all --workers N background processes share
(loader.shared_cache; /dev/shm where it has room), up to loader.cache_mb MiB per set
(default 4096): each sample is decoded once in all, samples past the budget every time. The
segmenter's contexts (of many sizes) are cached per process, least recently used out
first. Neither changes the weights. On a GPU: --set recipe.precision=bf16 (autocast), larger
--batch-size with a scaled --lr, and --workers (bench/bench_train_device.py measures it).

--config FILE (YAML or JSON) sets every field of the model config (sizes, loss weights, DZI
jitter ...), the recipe (epochs, lr, batch_size, hsv/flip/scale augmentations ...), the
photometric augmentations (blur, noise, gamma, colour, JPEG; off unless configured, the
'domain' preset turns them all on) and the loader. Flags given on the command line override
the file, and --set SECTION.KEY=VALUE any one field after both. The resolved configuration
is written to OUT/config.yaml (a valid --config file); resuming with a different
configuration is refused. Print a preset's full defaults with --dump-config.

A --config recipe with a data: section (bopsurg/recipes/robust_*.yaml) names the splits it
trains and validates on, as record + generate settings: they are the default --split and
--val-split, and one that DATASET lacks stops the run with the 'bopsurg data' command that
makes it.
"""

EPILOG = """\
a config file (pose.yaml; every key optional, unknown keys are errors):
  preset: cpu            # model preset the 'pose' section modifies
  seed: 0
  pose:                  # PoseConfig fields ('detector:' DetectorConfig's, 'seg:'
                         # SegConfig's, 'ends:' EndConfig's)
    z_unit_mm: 100
    roi_in: 160
    w_region: 0.5
  recipe:                # PoseRecipe / DetectorRecipe / SegRecipe / EndsRecipe fields
    epochs: 60
    lr: 5.0e-4
    batch_size: 16
  augment:               # photometric augmentations, per sample
    preset: domain       # off (default; ends: domain) or domain, then overrides:
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
  bopsurg train seg data/needle --split train,train_wide --out runs/seg --preset amodal \\
      --config bopsurg/recipes/seg.yaml                       # the shipped segmenter's recipe
  bopsurg train ends data/needle --out runs/ends --set recipe.margin=3
  bopsurg predict data/needle --split test --out results.csv \\
      --detector runs/det/detector.pt --pose runs/pose/pose.pt
"""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "train",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "model", choices=("detector", "pose", "seg", "ends"), help="which model to train"
    )
    p.add_argument("dataset", nargs="?", help="BOP dataset root")
    p.add_argument(
        "--split",
        default=None,
        help="training split, or several comma-separated (train,train_wide) read as one "
        "(default: the --config recipe's data.train, else train)",
    )
    p.add_argument(
        "--val-split",
        default=None,
        help="validation split(s) (default: the --config recipe's data.val, else one scene in "
        "10 held out, a seeded draw)",
    )
    p.add_argument("--out", metavar="DIR", help="run folder (created / resumed); required")
    p.add_argument(
        "--config", metavar="FILE", help="YAML/JSON file of model, recipe, augment, loader settings"
    )
    p.add_argument(
        "--set",
        action="append",
        metavar="SECTION.KEY=VALUE",
        help="set one field (VALUE in YAML), after --config and the flags; repeatable "
        "(--set recipe.hue_whole=0.5 --set seg.stages=4)",
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


@dataclass(frozen=True)
class Kind:
    """What ``bopsurg train KIND`` needs of one model: its config class and presets, its
    recipe class, and its trainer (``bopsurg.models.MODULE.FUNCTION``)."""

    config: type[Any]
    preset: Callable[[str, int], Any]  # (preset name, number of classes) -> config
    recipe: type[Any]
    module: str
    function: str


def _kinds() -> dict[str, Kind]:
    from bopsurg.models.detector import DetectorConfig
    from bopsurg.models.pose.config import PoseConfig
    from bopsurg.models.refine.ends import EndConfig
    from bopsurg.models.refine.seghead import SegConfig
    from bopsurg.models.refine.train_ends import EndsRecipe, ends_preset
    from bopsurg.models.refine.train_seg import SegRecipe, seg_preset
    from bopsurg.models.train_detector import DetectorRecipe
    from bopsurg.models.train_pose import PoseRecipe

    def detector(name: str, n: int) -> Any:
        return DetectorConfig.preset(name, num_classes=n)

    return {
        "detector": Kind(DetectorConfig, detector, DetectorRecipe, "train_detector",
                         "train_detector"),
        "pose": Kind(PoseConfig, lambda name, _: PoseConfig.preset(name), PoseRecipe, "train_pose",
                     "train_pose"),
        "seg": Kind(SegConfig, lambda name, _: seg_preset(name), SegRecipe, "refine.train_seg",
                    "train_seg"),
        "ends": Kind(EndConfig, lambda name, _: ends_preset(name), EndsRecipe,
                     "refine.train_ends", "train_ends"),
    }  # fmt: skip


def run(args: argparse.Namespace) -> int:
    """Execute the subcommand."""
    if args.epochs is not None and args.epochs < 1:
        raise BopsurgError(f"--epochs must be >= 1, got {args.epochs}")
    obj_ids = _ids(args.obj_ids)
    if args.model != "detector" and obj_ids and len(obj_ids) > 1:
        raise BopsurgError(
            f"--obj-ids: a {args.model} model is trained for one object; run one per object"
        )
    conf = resolve(args, len(obj_ids) if obj_ids else 1)
    from bopsurg.models.run_config import (
        apply_overrides,
        check_splits_made,
        read_config_file,
        recipe_data,
        run_splits,
    )

    raw = apply_overrides(read_config_file(args.config) if args.config else {}, args.set or [])
    data = recipe_data(raw, f"--config {args.config}")
    if args.dump_config:
        from bopsurg.models.config_tree import to_yaml
        from bopsurg.models.run_config import resolved

        extra = {"data": raw["data"]} if data is not None else {}
        print(to_yaml({**resolved(args.model, *conf), **extra}), end="")
        return 0
    if not args.dataset or not args.out:
        raise BopsurgError("the dataset and --out are required (except with --dump-config)")
    split, val_split = run_splits(args.split, args.val_split, data)
    if data is not None:
        check_splits_made(args.dataset, [*split.split(","), *(val_split or "").split(",")],
                          data, args.config)  # fmt: skip
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    preset, seed, cfg, recipe, loader = conf
    kind = _kinds()[args.model]
    trainer = getattr(importlib.import_module(f"bopsurg.models.{kind.module}"), kind.function)
    objects: dict[str, Any] = (
        {"obj_ids": obj_ids}
        if args.model == "detector"
        else {"obj_id": obj_ids[0] if obj_ids else None}
    )
    t0 = time.perf_counter()
    path = trainer(
        args.dataset, args.out, split=split, val_split=val_split, preset=preset,
        recipe=recipe, seed=seed, device=args.device, restart=args.restart,
        progress=not args.no_progress, config=cfg, loader=loader, **objects,
    )  # fmt: skip
    print(f"trained {args.model} in {time.perf_counter() - t0:.0f} s -> {path}")
    return 0


def resolve(args: argparse.Namespace, num_classes: int) -> tuple[str, int, Any, Any, Any]:
    """``(preset, seed, model config, recipe, loader)``: defaults, then the ``--config`` file,
    then the flags given on the command line, then ``--set``.

    Raises:
        BopsurgError: A bad file, section, key or value (one line naming the file and key).
    """
    from bopsurg.models.run_config import (
        MODEL_SECTIONS,
        LoaderConfig,
        apply_overrides,
        augment_config,
        build,
        read_config_file,
    )

    section = args.model
    data = _with_flags(read_config_file(args.config) if args.config else {}, args)
    data = apply_overrides(data, list(args.set or []))
    where = f"--config {args.config}" if args.config else "--set"
    for other in MODEL_SECTIONS:
        if other != section and other in data:
            raise BopsurgError(
                f"{where}: section {other!r} configures a {other} model, not a {section} run"
            )
    preset = str(data.get("preset") or "cpu")
    seed = data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise BopsurgError(f"{where}: seed: expected an integer, got {seed!r}")
    recipe_data = data.get("recipe") or {}
    if isinstance(recipe_data, dict) and "augment" in recipe_data:
        raise BopsurgError(f"{where}: recipe.augment: use the top-level 'augment' section")
    kind = _kinds()[args.model]
    try:
        base = kind.preset(preset, num_classes).to_dict()
    except (ValueError, KeyError) as err:
        raise BopsurgError(f"--preset: {err}") from err
    cfg = build(kind.config, base, data.get(section), f"{where}: {section}")
    recipe = build(kind.recipe, {}, recipe_data, f"{where}: recipe")
    if args.model == "pose" and (recipe.symmetric or cfg.symmetric):
        cfg, recipe = replace(cfg, symmetric=True), replace(recipe, symmetric=True)
    augment = augment_config(data.get("augment"), f"{where}: augment", kind.recipe().augment)
    recipe = replace(recipe, augment=augment)
    loader = build(LoaderConfig, {}, data.get("loader"), f"{where}: loader")
    return preset, seed, cfg, recipe, loader


def _with_flags(data: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """The ``--config`` mapping ``data`` with the values of the flags given set in it."""
    if args.workers is not None and args.workers < 0:
        raise BopsurgError(f"--workers must be >= 0, got {args.workers}")
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    flags = {
        ("preset", None): args.preset,
        ("seed", None): args.seed,
        ("recipe", "epochs"): args.epochs,
        ("recipe", "batch_size"): args.batch_size,
        ("recipe", "lr"): args.lr,
        ("recipe", "init"): args.init,
        ("recipe", "symmetric"): True if args.model == "pose" and args.symmetric else None,
        ("loader", "num_workers"): args.workers,
    }
    for (section, key), value in flags.items():
        if value is None:
            continue
        if key is None:
            out[section] = value
        elif isinstance(out.get(section), dict):
            out[section][key] = value
        elif out.get(section) is None:
            out[section] = {key: value}
    return out


def _ids(text: str | None) -> list[int] | None:
    if not text:
        return None
    try:
        return [int(v) for v in text.split(",")]
    except ValueError as err:
        raise BopsurgError(f"--obj-ids: expected integers like 1,2, got {text!r}") from err
