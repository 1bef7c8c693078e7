"""SimOTA label assignment (YOLOX): which anchors are positives, and for which ground truth.

For one image with G ground-truth boxes:

1. Candidates: anchors whose cell centre lies within a square of half-side 1.5·stride around
   a GT centre.
2. Cost[g, a] = BCE(sqrt(σ(cls)·σ(obj)), onehot(class_g)) summed over classes
   + 3·(−log(IoU(pred_a, gt_g) + 1e-8)) + 1e6·[a outside g's square].
3. dynamic_k[g] = max(1, int(Σ top-10 IoU of g)); GT g takes its dynamic_k cheapest anchors.
4. An anchor taken by several GTs keeps only its cheapest one.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .boxes import box_area, cxcywh_to_xyxy, pairwise_iou_cxcywh

CENTER_RADIUS = 1.5  # half-side of the candidate square, in strides
IOU_WEIGHT = 3.0
OUTSIDE_COST = 1e6
TOP_K_IOU = 10


@dataclass
class Assignment:
    """Result for one image with A anchors.

    Attributes:
        fg_mask: (A,) bool, positives.
        gt_index: (A,) int64, the matched GT of each anchor, -1 for background.
        iou: (A,) float, IoU of the anchor's predicted box with its GT (0 for background).
    """

    fg_mask: Tensor
    gt_index: Tensor
    iou: Tensor

    @property
    def num_fg(self) -> int:
        return int(self.fg_mask.sum())


def candidate_mask(
    centers: Tensor, strides: Tensor, gt_boxes: Tensor, radius: float = CENTER_RADIUS
) -> Tensor:
    """(G, A) bool: anchor centres (A, 2) px within ``radius·stride`` (L∞) of the centres
    of the GT boxes (G, 4) cxcywh px."""
    d = (centers[None, :, :] - gt_boxes[:, None, :2]).abs()  # (G, A, 2)
    return (d < radius * strides[None, :, None]).all(dim=-1)


def dynamic_k_matching(cost: Tensor, ious: Tensor, top_k: int = TOP_K_IOU) -> Tensor:
    """Match GTs to anchors.

    Args:
        cost: (G, K) matching cost of GT g and candidate anchor k.
        ious: (G, K) IoU of GT g with anchor k's predicted box.

    Returns:
        (G, K) bool matching; every column has at most one True.
    """
    g, k = cost.shape
    dynamic_k = ious.topk(min(top_k, k), dim=1).values.sum(dim=1).int().clamp_min(1)  # (G,)
    # Mark each GT's dynamic_k cheapest anchors: the flag "rank < k" scattered back to anchors.
    order = cost.argsort(dim=1)
    ranks = torch.arange(k, device=cost.device).expand(g, k)
    matching = torch.zeros_like(cost, dtype=torch.bool)
    matching.scatter_(1, order, ranks < dynamic_k[:, None])
    shared = (matching.sum(dim=0) > 1).nonzero().squeeze(1)
    if len(shared):
        best = cost[:, shared].argmin(dim=0)
        matching[:, shared] = False
        matching[best, shared] = True
    return matching


def matching_cost(
    pred_boxes: Tensor,
    obj_logits: Tensor,
    cls_logits: Tensor,
    gt_boxes: Tensor,
    gt_classes: Tensor,
    inside: Tensor,
) -> tuple[Tensor, Tensor]:
    """SimOTA cost (G, K) and IoU (G, K) of G GTs against K candidate anchors.

    pred_boxes (K, 4) and gt_boxes (G, 4) are cxcywh px; obj_logits (K,), cls_logits (K, C),
    gt_classes (G,) int64, inside (G, K) bool (anchor in the GT's candidate square).
    """
    ious = pairwise_iou_cxcywh(gt_boxes, pred_boxes)
    p = (cls_logits.sigmoid() * obj_logits.sigmoid()[:, None]).sqrt().clamp(1e-8, 1 - 1e-8)
    neg, pos = -torch.log1p(-p), -torch.log(p)  # BCE against target 0 and against 1, (K, C)
    # BCE with a one-hot target = Σ_c neg − neg[class] + pos[class], without a (G, K, C) tensor.
    cls_cost = neg.sum(dim=1)[None, :] + (pos - neg).T[gt_classes]
    cost = cls_cost + IOU_WEIGHT * -torch.log(ious + 1e-8) + OUTSIDE_COST * (~inside).float()
    return cost, ious


@torch.no_grad()
def simota_assign(
    pred_boxes: Tensor,
    obj_logits: Tensor,
    cls_logits: Tensor,
    centers: Tensor,
    strides: Tensor,
    gt_boxes: Tensor,
    gt_classes: Tensor,
) -> Assignment:
    """Assign the A anchors of one image to its G ground truths.

    Args:
        pred_boxes: (A, 4) predicted cxcywh boxes, input px.
        obj_logits: (A,) objectness logits.
        cls_logits: (A, C) class logits.
        centers: (A, 2) anchor cell centres, input px.
        strides: (A,) anchor strides, px.
        gt_boxes: (G, 4) cxcywh, input px.
        gt_classes: (G,) int64.
    """
    a = pred_boxes.shape[0]
    fg = torch.zeros(a, dtype=torch.bool, device=pred_boxes.device)
    gt_index = torch.full((a,), -1, dtype=torch.long, device=pred_boxes.device)
    iou = torch.zeros(a, dtype=pred_boxes.dtype, device=pred_boxes.device)
    if len(gt_boxes) == 0:
        return Assignment(fg, gt_index, iou)
    inside = candidate_mask(centers, strides, gt_boxes)  # (G, A)
    cand = inside.any(dim=0).nonzero().squeeze(1)  # anchors considered at all
    if len(cand) == 0:
        return Assignment(fg, gt_index, iou)
    cost, ious = matching_cost(
        pred_boxes[cand], obj_logits[cand], cls_logits[cand], gt_boxes, gt_classes, inside[:, cand]
    )
    matching = dynamic_k_matching(cost, ious)
    taken = matching.any(dim=0)
    anchors = cand[taken]
    matched = matching[:, taken].float().argmax(dim=0)
    fg[anchors] = True
    gt_index[anchors] = matched
    iou[anchors] = ious[matched, taken.nonzero().squeeze(1)]
    return Assignment(fg, gt_index, iou)


@dataclass
class BatchAssignment:
    """Result for B images with A anchors each (what :func:`simota_assign` gives per image).

    Attributes:
        fg_mask: (B, A) bool, positives.
        gt_index: (B, A) int64, the matched GT (index into the image's padded GTs), -1 for
            background.
        iou: (B, A) float, IoU of the anchor's predicted box with its GT (0 for background).
    """

    fg_mask: Tensor
    gt_index: Tensor
    iou: Tensor


@torch.no_grad()
def simota_assign_batch(
    pred_boxes: Tensor,
    obj_logits: Tensor,
    cls_logits: Tensor,
    centers: Tensor,
    strides: Tensor,
    gt_boxes: Tensor,
    gt_classes: Tensor,
    gt_valid: Tensor,
) -> BatchAssignment:
    """:func:`simota_assign` for a whole batch at once (no per-image loop, no wait for the
    device), the GTs padded to the most any image has.

    Args:
        pred_boxes: (B, A, 4) cxcywh px; obj_logits (B, A); cls_logits (B, A, C).
        centers: (A, 2) anchor cell centres, px; strides: (A,) px.
        gt_boxes: (B, G, 4) cxcywh px; gt_classes: (B, G) int64; gt_valid: (B, G) bool,
            False for padding.
    """
    B, A = obj_logits.shape
    if gt_boxes.shape[1] == 0:  # no GT in any image
        none = torch.zeros((B, A), dtype=torch.bool, device=obj_logits.device)
        return BatchAssignment(none, torch.full_like(none, -1, dtype=torch.long), none.float())
    inside = candidate_mask(centers, strides, gt_boxes.reshape(-1, 4)).view(B, -1, A)
    inside &= gt_valid[:, :, None]
    cand = inside.any(dim=1)  # (B, A): anchors considered at all
    xy_g, xy_p = cxcywh_to_xyxy(gt_boxes)[:, :, None], cxcywh_to_xyxy(pred_boxes)[:, None]
    lt, rb = (
        torch.maximum(xy_g[..., :2], xy_p[..., :2]),
        torch.minimum(xy_g[..., 2:], xy_p[..., 2:]),
    )
    inter = (rb - lt).clamp_min(0).prod(dim=-1)
    ious = inter / (box_area(xy_g) + box_area(xy_p) - inter).clamp_min(1e-12)  # (B, G, A)
    ious = ious * cand[:, None]  # as if only the candidates were there
    p = (cls_logits.sigmoid() * obj_logits.sigmoid()[..., None]).sqrt().clamp(1e-8, 1 - 1e-8)
    neg, pos = -torch.log1p(-p), -torch.log(p)  # (B, A, C)
    picked = (pos - neg).gather(2, gt_classes[:, None, :].expand(B, A, -1))  # (B, A, G)
    cost = neg.sum(dim=2)[:, None, :] + picked.transpose(1, 2)
    cost = cost + IOU_WEIGHT * -torch.log(ious + 1e-8) + OUTSIDE_COST * (~inside).float()
    cost = cost.masked_fill(~cand[:, None] | ~gt_valid[:, :, None], float("inf"))
    k = min(TOP_K_IOU, A)
    dynamic_k = ious.topk(k, dim=2).values.sum(dim=2).int().clamp_min(1) * gt_valid
    ranks = torch.empty_like(cost, dtype=torch.long)
    ranks.scatter_(2, cost.argsort(dim=2), torch.arange(A, device=cost.device).expand_as(ranks))
    matching = (ranks < dynamic_k[..., None]) & cand[:, None]
    best = cost.argmin(dim=1)  # (B, A): the cheapest GT of each anchor
    shared = matching.sum(dim=1) > 1
    one = torch.nn.functional.one_hot(best, gt_boxes.shape[1]).transpose(1, 2).bool()
    matching = torch.where(shared[:, None], one, matching)
    fg = matching.any(dim=1)
    gt_index = torch.where(fg, matching.float().argmax(dim=1), -1)
    iou = torch.where(fg, ious.gather(1, gt_index.clamp_min(0)[:, None])[:, 0], 0.0)
    return BatchAssignment(fg, gt_index, iou)
