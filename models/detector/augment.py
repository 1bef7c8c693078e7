"""Batched, seeded detector augmentations on images already at the network input size.

Images are (B, 3, H, W) float RGB in [0, 1]; boxes come as a list of B tensors (n_i, 5)
[class, x1, y1, x2, y2] in input pixels (as the detector's targets). Every random draw uses
the given ``torch.Generator`` (a CPU generator; the draws are moved to the images' device),
so a run is reproducible. The functions return new tensors and never modify their inputs.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .boxes import box_area
from .letterbox import PAD_VALUE

#: A transformed box is dropped when narrower or lower than this many pixels...
MIN_BOX_SIDE = 2.0
#: ...or when less than this fraction of its (transformed) area stays inside the image.
MIN_AREA_KEPT = 0.2


def _uniform(gen: torch.Generator, shape: tuple[int, ...], lo: float, hi: float) -> Tensor:
    """U(lo, hi) draws on the CPU (whatever the generator's device)."""
    return (lo + (hi - lo) * torch.rand(shape, generator=gen, device=gen.device)).cpu()


# ---------------------------------------------------------------------------------- colour
def rgb_to_hsv(rgb: Tensor) -> Tensor:
    """(..., 3, H, W) RGB in [0, 1] -> HSV, all three in [0, 1] (hue in turns)."""
    r, g, b = rgb.unbind(dim=-3)
    v, argmax = rgb.max(dim=-3)
    delta = v - rgb.min(dim=-3).values
    s = torch.where(v > 0, delta / v.clamp_min(1e-12), torch.zeros_like(v))
    d = delta.clamp_min(1e-12)
    # hue sector by the largest channel (in sixths of a turn)
    h = torch.where(
        argmax == 0, (g - b) / d, torch.where(argmax == 1, 2 + (b - r) / d, 4 + (r - g) / d)
    )
    h = torch.where(delta > 0, (h / 6) % 1.0, torch.zeros_like(h))
    return torch.stack((h, s, v), dim=-3)


def hsv_to_rgb(hsv: Tensor) -> Tensor:
    """Inverse of :func:`rgb_to_hsv`."""
    h, s, v = hsv.unbind(dim=-3)
    n = torch.tensor([5.0, 3.0, 1.0], device=hsv.device, dtype=hsv.dtype).view(3, 1, 1)
    k = (n + h.unsqueeze(-3) * 6) % 6
    # f(n) = v − v·s·clamp(min(k, 4 − k), 0, 1), channels (R, G, B) for n = (5, 3, 1)
    return v.unsqueeze(-3) * (1 - s.unsqueeze(-3) * torch.minimum(k, 4 - k).clamp(0, 1))


def hsv_jitter(
    images: Tensor,
    gen: torch.Generator,
    h: float = 0.015,
    s: float = 0.7,
    v: float = 0.4,
    whole: float = 0.0,
) -> Tensor:
    """Random colour change per image.

    Hue is shifted by U(−h, h) turns, or, for a share ``whole`` of the images, by U(−0.5, 0.5)
    (the whole colour circle: most images keep their usual colours, the rest show tissue of
    any colour); saturation and value are multiplied by U(1 − s, 1 + s) and U(1 − v, 1 + v),
    then clipped to [0, 1]. images (B, 3, H, W) -> same shape. ``whole = 0`` draws nothing
    more, so the draws of older recipes are unchanged.
    """
    bsz = images.shape[0]
    dh = _uniform(gen, (bsz,), -h, h)
    gains = torch.stack((_uniform(gen, (bsz,), -s, s), _uniform(gen, (bsz,), -v, v)), 1) + 1
    if whole > 0:
        spin = _uniform(gen, (bsz,), 0.0, 1.0) < whole
        dh = torch.where(spin, _uniform(gen, (bsz,), -0.5, 0.5), dh)
    dh, gains = dh.to(images), gains.to(images)
    hsv = rgb_to_hsv(images.clamp(0, 1))
    hue = (hsv[:, 0] + dh[:, None, None]) % 1.0
    sv = (hsv[:, 1:] * gains[:, :, None, None]).clamp(0, 1)
    return hsv_to_rgb(torch.cat((hue[:, None], sv), dim=1))


# -------------------------------------------------------------------------------- geometry
def random_flip(
    images: Tensor, boxes_list: list[Tensor], gen: torch.Generator, p: float = 0.5
) -> tuple[Tensor, list[Tensor]]:
    """Horizontal flip of each image with probability ``p``; boxes follow (x -> W − x)."""
    w = images.shape[-1]
    flip = _uniform(gen, (images.shape[0],), 0.0, 1.0) < p
    out = torch.where(flip.to(images.device)[:, None, None, None], images.flip(-1), images)
    new_boxes = []
    for f, boxes in zip(flip.tolist(), boxes_list, strict=True):
        if f and len(boxes):
            boxes = boxes.clone()
            boxes[:, [1, 3]] = w - boxes[:, [3, 1]]
        new_boxes.append(boxes)
    return out, new_boxes


def random_affine(
    images: Tensor,
    boxes_list: list[Tensor],
    gen: torch.Generator,
    scale: tuple[float, float] = (0.5, 1.5),
    translate: float = 0.1,
) -> tuple[Tensor, list[Tensor]]:
    """Random zoom about the image centre and shift, per image (no rotation or shear: the
    axis-aligned hull of a rotated box would be loose around a thin needle).

    A point moves as ``x' = k·(x − W/2) + W/2 + t_x`` with ``k ~ U(scale)`` and
    ``t_x ~ U(−translate, translate)·W`` (likewise y with H). Uncovered pixels are filled with
    :data:`PAD_VALUE`. Boxes are transformed, clipped to the image and dropped when thinner
    than :data:`MIN_BOX_SIDE` px or when less than :data:`MIN_AREA_KEPT` of them stays inside.

    Returns:
        (images (B, 3, H, W), boxes list).
    """
    bsz, _, h, w = images.shape
    k = _uniform(gen, (bsz,), *scale)
    t = _uniform(gen, (bsz, 2), -translate, translate) * torch.tensor([float(w), float(h)])
    # grid_sample's normalised coordinates (align_corners=False) are u = 2x/W − 1, where the
    # zoom about the centre is u' = k·u + 2·t_x/W; theta is its inverse (output -> input).
    t_norm = 2 * t / torch.tensor([float(w), float(h)])
    theta = torch.zeros(bsz, 2, 3)
    theta[:, 0, 0] = theta[:, 1, 1] = 1 / k
    theta[:, :, 2] = -t_norm / k[:, None]
    theta = theta.to(images)
    grid = F.affine_grid(theta, list(images.shape), align_corners=False)
    # sample (image − fill) with zero padding, then add fill back: borders become the fill
    out = F.grid_sample(
        images - PAD_VALUE, grid, mode="bilinear", padding_mode="zeros", align_corners=False
    )
    out = out + PAD_VALUE

    new_boxes = []
    centre = torch.tensor([w / 2, h / 2, w / 2, h / 2])
    limits = torch.tensor([float(w), float(h), float(w), float(h)])
    for i, boxes in enumerate(boxes_list):
        if len(boxes) == 0:
            new_boxes.append(boxes)
            continue
        xyxy = boxes[:, 1:5].detach().cpu().float()
        moved = k[i] * (xyxy - centre) + centre + t[i].repeat(2)
        clipped = torch.minimum(moved.clamp_min(0), limits)
        bw, bh = clipped[:, 2] - clipped[:, 0], clipped[:, 3] - clipped[:, 1]
        kept_frac = box_area(clipped) / box_area(moved).clamp_min(1e-12)
        ok = (bw >= MIN_BOX_SIDE) & (bh >= MIN_BOX_SIDE) & (kept_frac >= MIN_AREA_KEPT)
        res = boxes[ok.to(boxes.device)].clone()
        res[:, 1:5] = clipped[ok].to(res)
        new_boxes.append(res)
    return out, new_boxes
