"""Anchor points (one per grid cell and level) and the box parametrisation.

Anchor a of a level with stride s sits at grid cell (i, j). A raw prediction
(tx, ty, tw, th) decodes to the cxcywh box, in input pixels,
``cx = (tx + j)·s, cy = (ty + i)·s, w = exp(tw)·s, h = exp(th)·s`` (YOLOX). The cell's centre,
used to pick SimOTA candidates, is ((j + 0.5)·s, (i + 0.5)·s).
"""

from __future__ import annotations

import torch
from torch import Tensor

#: Upper bound of the raw log-size, so exp() cannot overflow in early training
#: (exp(10)·8 px is already far larger than any input).
MAX_LOG_SIZE = 10.0


def make_anchors(
    input_hw: tuple[int, int], strides: tuple[int, ...], device: torch.device | str
) -> tuple[Tensor, Tensor]:
    """Grid cells of all levels, in the order the model concatenates its outputs.

    Args:
        input_hw: network input (H, W) in pixels, multiples of max(strides).
        strides: level strides in pixels.

    Returns:
        (grid (A, 2) float32 cell indices (j, i), strides (A,) float32 pixels),
        A = Σ (H/s)·(W/s), levels in order, cells row-major within a level.
    """
    grids, strs = [], []
    for s in strides:
        h, w = input_hw[0] // s, input_hw[1] // s
        ii, jj = torch.meshgrid(
            torch.arange(h, device=device, dtype=torch.float32),
            torch.arange(w, device=device, dtype=torch.float32),
            indexing="ij",
        )
        grids.append(torch.stack((jj, ii), dim=-1).reshape(-1, 2))
        strs.append(torch.full((h * w,), float(s), device=device))
    return torch.cat(grids), torch.cat(strs)


def decode_boxes(raw_box: Tensor, grid: Tensor, strides: Tensor) -> Tensor:
    """Raw (..., A, 4) (tx, ty, tw, th) -> (..., A, 4) cxcywh in input pixels."""
    s = strides[:, None]
    xy = (raw_box[..., :2] + grid) * s
    wh = torch.exp(raw_box[..., 2:4].clamp(max=MAX_LOG_SIZE)) * s
    return torch.cat((xy, wh), dim=-1)


def encode_boxes(boxes: Tensor, grid: Tensor, strides: Tensor, eps: float = 1e-8) -> Tensor:
    """Inverse of :func:`decode_boxes`: cxcywh (N, 4) px at anchors grid (N, 2), strides (N,)
    -> raw targets (N, 4) (the L1 loss's targets)."""
    s = strides[:, None]
    return torch.cat((boxes[:, :2] / s - grid, torch.log(boxes[:, 2:4] / s + eps)), dim=-1)
