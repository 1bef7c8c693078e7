"""Train the YOLOX-like detector on the ``bbox_visib`` boxes of a BOP split.

Recipe (the YOLOX recipe scaled to a CPU and a few thousand synthetic frames): AdamW,
quadratic warm-up then cosine to 5 %, weight decay on conv weights only, EMA of the weights
(the EMA is what is validated and exported), HSV + horizontal flip + random scale/translate
augmentation, the L1 box term switched on for the last 15 % of the epochs (as YOLOX does for
its last no-augmentation epochs), and the optional photometric augmentations of
``recipe.augment`` (blur, noise, gamma, colour, JPEG; off by default) on the network input.
Images are read from disk per batch (:mod:`bopsurg.models.data`). The epoch loop is
:func:`~bopsurg.models.training.fit`; this module brings the data, the augmented training step
and the validation.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import cast

import numpy as np
import torch

from bopsurg.bop.dataset import BopDataset
from bopsurg.errors import BopsurgError
from bopsurg.models import training
from bopsurg.models.data import BatchReader, DetectionBatch, DetectionSet, load_detection_set
from bopsurg.models.detector import DetectorConfig, YoloxDetector, box_iou
from bopsurg.models.detector.augment import hsv_jitter, random_affine, random_flip
from bopsurg.models.detector.config import TRAINING_ONLY as DETECTOR_TRAINING_ONLY
from bopsurg.models.photometric import PhotometricConfig, augment_batch, batch_seeds
from bopsurg.models.run_config import LoaderConfig, resolved, write_config

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
    #: Amplitudes of the per-image HSV jitter (hue in turns, saturation and value gains;
    #: :func:`~bopsurg.models.detector.augment.hsv_jitter`). A hue of 0.5 spins the whole
    #: colour circle: tissue of any colour, for targets whose phantom is not ours.
    hsv: tuple[float, float, float] = (0.015, 0.7, 0.4)
    #: Share of the images whose hue turns by any amount instead of ``hsv[0]`` (ours kept).
    hue_whole: float = 0.0
    min_visib: float = 0.1
    val_every: int = 5
    augment: PhotometricConfig = field(default_factory=PhotometricConfig)
    #: Exported checkpoint (``NAME.pt``, same kind and config) the network starts from, to
    #: fine-tune it on new data; "" = random initialisation.
    init: str = ""
    #: ``fp32``, or ``bf16``: steps under ``torch.autocast`` in bfloat16 (a GPU's fast path;
    #: :attr:`~bopsurg.models.training.Schedule.precision`).
    precision: str = "fp32"
    #: Steps per epoch; 0: one pass over the training samples. More than a pass draws
    #: from consecutive shuffles (a small split trained for a fixed number of steps).
    steps_per_epoch: int = 0

    def __post_init__(self) -> None:
        if self.steps_per_epoch < 0:
            raise ValueError(f"steps_per_epoch must be >= 0, got {self.steps_per_epoch}")
        if self.precision not in training.PRECISIONS:
            raise ValueError(f"precision must be fp32 or bf16, got {self.precision!r}")
        if not 0.0 <= self.hue_whole <= 1.0:
            raise ValueError(f"hue_whole is a share of the images, in [0, 1], got {self.hue_whole}")

    def schedule(self) -> training.Schedule:
        """What the epoch loop reads; the cosine starts right after the warm-up (YOLOX)."""
        return training.Schedule(
            self.epochs, self.batch_size, self.lr, self.weight_decay, self.warmup_epochs,
            0.0, self.val_every, self.steps_per_epoch, self.precision,
        )  # fmt: skip


@torch.no_grad()
def validate(model: YoloxDetector, data: DetectionSet, device: torch.device) -> dict[str, float]:
    """Top-1 box per GT instance: recall at IoU 0.5 and mean IoU; false positives = images
    without GT where the best score is >= 0.3."""
    if len(data) == 0:
        return {}
    model.eval()
    ious, fps, negatives = [], 0, 0
    batch: DetectionBatch
    for batch in BatchReader(data, data.collate).all(32):
        images = batch.images.to(device).float() / 255
        dets = model.detect(images, conf_thr=0.001)
        for gt, det in zip(batch.targets, dets, strict=True):
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
    config: DetectorConfig | None = None,
    loader: LoaderConfig | None = None,
) -> Path:
    """Train (or resume) a detector run in ``out``; returns the exported ``detector.pt``.

    Args:
        dataset: BOP dataset root.
        out: Run folder (created; resumed when it holds a run with the same settings).
        split: Training split.
        val_split: Validation split; None = hold out one scene in 10 of ``split`` (seeded).
        preset: :meth:`DetectorConfig.preset` name (``cpu``, ``tiny``, ``s``, ``test``).
        recipe: Hyper-parameters (default :class:`DetectorRecipe`).
        seed: Seed of every random choice.
        device: ``auto``, ``cpu``, ``cuda`` ...
        restart: Discard a previous run in ``out``.
        progress: Show progress bars.
        max_images: Use only the first N training images (smoke tests).
        obj_ids: Objects to detect, one class each; None = the dataset's first object.
        config: The network's config (default: the preset's); its ``num_classes`` must be
            the number of objects.
        loader: How images are read (workers, cache); does not change the result.
    """
    recipe = recipe or DetectorRecipe()
    loader = loader or LoaderConfig()
    dev = training.resolve_device(device)
    splits = training.open_splits(dataset, split, val_split)
    classes = _classes(splits.train, obj_ids)
    preset_cfg = DetectorConfig.preset(preset, num_classes=len(classes))
    cfg = _checked(preset_cfg if config is None else config, classes)
    settings = training.RunSettings(
        "detector", str(Path(dataset).resolve()), split, preset, seed, asdict(recipe),
        {"val_split": val_split, "max_images": max_images, "classes": list(classes)},
        cfg.to_dict(),
    )  # fmt: skip
    legacy = {"model": preset_cfg.to_dict(), "recipe": LEGACY_RECIPE}
    run, state = training.open_run(out, settings, restart=restart, legacy=legacy)
    weights = Path(out) / "detector.pt"
    if training.finished(run, state, weights):
        return weights
    write_config(out, resolved("detector", preset, seed, cfg, recipe, loader))
    train, val = (
        load_detection_set(
            ds, ids, cfg.input_hw, classes, min_visib=recipe.min_visib,
            cache_mb=loader.cache_mb, cache_items=loader.cache_items, shared=loader.shared_cache,
        )
        for ds, ids in ((splits.train, splits.train_ids), (splits.val, splits.val_ids))
    )  # fmt: skip
    if max_images is not None:
        train = train.head(max_images)
    log.info("detector: %d train images, %d validation images", len(train), len(val))
    model = YoloxDetector(cfg)
    meta = {"classes": list(classes)}
    if recipe.init and state is None:
        training.init_weights(
            model, recipe.init, "detector", cfg.to_dict(), meta, DETECTOR_TRAINING_ONLY
        )
    model = model.to(dev)
    export = training.Export(weights, "detector", cfg.to_dict(), meta)
    path: Path = training.fit(
        model, run, state, recipe.schedule(), n_train=len(train),
        step=_step_fn(model, recipe, dev, seed),
        validate=lambda ema: validate(cast(YoloxDetector, ema), val, dev),
        export=export, device=dev, progress=progress,
        load=BatchReader(
            train, train.collate, loader.num_workers, dev.type == "cuda", device=dev
        ),
    )  # fmt: skip
    return path


#: Recipe settings that runs written by an older bopsurg lack, at the value they had then.
LEGACY_RECIPE = {
    "augment": asdict(PhotometricConfig()),
    "precision": "fp32",
    "steps_per_epoch": 0,
    "init": "",
    "hsv": [0.015, 0.7, 0.4],
    "hue_whole": 0.0,
}


def _checked(cfg: DetectorConfig, classes: tuple[int, ...]) -> DetectorConfig:
    """``cfg``, checked to have a class per detected object."""
    if cfg.num_classes != len(classes):
        raise BopsurgError(
            f"the detector config has num_classes {cfg.num_classes} but {len(classes)} "
            f"object(s) are detected ({list(classes)}); set num_classes by --obj-ids"
        )
    return cfg


def _classes(ds: BopDataset, obj_ids: Sequence[int] | None) -> tuple[int, ...]:
    """The detected objects: ``obj_ids``, or the dataset's first object.

    Raises:
        BopsurgError: An object the dataset does not have.
    """
    classes = tuple(obj_ids) if obj_ids else tuple(ds.obj_ids[:1])
    unknown = sorted(set(classes) - set(ds.obj_ids))
    if unknown:
        raise BopsurgError(f"--obj-ids: {unknown} not among the dataset's objects {ds.obj_ids}")
    return classes


def _step_fn(
    model: YoloxDetector, recipe: DetectorRecipe, dev: torch.device, seed: int
) -> training.StepFn:
    """The detector's training step: augment a batch (HSV, flip, scale/translate, then the
    per-sample photometric set), YOLOX losses with the L1 box term from epoch ``l1_from`` on."""
    l1_from = math.ceil(recipe.epochs * (1 - recipe.l1_fraction))

    def step(batch: DetectionBatch, gen: torch.Generator, epoch: int) -> dict[str, torch.Tensor]:
        images = batch.images.to(dev, non_blocking=True).float() / 255
        counts = [len(t) for t in batch.targets]  # one copy to the device, not one per image
        flat = torch.cat(batch.targets).to(dev, non_blocking=True)
        targets = list(torch.split(flat, counts))
        images = hsv_jitter(images, gen, *recipe.hsv, whole=recipe.hue_whole)
        images, targets = random_flip(images, targets, gen, p=recipe.flip)
        images, targets = random_affine(
            images, targets, gen, scale=recipe.scale, translate=recipe.translate
        )
        images = augment_batch(images, recipe.augment, batch_seeds(seed, epoch, batch.idx))
        losses: dict[str, torch.Tensor] = model.loss(
            model(images), targets, use_l1=epoch >= l1_from
        )
        return losses

    return step
