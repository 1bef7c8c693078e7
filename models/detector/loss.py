"""YOLOX loss: IoU, objectness, classification and (optionally) L1, with SimOTA targets.

All terms are sums divided by ``max(num_fg, 1)``, the number of positive anchors in the batch:

- iou: 5·Σ_pos (1 − IoU²) of the decoded boxes with their GT boxes;
- obj: Σ_all BCE(obj_logit, 1[positive]) (the only term on images without objects);
- cls: Σ_pos BCE(cls_logits, onehot(class)·IoU), an IoU-aware soft target;
- l1: Σ_pos |raw box − encoded GT| (only when ``use_l1``; YOLOX switches it on for the last,
  augmentation-free epochs).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .anchors import decode_boxes, encode_boxes
from .assign import simota_assign_batch
from .boxes import elementwise_iou_cxcywh, xyxy_to_cxcywh

IOU_LOSS_WEIGHT = 5.0


def yolox_loss(
    raw: Tensor,
    targets: list[Tensor],
    grid: Tensor,
    strides: Tensor,
    num_classes: int,
    use_l1: bool = False,
) -> dict[str, Tensor]:
    """Loss of a batch.

    Args:
        raw: (B, A, 5 + C) raw predictions [tx, ty, tw, th, obj, cls...].
        targets: B tensors (n_i, 5) [class, x1, y1, x2, y2], input px; n_i may be 0.
        grid: (A, 2) anchor cells (j, i); strides: (A,) px (see :mod:`.anchors`).
        num_classes: C.
        use_l1: add the L1 term (otherwise it is 0).

    Returns:
        Scalars "iou", "obj", "cls", "l1", "total" (differentiable) and "num_fg" (int64, the
        number of positives, for logging).
    """
    if len(targets) != raw.shape[0]:
        raise ValueError(f"{len(targets)} target tensors for a batch of {raw.shape[0]}")
    raw = raw.float()  # the assignment and the losses run in float32, also under autocast
    boxes = decode_boxes(raw[..., :4], grid, strides)  # (B, A, 4) cxcywh
    obj, cls = raw[..., 4], raw[..., 5:]
    centers = (grid + 0.5) * strides[:, None]

    # the GTs padded to the most an image has, moved to the device in one copy
    counts = torch.tensor([len(t) for t in targets])
    padded = torch.nn.utils.rnn.pad_sequence(
        [t.reshape(-1, 5).float() for t in targets], batch_first=True
    ).to(raw.device, non_blocking=True)
    gt_valid = (torch.arange(padded.shape[1]) < counts[:, None]).to(raw.device)
    gt_cls, gt_box = padded[..., 0].long(), xyxy_to_cxcywh(padded[..., 1:5])
    a = simota_assign_batch(
        boxes.detach(), obj.detach(), cls.detach(), centers, strides, gt_box, gt_cls, gt_valid
    )
    fg_mask = a.fg_mask  # (B, A)
    b_idx = fg_mask.nonzero()[:, 0]  # row-major (b, a): the order boolean indexing walks
    matched = a.gt_index[fg_mask]
    gt_boxes = [gt_box[b_idx, matched]]
    cls_targets = [F.one_hot(gt_cls[b_idx, matched], num_classes).float() * a.iou[fg_mask, None]]
    l1_targets = []
    if use_l1:
        anchors = fg_mask.nonzero()[:, 1]
        l1_targets.append(encode_boxes(gt_boxes[0], grid[anchors], strides[anchors]))

    num_fg = fg_mask.sum()
    denom = num_fg.clamp_min(1).float()
    loss_obj = F.binary_cross_entropy_with_logits(obj, fg_mask.float(), reduction="sum") / denom
    zero = raw.new_zeros(())
    loss_iou = loss_cls = loss_l1 = zero
    if len(gt_boxes[0]):
        # boolean indexing walks (b, a) row-major, the order in which the targets were collected
        iou = elementwise_iou_cxcywh(boxes[fg_mask], torch.cat(gt_boxes))
        loss_iou = IOU_LOSS_WEIGHT * (1 - iou.square()).sum() / denom
        loss_cls = (
            F.binary_cross_entropy_with_logits(
                cls[fg_mask], torch.cat(cls_targets), reduction="sum"
            )
            / denom
        )
        if use_l1:
            loss_l1 = (raw[..., :4][fg_mask] - torch.cat(l1_targets)).abs().sum() / denom
    total = loss_iou + loss_obj + loss_cls + loss_l1
    return {
        "iou": loss_iou,
        "obj": loss_obj,
        "cls": loss_cls,
        "l1": loss_l1,
        "total": total,
        "num_fg": num_fg,
    }
