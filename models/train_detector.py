"""Train the YOLOX-like detector on the ``bbox_visib`` boxes of a BOP split.

Recipe (the YOLOX recipe scaled to a CPU and a few thousand synthetic frames): AdamW,
quadratic warm-up then cosine to 5 %, weight decay on conv weights only, EMA of the weights
(the EMA is what is validated and exported), HSV + horizontal flip + random scale/translate
augmentation, the L1 box term switched on for the last 15 % of the epochs (as YOLOX does for
its last no-augmentation epochs). The epoch loop is :func:`~bopsurg.models.training.fit`;
this module brings the data, the augmented training step and the validation.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import cast

import numpy as np
import torch

from bopsurg.errors import BopsurgError
from bopsurg.models import training
from bopsurg.models.data import DetectionSet, load_detection_set
from bopsurg.models.detector import DetectorConfig, YoloxDetector, box_iou
from bopsurg.models.detector.augment import hsv_jitter, random_affine, random_flip

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DetectorRecipe:
    """Training hyper-parameters (recorded in the checkpoint)."""

    epochs: int = 24
    batch_size: int = 16
    lr: float = 2e-3
    weight_decay: float = 5e-4
    warmup_epochs: float = 1.0
    l1_fraction: float = 0.15
    scale: tuple[float, float] = (0.6, 1.4)
    translate: float = 0.1
    flip: float = 0.5
    min_visib: float = 0.1
    val_every: int = 5

    def schedule(self) -> training.Schedule:
        """What the epoch loop reads; the cosine starts right after the warm-up (YOLOX)."""
        return training.Schedule(
            self.epochs, self.batch_size, self.lr, self.weight_decay, self.warmup_epochs,
            0.0, self.val_every,
        )  # fmt: skip


@torch.no_grad()
def validate(model: YoloxDetector, data: DetectionSet, device: torch.device) -> dict[str, float]:
    """Top-1 box per GT instance: recall at IoU 0.5 and mean IoU; false positives = images
    without GT where the best score is >= 0.3."""
    if len(data) == 0:
        return {}
    model.eval()
    ious, fps, negatives = [], 0, 0
    for idx in torch.split(torch.arange(len(data)), 32):
        images = data.images[idx].to(device).float() / 255
        dets = model.detect(images, conf_thr=0.001)
        for i, det in zip(idx.tolist(), dets, strict=True):
            gt = data.targets[i]
            if len(gt) == 0:
                negatives += 1
                fps += int(len(det) > 0 and float(det[0, 4]) >= 0.3)
                continue
            for g in gt:
                same = det[det[:, 5] == g[0]]
                iou = box_iou(g[None, 1:].to(det), same[:1, :4]) if len(same) else None
                ious.append(0.0 if iou is None else float(iou.max()))
    a = np.array(ious)
    out = {"recall50": float((a >= 0.5).mean()) if len(a) else math.nan}
    out["recall75"] = float((a >= 0.75).mean()) if len(a) else math.nan
    out["mean_iou"] = float(a.mean()) if len(a) else math.nan
    if negatives:
        out["false_pos_rate"] = fps / negatives
    return out


def train_detector(
    dataset: str | Path,
    out: str | Path,
    *,
    split: str = "train",
    val_split: str | None = None,
    preset: str = "cpu",
    recipe: DetectorRecipe | None = None,
    seed: int = 0,
    device: str = "auto",
    restart: bool = False,
    progress: bool = True,
    max_images: int | None = None,
    obj_ids: Sequence[int] | None = None,
) -> Path:
    """Train (or resume) a detector run in ``out``; returns the exported ``detector.pt``.

    Args:
        dataset: BOP dataset root.
        out: Run folder (created; resumed when it holds a run with the same settings).
        split: Training split.
        val_split: Validation split; None = hold out every 10th scene of ``split``.
        preset: :meth:`DetectorConfig.preset` name (``cpu``, ``tiny``, ``s``, ``test``).
        recipe: Hyper-parameters (default :class:`DetectorRecipe`).
        seed: Seed of every random choice.
        device: ``auto``, ``cpu``, ``cuda`` ...
        restart: Discard a previous run in ``out``.
        progress: Show progress bars.
        max_images: Use only the first N training images (smoke tests).
        obj_ids: Objects to detect, one class each; None = the dataset's first object.
    """
    recipe = recipe or DetectorRecipe()
    dev = training.resolve_device(device)
    splits = training.open_splits(dataset, split, val_split)
    ds = splits.train
    classes = tuple(obj_ids) if obj_ids else tuple(ds.obj_ids[:1])
    unknown = sorted(set(classes) - set(ds.obj_ids))
    if unknown:
        raise BopsurgError(f"--obj-ids: {unknown} not among the dataset's objects {ds.obj_ids}")
    cfg = DetectorConfig.preset(preset, num_classes=len(classes))
    settings = training.RunSettings(
        "detector", str(Path(dataset).resolve()), split, preset, seed, asdict(recipe),
        {"val_split": val_split, "max_images": max_images, "classes": list(classes)},
    )  # fmt: skip
    run, state = training.open_run(out, settings, restart=restart)
    train = load_detection_set(
        ds, splits.train_ids, cfg.input_hw, classes, min_visib=recipe.min_visib, progress=progress
    )
    if max_images is not None:
        train = DetectionSet(
            train.images[:max_images], train.targets[:max_images], train.keys[:max_images],
            train.scales[:max_images], train.classes,
        )  # fmt: skip
    val = load_detection_set(
        splits.val, splits.val_ids, cfg.input_hw, classes, min_visib=recipe.min_visib,
        progress=progress,
    )  # fmt: skip
    log.info("detector: %d train images, %d validation images", len(train), len(val))
    model = YoloxDetector(cfg).to(dev)
    meta = {"classes": list(classes)}
    export = training.Export(Path(out) / "detector.pt", "detector", cfg.to_dict(), meta)
    step = _step_fn(model, train, recipe, dev)
    return training.fit(
        model, run, state, recipe.schedule(), n_train=len(train), step=step,
        validate=lambda ema: validate(cast(YoloxDetector, ema), val, dev), export=export,
        device=dev, progress=progress,
    )  # fmt: skip


def _step_fn(
    model: YoloxDetector, train: DetectionSet, recipe: DetectorRecipe, dev: torch.device
) -> training.StepFn:
    """The detector's training step: augment a batch (HSV, flip, scale/translate), YOLOX
    losses with the L1 box term from epoch ``l1_from`` on."""
    l1_from = math.ceil(recipe.epochs * (1 - recipe.l1_fraction))

    def step(idx: torch.Tensor, gen: torch.Generator, epoch: int) -> dict[str, torch.Tensor]:
        images = train.images[idx].to(dev).float() / 255
        targets = [train.targets[i].to(dev) for i in idx.tolist()]
        images = hsv_jitter(images, gen)
        images, targets = random_flip(images, targets, gen, p=recipe.flip)
        images, targets = random_affine(
            images, targets, gen, scale=recipe.scale, translate=recipe.translate
        )
        return model.loss(model(images), targets, use_l1=epoch >= l1_from)

    return step
