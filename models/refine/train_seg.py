"""Train the needle segmenter (:mod:`.seghead`) on a BOP split's visible (and full) masks.

    python -m bopsurg.models.refine.train_seg DATASET --out runs/seg --steps 1500 --seed 0

Per GT needle instance (visib_fract >= 0.1) a native-resolution context around its visible box
(with ``--frame whole``: that box grown to the full mask's box, the whole needle; 2.5 × the
box's longer side, zero-padded, no resampling) is cut with its visible mask (and,
for an ``--amodal`` segmenter, its full mask) from the files on disk when a batch needs it
(only the index of instances is kept in memory). Each step draws a batch, jitters the crop as
the pose head does (Dynamic Zoom-In: side × U(0.75, 1.25), centre ± 0.25 box), cuts the RGB
and the masks with the same bilinear ``grid_sample`` the estimator uses at test time, adds
colour jitter and flips, and minimises BCE + Dice per mask (the bilinear crop makes each the
covered fraction of each grid pixel). AdamW with warm-up and cosine decay; deterministic for
a seed. Writes OUT/needle_seg.pt (float16) and its JSON (config, the needle arc from
models_info, recipe, seed, time). ``--init`` starts from another segmenter's weights (a
one-channel one gives its visible-mask output to both channels of an amodal one; a stage
``--stages 4`` adds starts afresh), to fine-tune rather than train from scratch.

The loop is its own here; it should move onto the common epoch loop of ``models/training.py``.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import overload

import numpy as np
import torch
from tqdm import tqdm

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_mask, load_rgb
from bopsurg.bop.scene import bbox_from_mask
from bopsurg.errors import BopsurgError
from bopsurg.models.checkpoint import load_checkpoint, load_weights, save_checkpoint
from bopsurg.models.data import (
    CONTEXT_RATIO,
    InstanceRecord,
    list_instances,
    open_split,
    split_scenes,
)
from bopsurg.models.detector.augment import hsv_jitter
from bopsurg.models.photometric import PhotometricConfig, augment_batch, batch_seeds
from bopsurg.models.pose.roi import crop, dzi_boxes
from bopsurg.models.refine.arc import dataset_arc
from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig, seg_loss
from bopsurg.models.training import warmup_cosine_lr

log = logging.getLogger(__name__)


#: One context: RGB (s, s, 3) uint8, masks (s, s, C) uint8 (visible, then full), visible box
#: (4,) in context px.
Context = tuple[np.ndarray, np.ndarray, np.ndarray]


class ContextSet(Sequence[Context]):
    """The contexts of GT instances, cut from their images on demand (nothing decoded is
    kept, so memory does not grow with the dataset).

    Args:
        dataset: The split.
        records: The instances.
        amodal: Also cut the full (amodal) mask, as the masks' second channel.
        whole: Frame the visible box grown to the full mask's box (needs ``amodal``), as
            :attr:`SegConfig.frame` ``"whole"`` does at test time.
    """

    def __init__(
        self,
        dataset: BopDataset,
        records: list[InstanceRecord],
        amodal: bool = False,
        whole: bool = False,
    ) -> None:
        if whole and not amodal:
            raise ValueError("whole-needle contexts need the full (amodal) mask: set amodal")
        self.dataset, self.records, self.amodal, self.whole = dataset, records, amodal, whole

    def __len__(self) -> int:
        return len(self.records)

    @overload
    def __getitem__(self, i: int) -> Context: ...
    @overload
    def __getitem__(self, i: slice) -> list[Context]: ...
    def __getitem__(self, i: int | slice) -> Context | list[Context]:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
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


def load_contexts(
    dataset: BopDataset,
    scene_ids: list[int],
    obj_id: int,
    progress: bool,
    amodal: bool = False,
    whole: bool = False,
) -> ContextSet:
    """The instances of ``obj_id`` (visib_fract >= 0.1) of ``scene_ids``; each item is
    (RGB (s, s, 3) uint8, masks (s, s, C) uint8, box (4,) in context px), read when indexed.
    ``progress`` is accepted for compatibility: nothing is decoded here."""
    del progress
    per_image = list_instances(dataset, scene_ids, obj_ids=[obj_id], min_visib=0.1)
    return ContextSet(dataset, [r for rs in per_image.values() for r in rs], amodal, whole)


def make_batch(
    items: Sequence[Context], idx: torch.Tensor, cfg: SegConfig, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Jittered crops (B, 3, S, S) in [0, 1] and soft masks (B, C, S, S) of items ``idx``."""
    xs, ys = [], []
    for i in idx.tolist():  # contexts differ in size: one grid_sample each
        rgb, mask, box = items[i]
        img = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
        m = torch.from_numpy(mask).permute(2, 0, 1)[None].float()
        b = torch.from_numpy(box)[None]
        b = torch.cat([b[:, :2] - 0.5, b[:, 2:]], 1)  # pixel-centre convention, as at test
        centre, side = dzi_boxes(b, gen, (0.25, 0.25, cfg.pad), rgb.shape[:2])
        xs.append(crop(img, centre, side, cfg.roi, "bilinear"))
        ys.append(crop(m, centre, side, cfg.roi, "bilinear"))
    x, y = torch.cat(xs), torch.cat(ys)
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


def init_weights(net: NeedleSegNet, path: Path) -> None:
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


def train(
    data: Path,
    out: Path,
    steps: int,
    batch: int,
    seed: int,
    cfg: SegConfig,
    progress: bool,
    split: str = "train",
    augment: str = "off",
    init: Path | None = None,
    hue: float = 0.0,
    hue_whole: float = 0.0,
) -> Path:
    """Train and write OUT/needle_seg.pt; returns its path.

    ``split`` may name several splits (``train,train_wide``); ``augment`` names a
    :class:`~bopsurg.models.photometric.PhotometricConfig` preset applied to the crops
    (``off``: none, the shipped recipe; ``domain``: blur, noise, gamma, colour, JPEG);
    ``init`` a segmenter checkpoint to start from (:func:`init_weights`); ``hue`` the
    amplitude (turns) of a hue shift per crop, U(-hue, hue), drawn like ``augment`` (0.5 spins
    the whole colour circle: the tissue's colour is not what tells the needle); ``hue_whole``
    the share of crops whose hue turns by any amount instead (the rest keep their colours)."""
    if not 0.0 <= hue <= 0.5:
        raise ValueError(f"--hue must lie in [0, 0.5] turns, got {hue}")
    if not 0.0 <= hue_whole <= 1.0:
        raise ValueError(f"--hue-whole must lie in [0, 1], got {hue_whole}")
    torch.manual_seed(seed)
    torch.set_num_threads(max(1, torch.get_num_threads()))
    ds = open_split(data, split)
    photometric = PhotometricConfig(**PhotometricConfig.preset_values(augment))
    arc = dataset_arc(ds, 1)
    train_ids, _ = split_scenes(ds)
    items = load_contexts(ds, train_ids, 1, progress, amodal=cfg.amodal, whole=cfg.frame == "whole")
    if not items:
        raise BopsurgError(f"{data}: no needle instances with visib_fract >= 0.1 to train on")
    log.info("%d training instances", len(items))
    net = NeedleSegNet(cfg)
    if init is not None:
        init_weights(net, init)
    opt = torch.optim.AdamW(net.parameters(), lr=3e-3, weight_decay=1e-4)
    gen = torch.Generator().manual_seed(seed)
    warm = max(1, steps // 20)
    t0 = time.perf_counter()
    net.train()
    bar = tqdm(range(steps), desc="needle_seg", disable=not progress)
    for step in bar:
        lr = warmup_cosine_lr(step, steps, warm, 3e-3)
        for g in opt.param_groups:
            g["lr"] = lr
        idx = torch.randint(len(items), (batch,), generator=gen)
        x, y = make_batch(items, idx, cfg, gen)
        if augment != "off":  # seeded per (step, sample): no draw from gen, so "off" is unchanged
            x = augment_batch(x, photometric, batch_seeds(seed, step, idx))
        if hue > 0 or hue_whole > 0:  # its own generator, for the same reason
            hue_gen = torch.Generator().manual_seed(seed * 1_000_003 + step)
            x = hsv_jitter(x, hue_gen, hue, 0.0, 0.0, whole=hue_whole)
        loss = seg_loss(net(x), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        bar.set_postfix(loss=f"{loss.item():.3f}")
        if step % 50 == 0:
            log.info("step %d loss %.4f", step, loss.item())
    seconds = time.perf_counter() - t0
    path = out / "needle_seg.pt"
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "arc": {"radius": arc.radius, "arc_rad": arc.arc_rad},
        "dataset": str(data),
        "instances": len(items),
        "recipe": {"steps": steps, "batch": batch, "lr": 3e-3, "seed": seed},
        **({"split": split} if split != "train" else {}),
        **({"augment": augment} if augment != "off" else {}),
        **({"init": str(init)} if init is not None else {}),
        **({"hue": hue} if hue > 0 else {}),
        **({"hue_whole": hue_whole} if hue_whole > 0 else {}),
        "train_seconds": round(seconds, 1),
        "torch": torch.__version__,
    }
    save_checkpoint(
        path, net.state_dict(), kind="needle_seg", config=cfg.to_dict(), meta=meta, half=True
    )
    log.info("wrote %s (%.1f min)", path, seconds / 60)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m bopsurg.models.refine.train_seg",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("dataset", type=Path, help="BOP dataset root with a train split")
    ap.add_argument(
        "--split", default="train", help="training split(s), comma-separated (default: train)"
    )
    ap.add_argument(
        "--augment",
        default="off",
        choices=sorted(PhotometricConfig.PRESETS),
        help="photometric augmentation preset of the crops (default: off)",
    )
    ap.add_argument("--out", type=Path, required=True, help="run folder")
    ap.add_argument("--steps", type=int, default=1500, help="optimiser steps (default 1500)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--roi", type=int, default=SegConfig.roi, help="ROI side, px")
    ap.add_argument("--width", type=int, default=SegConfig.width, help="full-res channels")
    ap.add_argument(
        "--stages",
        type=int,
        default=SegConfig.stages,
        help="stride-2 stages, 3 or 4 (4: twice the context, for the full mask)",
    )
    ap.add_argument(
        "--amodal",
        action="store_true",
        help="also predict the needle's full (amodal) mask, the evidence the fit prefers",
    )
    ap.add_argument(
        "--frame",
        choices=["visible", "whole"],
        default=SegConfig.frame,
        help="what the ROI frames: the visible box (default), or the needle's whole "
        "projection (needs --amodal; at test, the start pose's projected arc)",
    )
    ap.add_argument("--init", type=Path, help="start from this segmenter checkpoint (fine-tune)")
    ap.add_argument(
        "--hue",
        type=float,
        default=0.0,
        help="hue shift amplitude per crop, turns (0.5: any tissue colour; default 0: none)",
    )
    ap.add_argument(
        "--hue-whole",
        type=float,
        default=0.0,
        metavar="SHARE",
        help="share of the crops whose hue turns by any amount, the rest keeping --hue's "
        "(0.5: half see tissue of any colour, half ours; default 0: none)",
    )
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        cfg = SegConfig(
            roi=args.roi, width=args.width, amodal=args.amodal, stages=args.stages,
            frame=args.frame,
        )  # fmt: skip
        train(
            args.dataset, args.out, args.steps, args.batch, args.seed, cfg,
            not args.no_progress, split=args.split, augment=args.augment, init=args.init,
            hue=args.hue,
            hue_whole=args.hue_whole,
        )  # fmt: skip
    except (BopsurgError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)  # noqa: T201 (the CLI's one-line error)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
