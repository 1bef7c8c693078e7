"""Train the needle segmenter (:mod:`.seghead`) on a BOP split's visible (and full) masks.

    bopsurg train seg DATASET --out runs/seg --seed 0 [--config bopsurg/recipes/seg.yaml]

Per GT needle instance (visib_fract >= ``recipe.min_visib``) a native-resolution context
around its visible box (with ``seg.frame: whole``: that box grown to the full mask's box, the
whole needle; 2.5 × the box's longer side, zero-padded, no resampling) is cut with its visible
mask (and, for an ``amodal`` segmenter, its full mask) from the files on disk when a batch
needs it (only the index of instances is kept in memory, and decoded contexts in the loader's
cache). Each step jitters the crop of each drawn instance as the pose head does (Dynamic
Zoom-In: side × U(0.75, 1.25), centre ± 0.25 box), cuts the RGB and the masks with the same
bilinear ``grid_sample`` the estimator uses at test time, adds colour jitter and flips (and,
when configured, a hue shift and the photometric set), and minimises BCE + Dice per mask (the
bilinear crop makes each the covered fraction of each grid pixel).

The epoch loop is :func:`~bopsurg.models.training.fit` (AdamW, warm-up + cosine, EMA,
resume, validation: the masks' IoU on the held-out scenes' test-time crops). The run is
counted in steps: ``recipe.epochs × recipe.steps_per_epoch``, each epoch drawing its
instances from shuffles of the training set. Writes OUT/needle_seg.pt (the EMA weights,
float16) and its JSON (config, the needle arc from models_info, recipe, provenance).
``recipe.init`` starts from another segmenter's weights (a one-channel one gives its
visible-mask output to both channels of an amodal one; a stage ``stages: 4`` adds starts
afresh), to fine-tune rather than train from scratch.
"""

from __future__ import annotations

import logging
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_mask, load_rgb
from bopsurg.bop.scene import bbox_from_mask
from bopsurg.errors import BopsurgError
from bopsurg.models import training
from bopsurg.models.checkpoint import load_checkpoint, load_weights
from bopsurg.models.data import (
    CONTEXT_RATIO,
    MIB,
    BatchReader,
    InstanceRecord,
    LruCache,
    list_instances,
)
from bopsurg.models.detector.augment import hsv_jitter
from bopsurg.models.photometric import PhotometricConfig, augment_batch, batch_seeds
from bopsurg.models.pose.roi import crop, dzi_boxes
from bopsurg.models.refine.arc import dataset_arc
from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig, seg_loss
from bopsurg.models.run_config import LoaderConfig, resolved, write_config

log = logging.getLogger(__name__)

#: Model presets of ``bopsurg train seg --preset``: ``cpu`` the default segmenter (visible
#: mask, three stages), ``amodal`` the shipped layout (full mask too, four stages), ``test``
#: a tiny one for tests.
SEG_PRESETS: dict[str, SegConfig] = {
    "cpu": SegConfig(),
    "amodal": SegConfig(amodal=True, stages=4),
    "test": SegConfig(roi=64, width=4),
}


def seg_preset(name: str) -> SegConfig:
    """The segmenter config of a preset name (:data:`SEG_PRESETS`)."""
    if name not in SEG_PRESETS:
        raise ValueError(f"unknown seg preset {name!r} (presets: {', '.join(SEG_PRESETS)})")
    return SEG_PRESETS[name]


@dataclass(frozen=True)
class SegRecipe:
    """Training hyper-parameters (recorded in the checkpoint and the run folder).

    The defaults are those of the segmenter's former trainer (1,500 steps of 16 at 3e-3,
    warm-up over the first 5 %, AdamW decay 1e-4, no photometric set, no hue shift).
    """

    epochs: int = 10
    steps_per_epoch: int = 150
    batch_size: int = 16
    lr: float = 3e-3
    weight_decay: float = 1e-4
    warmup_epochs: float = 0.5
    val_every: int = 5
    min_visib: float = 0.1
    #: Amplitude (turns) of a hue shift per crop, U(-hue, hue); 0.5 spins the whole colour
    #: circle: the tissue's colour is not what tells the needle.
    hue: float = 0.0
    #: Share of the crops whose hue turns by any amount instead (the rest keep theirs).
    hue_whole: float = 0.0
    augment: PhotometricConfig = field(default_factory=PhotometricConfig)
    #: Segmenter checkpoint to start from (:func:`init_weights`); "" = random weights.
    init: str = ""
    #: ``fp32``, or ``bf16``: steps under ``torch.autocast`` in bfloat16 (a GPU's fast path;
    #: :attr:`~bopsurg.models.training.Schedule.precision`).
    precision: str = "fp32"

    def __post_init__(self) -> None:
        if self.precision not in training.PRECISIONS:
            raise ValueError(f"precision must be fp32 or bf16, got {self.precision!r}")
        if not 0.0 <= self.hue <= 0.5:
            raise ValueError(f"hue must lie in [0, 0.5] turns, got {self.hue}")
        if not 0.0 <= self.hue_whole <= 1.0:
            raise ValueError(f"hue_whole is a share of the crops, in [0, 1], got {self.hue_whole}")
        if self.steps_per_epoch < 1:
            raise ValueError(f"steps_per_epoch must be >= 1, got {self.steps_per_epoch}")

    def schedule(self) -> training.Schedule:
        """What the epoch loop reads; the cosine starts right after the warm-up."""
        return training.Schedule(
            self.epochs, self.batch_size, self.lr, self.weight_decay, self.warmup_epochs,
            0.0, self.val_every, self.steps_per_epoch, self.precision,
        )  # fmt: skip


#: One context: RGB (s, s, 3) uint8, masks (s, s, C) uint8 (visible, then full), visible box
#: (4,) in context px.
Context = tuple[np.ndarray, np.ndarray, np.ndarray]


class ContextSet(Dataset[Context]):
    """The contexts of GT instances, cut from their images on demand and kept in an LRU
    cache of ``cache_mb`` MiB (0: none; memory does not grow with the dataset).

    Args:
        dataset: The split.
        records: The instances.
        amodal: Also cut the full (amodal) mask, as the masks' second channel.
        whole: Frame the visible box grown to the full mask's box (needs ``amodal``), as
            :attr:`SegConfig.frame` ``"whole"`` does at test time.
        cache_mb: Cache budget, MiB per process.
    """

    def __init__(
        self,
        dataset: BopDataset,
        records: list[InstanceRecord],
        amodal: bool = False,
        whole: bool = False,
        cache_mb: float = 0,
    ) -> None:
        if whole and not amodal:
            raise ValueError("whole-needle contexts need the full (amodal) mask: set amodal")
        self.dataset, self.records, self.amodal, self.whole = dataset, records, amodal, whole
        self.cache: LruCache[Context] = LruCache(int(cache_mb * MIB))

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, i: int) -> Context:
        if not 0 <= i < len(self.records):  # ends iteration (the sequence protocol)
            raise IndexError(i)
        ctx: Context = self.cache.get(i, lambda: self._read(i))
        return ctx

    def _read(self, i: int) -> Context:
        r = self.records[i]
        scene = self.dataset.scene(r.scene_id)
        rgb = load_rgb(scene.rgb_path(r.im_id))
        paths = [scene.mask_visib_path(r.im_id, r.gt_id)]
        if self.amodal:
            paths.append(scene.mask_path(r.im_id, r.gt_id))
        mask = np.stack([load_mask(p).astype(np.uint8) for p in paths], axis=-1)
        x, y, w, h = r.bbox_visib
        if self.whole:  # the full mask is channel 1
            fx, fy, fw, fh = bbox_from_mask(mask[..., 1])
            if fw >= 0:  # not empty
                x0, y0 = min(x, fx), min(y, fy)
                x1, y1 = max(x + w, fx + fw), max(y + h, fy + fh)
                x, y, w, h = x0, y0, x1 - x0, y1 - y0
        s = math.ceil(CONTEXT_RATIO * max(w, h, 1))
        x0, y0 = round(x + w / 2 - s / 2), round(y + h / 2 - s / 2)
        H, W = mask.shape[:2]
        ctx_rgb = np.zeros((s, s, 3), np.uint8)
        ctx_mask = np.zeros((s, s, mask.shape[2]), np.uint8)
        sx, sy = max(x0, 0), max(y0, 0)
        ex, ey = min(x0 + s, W), min(y0 + s, H)
        if ex > sx and ey > sy:
            ctx_rgb[sy - y0 : ey - y0, sx - x0 : ex - x0] = rgb[sy:ey, sx:ex]
            ctx_mask[sy - y0 : ey - y0, sx - x0 : ex - x0] = mask[sy:ey, sx:ex]
        return ctx_rgb, ctx_mask, np.array([x - x0, y - y0, w, h], np.float32)


@dataclass
class ContextBatch:
    """A batch of :class:`ContextSet`: the sample indices (B,) and their contexts (their
    sizes differ, so they stay a list)."""

    idx: torch.Tensor
    items: list[Context]


def collate_contexts(samples: list[Context], idx: list[int]) -> ContextBatch:
    """The batch of ``samples`` (what :class:`~bopsurg.models.data.BatchReader` yields)."""
    return ContextBatch(torch.tensor(idx, dtype=torch.int64), samples)


def load_contexts(
    dataset: BopDataset,
    scene_ids: list[int],
    obj_id: int,
    amodal: bool = False,
    whole: bool = False,
    *,
    min_visib: float = 0.1,
    cache_mb: float = 0,
) -> ContextSet:
    """The instances of ``obj_id`` (visib_fract >= ``min_visib``) of ``scene_ids``; each item
    is (RGB (s, s, 3) uint8, masks (s, s, C) uint8, box (4,) in context px), read when
    indexed."""
    per_image = list_instances(dataset, scene_ids, obj_ids=[obj_id], min_visib=min_visib)
    records = [r for rs in per_image.values() for r in rs]
    return ContextSet(dataset, records, amodal, whole, cache_mb)


def crops(
    items: Sequence[Context], cfg: SegConfig, gen: torch.Generator | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Crops (B, 3, S, S) in [0, 1] and soft masks (B, C, S, S) of ``items``: DZI-jittered
    with ``gen``, the test-time crop (``pad`` × the box) without."""
    xs, ys = [], []
    for rgb, mask, box in items:  # contexts differ in size: one grid_sample each
        img = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
        m = torch.from_numpy(mask).permute(2, 0, 1)[None].float()
        b = torch.from_numpy(box)[None]
        b = torch.cat([b[:, :2] - 0.5, b[:, 2:]], 1)  # pixel-centre convention, as at test
        hw = (int(rgb.shape[0]), int(rgb.shape[1]))
        centre, side = dzi_boxes(b, gen, (0.25, 0.25, cfg.pad), hw)
        xs.append(crop(img, centre, side, cfg.roi, "bilinear"))
        ys.append(crop(m, centre, side, cfg.roi, "bilinear"))
    return torch.cat(xs), torch.cat(ys)


def make_batch(
    items: Sequence[Context], cfg: SegConfig, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Jittered crops (B, 3, S, S) in [0, 1] and soft masks (B, C, S, S) of ``items``, with
    a brightness and colour jitter and horizontal and vertical flips."""
    x, y = crops(items, cfg, gen)
    n = len(x)
    u = torch.rand((n, 4), generator=gen)
    gain = 1.0 + 0.4 * (u[:, :1] - 0.5)  # brightness
    tint = 1.0 + 0.1 * (torch.rand((n, 3), generator=gen) - 0.5)  # per-channel colour
    x = (x * gain[:, :, None, None] * tint[:, :, None, None]).clamp(0, 1)
    flip = u[:, 1] < 0.5
    x[flip], y[flip] = x[flip].flip(-1), y[flip].flip(-1)
    vflip = u[:, 2] < 0.5
    x[vflip], y[vflip] = x[vflip].flip(-2), y[vflip].flip(-2)
    return x, y


def init_weights(net: NeedleSegNet, path: str | Path) -> None:
    """Load the weights of the segmenter checkpoint ``path`` into ``net``, whose config may
    add the amodal channel (a one-channel checkpoint's output layer then initialises both:
    the full mask starts as the visible one) or a stride-2 stage (its layers start afresh);
    everything else must match."""
    state, info = load_checkpoint(path, "needle_seg")
    mine = net.state_dict()
    for key in ("out.weight", "out.bias"):
        if key in state and state[key].shape[0] == 1 and mine[key].shape[0] > 1:
            state[key] = state[key].repeat(mine[key].shape[0], *[1] * (mine[key].dim() - 1))
    added = range(int(info["config"].get("stages", 3)) + 1, net.cfg.stages + 1)
    new = tuple(f"enc{k}." for k in added) + tuple(f"dec{k - 1}." for k in added)
    state |= {k: v for k, v in mine.items() if k.startswith(new) and k not in state}
    load_weights(net, state, path)


@torch.no_grad()
def validate(
    net: torch.nn.Module, data: ContextSet, cfg: SegConfig, device: torch.device
) -> dict[str, float]:
    """IoU of the predicted masks (probability > 0.5) with the targets (covered > 0.5) on
    the test-time crops, pooled over the set: ``iou_visib`` and, amodal, ``iou_full``."""
    if len(data) == 0:
        return {}
    net.eval()
    inter = union = torch.zeros(cfg.channels)
    for batch in BatchReader(data, collate_contexts).all(32):
        x, y = crops(batch.items, cfg, None)
        pred = net(x.to(device)).sigmoid().cpu() > 0.5
        truth = y > 0.5
        inter = inter + (pred & truth).sum((0, 2, 3))
        union = union + (pred | truth).sum((0, 2, 3))
    iou = (inter / union.clamp_min(1)).tolist()
    return {"iou_visib": iou[0], **({"iou_full": iou[1]} if cfg.amodal else {})}


def _step_fn(
    net: NeedleSegNet, cfg: SegConfig, recipe: SegRecipe, dev: torch.device, seed: int
) -> training.StepFn:
    """The segmenter's step: jittered crops of a batch, the photometric set (seeded per
    sample) and hue shift when configured, BCE + Dice."""

    def step(batch: ContextBatch, gen: torch.Generator, epoch: int) -> dict[str, torch.Tensor]:
        x, y = make_batch(batch.items, cfg, gen)
        x = augment_batch(x, recipe.augment, batch_seeds(seed, epoch, batch.idx))
        if recipe.hue > 0 or recipe.hue_whole > 0:
            x = hsv_jitter(x, gen, recipe.hue, 0.0, 0.0, whole=recipe.hue_whole)
        return {"total": seg_loss(net(x.to(dev)).float(), y.to(dev))}  # the loss in fp32

    return step


def train_seg(
    dataset: str | Path,
    out: str | Path,
    *,
    split: str = "train",
    val_split: str | None = None,
    obj_id: int | None = None,
    preset: str = "cpu",
    recipe: SegRecipe | None = None,
    seed: int = 0,
    device: str = "auto",
    restart: bool = False,
    progress: bool = True,
    config: SegConfig | None = None,
    loader: LoaderConfig | None = None,
) -> Path:
    """Train (or resume) a segmenter run in ``out``; returns the exported ``needle_seg.pt``.

    Args as :func:`bopsurg.models.train_pose.train_pose`: ``obj_id`` the needle (default:
    the dataset's first object), ``config`` the network (default: the preset's).
    """
    recipe, loader = recipe or SegRecipe(), loader or LoaderConfig()
    cfg = config or seg_preset(preset)
    dev = training.resolve_device(device)
    splits = training.open_splits(dataset, split, val_split)
    obj_id = splits.train.obj_ids[0] if obj_id is None else obj_id
    arc = dataset_arc(splits.train, obj_id)
    settings = training.RunSettings(
        "needle_seg", str(Path(dataset).resolve()), split, preset, seed, asdict(recipe),
        {"val_split": val_split, "obj_id": obj_id}, cfg.to_dict(),
    )  # fmt: skip
    run, state = training.open_run(out, settings, restart=restart)
    weights = Path(out) / "needle_seg.pt"
    if training.finished(run, state, weights):
        return weights
    write_config(out, resolved("seg", preset, seed, cfg, recipe, loader))
    whole = cfg.frame == "whole"
    sets = [
        load_contexts(splits.train if k == 0 else splits.val, ids, obj_id, cfg.amodal, whole,
                      min_visib=recipe.min_visib, cache_mb=loader.cache_mb)
        for k, ids in enumerate((splits.train_ids, splits.val_ids))
    ]  # fmt: skip
    train, val = sets
    if len(train) == 0:
        raise BopsurgError(f"{dataset}: no instances of obj_id {obj_id} to train the segmenter on")
    log.info("needle_seg: %d train instances, %d validation instances", len(train), len(val))
    net = NeedleSegNet(cfg)
    if recipe.init and state is None:
        init_weights(net, recipe.init)
    net = net.to(dev)
    meta = {"arc": {"radius": arc.radius, "arc_rad": arc.arc_rad}, "instances": len(train)}
    export = training.Export(weights, "needle_seg", cfg.to_dict(), meta)
    path: Path = training.fit(
        net, run, state, recipe.schedule(), n_train=len(train),
        step=_step_fn(net, cfg, recipe, dev, seed),
        validate=lambda ema: validate(ema, val, cfg, dev), export=export, device=dev,
        progress=progress, load=BatchReader(train, collate_contexts, loader.num_workers),
    )  # fmt: skip
    return path


def main(argv: list[str] | None = None) -> int:
    """The former entry point: says where the trainer went."""
    del argv
    print(  # noqa: T201 (the CLI's one-line error)
        "error: python -m bopsurg.models.refine.train_seg is gone: use 'bopsurg train seg' "
        "(--steps N: --set recipe.steps_per_epoch=N --epochs 1; --batch: --batch-size; "
        "--amodal, --stages, --roi, --width, --frame: --set seg.KEY=VALUE; --init, --hue, "
        "--hue-whole: --set recipe.KEY=VALUE; --augment P: --set augment.preset=P)",
        file=sys.stderr,
    )
    return 2


if __name__ == "__main__":
    sys.exit(main())
