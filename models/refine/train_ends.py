"""Train the needle-end classifier (:mod:`.ends`) on a BOP split's GT poses.

    python -m bopsurg.models.refine.train_ends DATASET --split train --out runs/ends --seed 0

Per GT needle instance (visib_fract >= 0.3) the patches of its two ends are cut at the GT
pose, twice the side the classifier sees (so a jittered crop stays inside), and kept in
memory as uint8. An end whose projection is not on the visible mask (within 2 px: in the
jaws, in the tissue) gets the target 0.5, "cannot tell" (``--seen-only`` leaves it out), so the
end that is seen decides; one off the image is left out. Each step draws a batch of ends and crops
each at a random turn (±``--turn`` degrees), scale (×0.8–1.25) and shift (±10 % of the side),
as a pose estimate a few degrees and millimetres off would frame it, flipped about its x axis
half the time (the other face), then the whole hue circle and the ``domain`` photometric set:
the colours of the tissue are not what tells a tip from a tail. Binary cross-entropy, AdamW
with warm-up and cosine decay; deterministic for a seed. Held-out scenes of the split (the
estimators' :func:`~bopsurg.models.data.split_scenes`) give the validation accuracy on seen
ends.

Writes OUT/needle_ends.pt and its JSON (config, the needle arc, recipe, seed, accuracy, and
``--margin``: the logit margin a swap needs when the estimator runs this classifier without
an ``ends_margin`` option; choose it on validation splits with ``bench/bench_ends.py``, the
smallest margin at which the classifier turns none of their right poses).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_mask, load_rgb
from bopsurg.errors import BopsurgError
from bopsurg.models.checkpoint import save_checkpoint
from bopsurg.models.data import list_instances, open_split, split_scenes
from bopsurg.models.detector.augment import hsv_jitter
from bopsurg.models.photometric import PhotometricConfig, augment_batch, batch_seeds
from bopsurg.models.refine.arc import ArcModel, dataset_arc
from bopsurg.models.refine.ends import TIP, EndConfig, EndNet, end_frames, sample_patches
from bopsurg.models.training import warmup_cosine_lr

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
) -> tuple[torch.Tensor, torch.Tensor]:
    """Patches (N, 3, 2P, 2P) uint8 of the ends of the instances (visib_fract >= 0.3) of
    ``scene_ids`` at their GT poses, and their targets (N,): 1 the tip, 0 the tail, and with
    ``unseen`` 0.5 for an end hidden in the image (in the jaws, in the tissue): the patch
    says nothing, so the classifier learns to say so (logit 0) and the other end decides.
    With ``max_instances``, that many instances drawn with ``seed``."""
    per_image = list_instances(ds, scene_ids, obj_ids=[obj_id], min_visib=0.3)
    records = [r for rs in per_image.values() for r in rs]
    if max_instances is not None and len(records) > max_instances:
        pick = np.random.default_rng(seed).choice(len(records), max_instances, replace=False)
        records = [records[i] for i in sorted(pick)]
    by_image: dict[tuple[int, int], list] = {}
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
    return p[0].round().clamp(0, 255).to(torch.uint8).numpy()


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
    net.eval()
    c = patch // 2
    with torch.inference_mode():
        x = patches[:, :, c : c + patch, c : c + patch].float() / 255
        pred = torch.cat([net(x[i : i + 512]) for i in range(0, len(x), 512)]) > 0
    net.train()
    return float((pred == labels.bool()).float().mean())


def train(
    data: Path,
    out: Path,
    *,
    split: str = "train",
    steps: int = 3000,
    batch: int = 128,
    lr: float = 3e-3,
    seed: int = 0,
    turn_deg: float = 15.0,
    max_instances: int | None = None,
    unseen: bool = True,
    cfg: EndConfig | None = None,
    margin: float = 0.0,
    progress: bool = True,
) -> Path:
    """Train and write OUT/needle_ends.pt; returns its path. ``margin`` (logits) is recorded
    as the classifier's default decision margin (:func:`.ends.load_judge`)."""
    if not math.isfinite(margin):
        raise BopsurgError(f"--margin must be a finite logit margin, got {margin}")
    cfg = cfg or EndConfig()
    torch.manual_seed(seed)
    ds = open_split(data, split)
    obj_id = 1
    arc = dataset_arc(ds, obj_id)
    train_ids, val_ids = split_scenes(ds)
    x_tr, y_tr = collect_ends(
        ds, train_ids, obj_id, arc, cfg, max_instances=max_instances, seed=seed, unseen=unseen,
        progress=progress,
    )  # fmt: skip
    n_val = None if max_instances is None else max(1, max_instances // 10)
    x_va, y_va = collect_ends(
        ds, val_ids, obj_id, arc, cfg, max_instances=n_val, seed=seed + 1, unseen=False,
        progress=progress,
    )  # fmt: skip
    log.info(
        "%d training ends (%.0f %% tips, %.0f %% hidden), %d validation",
        len(x_tr), 100 * (y_tr == 1).float().mean(), 100 * (y_tr == 0.5).float().mean(), len(x_va),
    )  # fmt: skip
    net = EndNet(cfg)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    photometric = PhotometricConfig(**PhotometricConfig.preset_values("domain"))
    gen = torch.Generator().manual_seed(seed)
    warm = max(1, steps // 20)
    t0 = time.perf_counter()
    net.train()
    bar = tqdm(range(steps), desc="needle_ends", disable=not progress)
    for step in bar:
        for g in opt.param_groups:
            g["lr"] = warmup_cosine_lr(step, steps, warm, lr)
        idx = torch.randint(len(x_tr), (batch,), generator=gen)
        x = jittered(x_tr[idx], gen, cfg.patch, turn_deg)
        x = hsv_jitter(x, gen, 0.5, 0.5, 0.4)
        x = augment_batch(x, photometric, batch_seeds(seed, step, idx))
        loss = F.binary_cross_entropy_with_logits(net(x), y_tr[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        bar.set_postfix(loss=f"{loss.item():.3f}")
    seconds = time.perf_counter() - t0
    acc = accuracy(net, x_va, y_va, cfg.patch)
    log.info("validation accuracy %.4f on %d ends (%.1f min)", acc, len(x_va), seconds / 60)
    path = out / "needle_ends.pt"
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "arc": {"radius": arc.radius, "arc_rad": arc.arc_rad},
        "dataset": str(data),
        "split": split,
        "ends": len(x_tr),
        "val_ends": len(x_va),
        "val_accuracy": round(acc, 4),
        "margin": margin,
        "recipe": {
            "steps": steps, "batch": batch, "lr": lr, "seed": seed, "turn_deg": turn_deg,
            "max_instances": max_instances, "unseen": unseen,
        },
        "train_seconds": round(seconds, 1),
        "torch": torch.__version__,
    }  # fmt: skip
    save_checkpoint(path, net.state_dict(), kind="needle_ends", config=cfg.to_dict(), meta=meta)
    log.info("wrote %s", path)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m bopsurg.models.refine.train_ends",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("dataset", type=Path, help="BOP dataset root")
    ap.add_argument("--split", default="train", help="training split(s), comma-separated")
    ap.add_argument("--out", type=Path, required=True, help="run folder")
    ap.add_argument("--steps", type=int, default=3000, help="optimiser steps (default 3000)")
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--turn", type=float, default=15.0, help="patch turn jitter, degrees")
    ap.add_argument("--max-instances", type=int, help="draw this many GT needles (default: all)")
    ap.add_argument(
        "--seen-only",
        action="store_true",
        help="leave out the hidden ends (default: taught as 'cannot tell', target 0.5)",
    )
    ap.add_argument("--patch", type=int, default=EndConfig.patch, help="patch side, px")
    ap.add_argument("--scale", type=float, default=EndConfig.scale,
                    help="patch side / the arc's projected radius")  # fmt: skip
    ap.add_argument(
        "--margin",
        type=float,
        default=0.0,
        help="logit margin a swap needs, recorded as the classifier's default (choose it on "
        "validation splits with bench/bench_ends.py; default 0)",
    )
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        train(
            args.dataset, args.out, split=args.split, steps=args.steps, batch=args.batch,
            lr=args.lr, seed=args.seed, turn_deg=args.turn, max_instances=args.max_instances,
            unseen=not args.seen_only,
            cfg=EndConfig(patch=args.patch, scale=args.scale), margin=args.margin,
            progress=not args.no_progress,
        )  # fmt: skip
    except (BopsurgError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)  # noqa: T201 (the CLI's one-line error)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
