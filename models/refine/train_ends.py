"""Train the needle-end classifier (:mod:`.ends`) on a BOP split's GT poses.

    bopsurg train ends DATASET --split train --out runs/ends --seed 0 \
        [--config bopsurg/recipes/robust_ends.yaml]

Per GT needle instance (visib_fract >= 0.3) the patches of its two ends are cut at the GT
pose, twice the side the classifier sees (so a jittered crop stays inside), and kept in
memory as uint8. An end whose projection is not on the visible mask (within 2 px: in the
jaws, in the tissue) gets the target 0.5, "cannot tell" (``recipe.unseen: false`` leaves it
out), so the end that is seen decides; one off the image is left out. Each step draws a batch
of ends and crops each at a random turn (±``recipe.turn_deg`` degrees), scale (×0.8–1.25)
and shift (±10 % of the side), as a pose estimate a few degrees and millimetres off would
frame it, flipped about its x axis half the time (the other face), then the whole hue circle
(``recipe.hsv``) and the ``domain`` photometric set (the ``augment`` section): the colours of
the tissue are not what tells a tip from a tail. Binary cross-entropy; the epoch loop is
:func:`~bopsurg.models.training.fit` (AdamW, warm-up + cosine, EMA, resume). Held-out scenes
of the split (the estimators' :func:`~bopsurg.models.data.split_scenes`) give the validation
accuracy on seen ends.

Writes OUT/needle_ends.pt (the EMA weights) and its JSON (config, the needle arc, recipe,
seed, accuracy, and ``recipe.margin``: the logit margin a swap needs when the estimator runs
this classifier without an ``ends.margin`` setting; choose it on validation splits with
``bench/bench_ends.py``, the smallest margin at which the classifier turns none of their
right poses).
"""

from __future__ import annotations

import logging
import math
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_mask, load_rgb
from bopsurg.errors import BopsurgError
from bopsurg.models import training
from bopsurg.models.data import InstanceRecord, list_instances
from bopsurg.models.detector.augment import hsv_jitter
from bopsurg.models.photometric import PhotometricConfig, augment_batch, batch_seeds
from bopsurg.models.refine.arc import ArcModel, dataset_arc
from bopsurg.models.refine.ends import TIP, EndConfig, EndNet, end_frames, sample_patches
from bopsurg.models.run_config import LoaderConfig, resolved, write_config

log = logging.getLogger(__name__)

#: An end counts as seen when the visible mask holds a pixel this close to its projection, px.
SEEN_PX = 2


def collect_ends(
    ds: BopDataset,
    scene_ids: list[int],
    obj_id: int,
    arc: ArcModel,
    cfg: EndConfig,
    *,
    max_instances: int | None = None,
    seed: int = 0,
    unseen: bool = True,
    progress: bool = True,
    allow_empty: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Patches (N, 3, 2P, 2P) uint8 of the ends of the instances (visib_fract >= 0.3) of
    ``scene_ids`` at their GT poses, and their targets (N,): 1 the tip, 0 the tail, and with
    ``unseen`` 0.5 for an end hidden in the image (in the jaws, in the tissue): the patch
    says nothing, so the classifier learns to say so (logit 0) and the other end decides.
    With ``max_instances``, that many instances drawn with ``seed``.

    Raises:
        BopsurgError: No end is seen in these scenes (unless ``allow_empty``: then empty
            tensors).
    """
    per_image = list_instances(ds, scene_ids, obj_ids=[obj_id], min_visib=0.3)
    records = [r for rs in per_image.values() for r in rs]
    if max_instances is not None and len(records) > max_instances:
        pick = np.random.default_rng(seed).choice(len(records), max_instances, replace=False)
        records = [records[i] for i in sorted(pick)]
    by_image: dict[tuple[int, int], list[InstanceRecord]] = {}
    for r in records:
        by_image.setdefault((r.scene_id, r.im_id), []).append(r)
    kernel = np.ones((2 * SEEN_PX + 1, 2 * SEEN_PX + 1), np.uint8)
    patches, labels = [], []
    for (sid, im_id), rs in tqdm(by_image.items(), desc="ends", disable=not progress):
        scene = ds.scene(sid)
        rgb = load_rgb(scene.rgb_path(im_id))
        for r in rs:
            uv, axis, side = end_frames(r.K, r.R[None], r.t[None], arc, cfg)
            mask = load_mask(scene.mask_visib_path(im_id, r.gt_id)).astype(np.uint8)
            seen = cv2.dilate(mask, kernel)
            for end in range(2):
                u, v = uv[0, end]
                if not (np.isfinite(u) and np.isfinite(v) and np.isfinite(side[0, end])):
                    continue
                iu, iv = round(u), round(v)
                if not (0 <= iv < seen.shape[0] and 0 <= iu < seen.shape[1]):
                    continue  # off the image: nothing to learn from
                if not (seen[iv, iu] or unseen):
                    continue
                patches.append(
                    _cut(rgb, uv[0, end], axis[0, end], 2.0 * side[0, end], 2 * cfg.patch)
                )
                labels.append(float(end == TIP) if seen[iv, iu] else 0.5)
    if not patches and allow_empty:
        side = 2 * cfg.patch
        return torch.zeros((0, 3, side, side), dtype=torch.uint8), torch.zeros(0)
    if not patches:
        raise BopsurgError(f"{ds.split_dir}: no needle end is seen in the GT of these scenes")
    return torch.from_numpy(np.stack(patches)), torch.tensor(labels)


def _cut(
    rgb: np.ndarray, centre: np.ndarray, axis: np.ndarray, side: float, size: int
) -> np.ndarray:
    """One patch (3, size, size) uint8 of an (H, W, 3) uint8 image, as
    :func:`~.ends.sample_patches` cuts it at test time, from only the window it covers (a
    whole float image per end fragments the heap: gigabytes over a training set)."""
    h, w = rgb.shape[:2]
    r = math.ceil(side * math.sqrt(0.5)) + 2  # the patch's half diagonal, and a margin
    u, v = math.floor(centre[0]), math.floor(centre[1])
    x0, x1, y0, y1 = max(u - r, 0), min(u + r + 1, w), max(v - r, 0), min(v + r + 1, h)
    win = torch.from_numpy(np.ascontiguousarray(rgb[y0:y1, x0:x1])).permute(2, 0, 1)[None].float()
    p = sample_patches(
        win,
        torch.tensor([[centre[0] - x0, centre[1] - y0]], dtype=torch.float32),
        torch.from_numpy(np.asarray(axis, np.float32).reshape(1, 2)),
        torch.tensor([side], dtype=torch.float32),
        size,
    )
    out: np.ndarray = p[0].round().clamp(0, 255).to(torch.uint8).numpy()
    return out


def jittered(
    patches: torch.Tensor, gen: torch.Generator, patch: int, turn_deg: float
) -> torch.Tensor:
    """Crops (B, 3, P, P) in [0, 1] of stored patches (B, 3, 2P, 2P) uint8: the central half
    turned, scaled and shifted at random, flipped about the x axis half the time."""
    b = len(patches)
    u = torch.rand((b, 5), generator=gen)
    ang = torch.deg2rad((2 * u[:, 0] - 1) * turn_deg)
    scale = 0.5 * torch.exp((2 * u[:, 1] - 1) * math.log(1.25))  # of the stored side
    shift = 0.1 * (2 * u[:, 2:4] - 1)  # of the stored side's half-extent units below
    flip = torch.where(u[:, 4] < 0.5, -1.0, 1.0)
    cos, sin = torch.cos(ang) * scale, torch.sin(ang) * scale
    theta = torch.stack(
        [
            torch.stack([cos, -sin * flip, shift[:, 0]], 1),
            torch.stack([sin, cos * flip, shift[:, 1]], 1),
        ],
        1,
    )
    grid = F.affine_grid(theta, [b, 3, patch, patch], align_corners=False)
    return F.grid_sample(patches.float() / 255, grid, mode="bilinear", align_corners=False)


def accuracy(net: EndNet, patches: torch.Tensor, labels: torch.Tensor, patch: int) -> float:
    """Share of the seen ends (targets 0 and 1) classified right on their central crops (no
    jitter)."""
    keep = labels != 0.5
    patches, labels = patches[keep], labels[keep]
    if len(patches) == 0:
        return float("nan")
    was_training = net.training
    net.eval()
    c = patch // 2
    dev = next(net.parameters()).device
    with torch.inference_mode():
        x = patches[:, :, c : c + patch, c : c + patch].float() / 255
        pred = torch.cat([net(x[i : i + 512].to(dev)).cpu() for i in range(0, len(x), 512)]) > 0
    net.train(was_training)
    return float((pred == labels.bool()).float().mean())


#: Model presets of ``bopsurg train ends --preset``: ``cpu`` the shipped classifier's
#: layout, ``test`` a tiny one for tests.
ENDS_PRESETS: dict[str, EndConfig] = {"cpu": EndConfig(), "test": EndConfig(patch=16, width=8)}


def ends_preset(name: str) -> EndConfig:
    """The classifier config of a preset name (:data:`ENDS_PRESETS`)."""
    if name not in ENDS_PRESETS:
        raise ValueError(f"unknown ends preset {name!r} (presets: {', '.join(ENDS_PRESETS)})")
    return ENDS_PRESETS[name]


def _domain() -> PhotometricConfig:
    return PhotometricConfig(**PhotometricConfig.preset_values("domain"))


@dataclass(frozen=True)
class EndsRecipe:
    """Training hyper-parameters (recorded in the checkpoint and the run folder).

    The defaults are those of the classifier's former trainer (3,000 steps of 128 ends at
    3e-3, warm-up over the first 5 %, AdamW decay 1e-4, the whole hue circle and the
    ``domain`` photometric set).
    """

    epochs: int = 10
    steps_per_epoch: int = 300
    batch_size: int = 128
    lr: float = 3e-3
    weight_decay: float = 1e-4
    warmup_epochs: float = 0.5
    val_every: int = 5
    #: Largest turn of a patch about its centre, degrees.
    turn_deg: float = 15.0
    #: Amplitudes of the per-patch HSV jitter (hue in turns: 0.5 the whole circle).
    hsv: tuple[float, float, float] = (0.5, 0.5, 0.4)
    #: Draw this many GT needles (seeded); None: all.
    max_instances: int | None = None
    #: Teach the hidden ends as "cannot tell" (target 0.5); False leaves them out.
    unseen: bool = True
    #: Logit margin a swap needs, recorded as the classifier's default (``bench_ends.py``).
    margin: float = 0.0
    augment: PhotometricConfig = field(default_factory=_domain)
    #: Exported ``needle_ends`` checkpoint (same config) to start from; "" = random weights.
    init: str = ""
    #: ``fp32``, or ``bf16``: steps under ``torch.autocast`` in bfloat16 (a GPU's fast path;
    #: :attr:`~bopsurg.models.training.Schedule.precision`).
    precision: str = "fp32"

    def __post_init__(self) -> None:
        if self.precision not in training.PRECISIONS:
            raise ValueError(f"precision must be fp32 or bf16, got {self.precision!r}")
        if not math.isfinite(self.margin):
            raise ValueError(f"margin must be a finite logit margin, got {self.margin}")
        if self.steps_per_epoch < 1:
            raise ValueError(f"steps_per_epoch must be >= 1, got {self.steps_per_epoch}")
        if self.max_instances is not None and (
            isinstance(self.max_instances, bool)
            or not isinstance(self.max_instances, int)
            or self.max_instances < 1
        ):
            raise ValueError(f"max_instances must be null or >= 1, got {self.max_instances!r}")

    def schedule(self) -> training.Schedule:
        """What the epoch loop reads; the cosine starts right after the warm-up."""
        return training.Schedule(
            self.epochs, self.batch_size, self.lr, self.weight_decay, self.warmup_epochs,
            0.0, self.val_every, self.steps_per_epoch, self.precision,
        )  # fmt: skip


def _step_fn(
    net: EndNet,
    patches: torch.Tensor,
    labels: torch.Tensor,
    cfg: EndConfig,
    recipe: EndsRecipe,
    dev: torch.device,
    seed: int,
) -> training.StepFn:
    """The classifier's step: jittered crops of the drawn ends, colour, BCE."""

    def step(idx: torch.Tensor, gen: torch.Generator, epoch: int) -> dict[str, torch.Tensor]:
        x = jittered(patches[idx], gen, cfg.patch, recipe.turn_deg)
        x = hsv_jitter(x, gen, *recipe.hsv)
        x = augment_batch(x, recipe.augment, batch_seeds(seed, epoch, idx))
        logits = net(x.to(dev)).float()  # the loss in fp32, also under bf16 autocast
        loss = F.binary_cross_entropy_with_logits(logits, labels[idx].to(dev))
        return {"total": loss}

    return step


def _ends(
    splits: training.Splits, obj_id: int, arc: ArcModel, cfg: EndConfig, recipe: EndsRecipe,
    seed: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """Training patches and targets, then validation ones (seen ends only; a tenth as many
    instances as ``recipe.max_instances``)."""
    x_tr, y_tr = collect_ends(
        splits.train, splits.train_ids, obj_id, arc, cfg, max_instances=recipe.max_instances,
        seed=seed, unseen=recipe.unseen, progress=False,
    )  # fmt: skip
    n_val = None if recipe.max_instances is None else max(1, recipe.max_instances // 10)
    x_va, y_va = collect_ends(
        splits.val, splits.val_ids, obj_id, arc, cfg, max_instances=n_val, seed=seed + 1,
        unseen=False, progress=False, allow_empty=True,
    )  # fmt: skip
    log.info(
        "needle_ends: %d training ends (%.0f %% tips, %.0f %% hidden), %d validation",
        len(x_tr), 100 * (y_tr == 1).float().mean(), 100 * (y_tr == 0.5).float().mean(), len(x_va),
    )  # fmt: skip
    return x_tr, y_tr, x_va, y_va


def train_ends(
    dataset: str | Path,
    out: str | Path,
    *,
    split: str = "train",
    val_split: str | None = None,
    obj_id: int | None = None,
    preset: str = "cpu",
    recipe: EndsRecipe | None = None,
    seed: int = 0,
    device: str = "auto",
    restart: bool = False,
    progress: bool = True,
    config: EndConfig | None = None,
    loader: LoaderConfig | None = None,
) -> Path:
    """Train (or resume) an end-classifier run in ``out``; returns ``needle_ends.pt``.

    Args as :func:`bopsurg.models.train_pose.train_pose`: ``obj_id`` the needle (default:
    the dataset's first object), ``config`` the network (default: the preset's); the ends
    are held in memory, so ``loader`` only goes into the written configuration.
    """
    recipe, loader = recipe or EndsRecipe(), loader or LoaderConfig()
    cfg = config or ends_preset(preset)
    dev = training.resolve_device(device)
    splits = training.open_splits(dataset, split, val_split)
    obj_id = splits.train.obj_ids[0] if obj_id is None else obj_id
    arc = dataset_arc(splits.train, obj_id)
    settings = training.RunSettings(
        "needle_ends", str(Path(dataset).resolve()), split, preset, seed, asdict(recipe),
        {"val_split": val_split, "obj_id": obj_id}, cfg.to_dict(),
    )  # fmt: skip
    run, state = training.open_run(out, settings, restart=restart)
    weights = Path(out) / "needle_ends.pt"
    if training.finished(run, state, weights):
        return weights
    write_config(out, resolved("ends", preset, seed, cfg, recipe, loader))
    x_tr, y_tr, x_va, y_va = _ends(splits, obj_id, arc, cfg, recipe, seed)
    n_val = len(x_va)
    net = EndNet(cfg)
    if recipe.init and state is None:
        training.init_weights(net, recipe.init, "needle_ends", cfg.to_dict())
    net = net.to(dev)
    meta: dict[str, Any] = {
        "arc": {"radius": arc.radius, "arc_rad": arc.arc_rad},
        "ends": len(x_tr), "val_ends": int((y_va != 0.5).sum()), "margin": recipe.margin,
    }  # fmt: skip
    export = training.Export(weights, "needle_ends", cfg.to_dict(), meta)
    path: Path = training.fit(
        net, run, state, recipe.schedule(), n_train=len(x_tr),
        step=_step_fn(net, x_tr, y_tr, cfg, recipe, dev, seed),
        validate=lambda ema: {"accuracy": accuracy(ema, x_va, y_va, cfg.patch)} if n_val else {},
        export=export, device=dev, progress=progress,
    )  # fmt: skip
    return path


def main(argv: list[str] | None = None) -> int:
    """The former entry point: says where the trainer went."""
    del argv
    print(  # noqa: T201 (the CLI's one-line error)
        "error: python -m bopsurg.models.refine.train_ends is gone: use 'bopsurg train ends' "
        "(--steps N: --set recipe.steps_per_epoch=N --epochs 1; --batch: --batch-size; "
        "--turn, --max-instances, --margin: --set recipe.turn_deg=, recipe.max_instances=, "
        "recipe.margin=; --seen-only: --set recipe.unseen=false; --patch, --scale: "
        "--set ends.patch=, ends.scale=)",
        file=sys.stderr,
    )
    return 2


if __name__ == "__main__":
    sys.exit(main())
