"""Box geometry: format conversions, IoU and NMS (the letterbox is in :mod:`.letterbox`).

Coordinates are continuous pixels: an image of width W spans x in [0, W] and pixel i covers
[i, i + 1]. ``xyxy`` boxes are (x1, y1, x2, y2); ``cxcywh`` boxes are (cx, cy, w, h).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def cxcywh_to_xyxy(b: Tensor) -> Tensor:
    """(..., 4) cxcywh -> (..., 4) xyxy."""
    cxcy, wh = b[..., :2], b[..., 2:4]
    return torch.cat((cxcy - wh / 2, cxcy + wh / 2), dim=-1)


def xyxy_to_cxcywh(b: Tensor) -> Tensor:
    """(..., 4) xyxy -> (..., 4) cxcywh."""
    p1, p2 = b[..., :2], b[..., 2:4]
    return torch.cat(((p1 + p2) / 2, p2 - p1), dim=-1)


def box_area(b: Tensor) -> Tensor:
    """(..., 4) xyxy -> (...) area in px² (0 for inverted boxes)."""
    return (b[..., 2] - b[..., 0]).clamp_min(0) * (b[..., 3] - b[..., 1]).clamp_min(0)


def box_iou(a: Tensor, b: Tensor) -> Tensor:
    """Pairwise IoU of xyxy boxes: a (N, 4), b (M, 4) -> (N, M)."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp_min(0).prod(dim=-1)
    union = box_area(a)[:, None] + box_area(b)[None, :] - inter
    return inter / union.clamp_min(1e-12)


def elementwise_iou(a: Tensor, b: Tensor) -> Tensor:
    """IoU of matching rows of xyxy boxes: a (N, 4), b (N, 4) -> (N,). Differentiable."""
    lt = torch.maximum(a[:, :2], b[:, :2])
    rb = torch.minimum(a[:, 2:], b[:, 2:])
    inter = (rb - lt).clamp_min(0).prod(dim=-1)
    union = box_area(a) + box_area(b) - inter
    return inter / union.clamp_min(1e-12)


def pairwise_iou_cxcywh(a: Tensor, b: Tensor) -> Tensor:
    """Pairwise IoU of cxcywh boxes: a (N, 4), b (M, 4) -> (N, M)."""
    return box_iou(cxcywh_to_xyxy(a), cxcywh_to_xyxy(b))


def elementwise_iou_cxcywh(a: Tensor, b: Tensor) -> Tensor:
    """IoU of matching rows of cxcywh boxes: (N, 4), (N, 4) -> (N,). Differentiable."""
    return elementwise_iou(cxcywh_to_xyxy(a), cxcywh_to_xyxy(b))


def nms(boxes: Tensor, scores: Tensor, iou_thr: float) -> Tensor:
    """Greedy non-maximum suppression.

    Args:
        boxes: (N, 4) xyxy.
        scores: (N,).
        iou_thr: a box is suppressed by a higher-scoring kept box when their IoU > iou_thr.

    Returns:
        (K,) int64 indices into ``boxes`` of the kept boxes, by decreasing score (ties keep
        their input order).
    """
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.sort(scores, descending=True, stable=True).indices
    # One IoU matrix on the device, then the inherently sequential greedy pass on the host
    # (a single transfer instead of one device sync per box).
    over = (box_iou(boxes[order], boxes[order]) > iou_thr).cpu().numpy()
    n = len(order)
    suppressed = np.zeros(n, dtype=bool)
    keep = []
    for i in range(n):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= over[i]
    return order[torch.as_tensor(keep, dtype=torch.long, device=order.device)]


def batched_nms(boxes: Tensor, scores: Tensor, classes: Tensor, iou_thr: float) -> Tensor:
    """Class-aware NMS: boxes of different classes never suppress each other.

    Each class is shifted by ``class · span`` with ``span`` the extent of all coordinates + 1,
    so the classes' boxes cannot overlap (also with negative coordinates). Shapes as in
    :func:`nms`, ``classes`` (N,) integer-valued.
    """
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    span = boxes.max() - boxes.min() + 1
    return nms(boxes + (classes.to(boxes.dtype) * span)[:, None], scores, iou_thr)
