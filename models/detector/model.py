"""YoloxDetector: CSPDarknet + PAFPN + decoupled head, with loss, decoding and detection.

Input images are (B, 3, H, W) float RGB in [0, 1] (no mean/std normalisation), letterboxed
to ``cfg.input_hw`` (see :mod:`.boxes`). Every box is in input pixels, xyxy.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor, nn

from .anchors import decode_boxes, make_anchors
from .backbone import CSPDarknet
from .boxes import batched_nms, cxcywh_to_xyxy
from .config import DetectorConfig
from .head import DecoupledHead
from .loss import yolox_loss
from .neck import PAFPN

logger = logging.getLogger(__name__)

#: Candidates kept (by score) per image before NMS.
PRE_NMS_TOP_K = 1000


class YoloxDetector(nn.Module):
    """A YOLOX-like anchor-free detector (one prediction per grid cell of strides 8, 16, 32)."""

    def __init__(self, cfg: DetectorConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.backbone = CSPDarknet(cfg.depth, cfg.width, cfg.depthwise)
        self.neck = PAFPN(self.backbone.out_channels, cfg.depth, cfg.depthwise)
        self.head = DecoupledHead(self.neck.out_channels, cfg.num_classes, cfg.width, cfg.depthwise)
        # (input_hw, device) -> (grid, strides); grids are rebuilt only for new sizes/devices
        self._anchor_cache: dict[tuple[tuple[int, int], torch.device], tuple[Tensor, Tensor]] = {}
        self._last_input_hw: tuple[int, int] | None = None
        logger.debug(
            "YoloxDetector %s: %.2f M parameters",
            cfg.to_dict(),
            sum(p.numel() for p in self.parameters()) / 1e6,
        )

    # ------------------------------------------------------------------ network
    def forward(self, images: Tensor) -> Tensor:
        """Raw predictions.

        Args:
            images: (B, 3, H, W) float RGB in [0, 1]; H and W multiples of 32 (normally
                ``cfg.input_hw``).

        Returns:
            (B, A, 5 + C) [tx, ty, tw, th, obj_logit, cls_logits...], levels concatenated in
            stride order, cells row-major; A = Σ_l (H/s_l)·(W/s_l).
        """
        hw = (int(images.shape[-2]), int(images.shape[-1]))
        step = max(self.cfg.strides)
        if images.dim() != 4 or images.shape[1] != 3 or hw[0] % step or hw[1] % step:
            raise ValueError(
                f"expected (B, 3, H, W) with H, W multiples of {step}, got {tuple(images.shape)}"
            )
        outs = self.head(self.neck(self.backbone(images)))
        self._last_input_hw = hw
        return torch.cat([o.flatten(2).transpose(1, 2) for o in outs], dim=1)

    # ------------------------------------------------------------------ anchors
    def anchors(self, input_hw: tuple[int, int], device: torch.device) -> tuple[Tensor, Tensor]:
        """Cached (grid (A, 2), strides (A,)) for an input size, on ``device``."""
        key = ((int(input_hw[0]), int(input_hw[1])), torch.device(device))
        if key not in self._anchor_cache:
            # built as normal tensors even under inference_mode, so the cached grid can later
            # take part in a training step's autograd graph
            with torch.inference_mode(False):
                self._anchor_cache[key] = make_anchors(key[0], self.cfg.strides, key[1])
        return self._anchor_cache[key]

    def _resolve_input_hw(self, raw: Tensor, input_hw: tuple[int, int] | None) -> tuple[int, int]:
        """The input size ``raw`` came from: ``input_hw`` if given, else that of the latest
        forward call or ``cfg.input_hw``, whichever matches the number of anchors."""
        options = [input_hw] if input_hw is not None else [self._last_input_hw, self.cfg.input_hw]
        for hw in options:
            if (
                hw is not None
                and sum((hw[0] // s) * (hw[1] // s) for s in self.cfg.strides) == raw.shape[1]
            ):
                return hw
        raise ValueError(
            f"{raw.shape[1]} anchors match none of the input sizes {options}; pass input_hw="
        )

    # ------------------------------------------------------------------ training
    def loss(
        self,
        raw: Tensor,
        targets: list[Tensor],
        use_l1: bool = False,
        *,
        input_hw: tuple[int, int] | None = None,
    ) -> dict[str, Tensor]:
        """YOLOX loss of raw predictions (see :mod:`.loss`).

        Args:
            raw: (B, A, 5 + C) from :meth:`forward`.
            targets: B tensors (n_i, 5) [class, x1, y1, x2, y2] in input px (n_i may be 0).
            use_l1: add the L1 term on the raw box parameters.
            input_hw: input (H, W) of ``raw``; by default the latest forward's or cfg's.

        Returns:
            "iou", "obj", "cls", "l1", "total" scalars and "num_fg".
        """
        grid, strides = self.anchors(self._resolve_input_hw(raw, input_hw), raw.device)
        return yolox_loss(raw, targets, grid, strides, self.cfg.num_classes, use_l1)

    # ------------------------------------------------------------------ inference
    def decode(self, raw: Tensor, *, input_hw: tuple[int, int] | None = None) -> Tensor:
        """Raw (B, A, 5 + C) -> (B, A, 4 + 1 + C): x1, y1, x2, y2 (input px), obj, cls probs."""
        grid, strides = self.anchors(self._resolve_input_hw(raw, input_hw), raw.device)
        raw = raw.float()
        boxes = cxcywh_to_xyxy(decode_boxes(raw[..., :4], grid, strides))
        return torch.cat((boxes, raw[..., 4:].sigmoid()), dim=-1)

    @torch.no_grad()
    def detect(
        self,
        images: Tensor,
        conf_thr: float = 0.01,
        nms_thr: float = 0.65,
        max_det: int = 100,
    ) -> list[Tensor]:
        """Detections per image.

        Runs the network in eval mode (BatchNorm running statistics) and restores the previous
        mode afterwards.

        Args:
            images: (B, 3, H, W) as for :meth:`forward`.
            conf_thr: minimum score = obj prob · best class prob.
            nms_thr: class-aware NMS IoU threshold.
            max_det: at most this many detections per image.

        Returns:
            B tensors (k, 6): x1, y1, x2, y2 (input px, clipped to the input), score, class id
            (as float), by decreasing score.
        """
        was_training = self.training
        self.eval()
        try:
            raw = self(images)
        finally:
            self.train(was_training)
        h, w = images.shape[-2:]
        dec = self.decode(raw, input_hw=(h, w))
        limits = dec.new_tensor([w, h, w, h])
        results = []
        for d in dec:
            cls_prob, cls_id = d[:, 5:].max(dim=1)
            score = d[:, 4] * cls_prob
            keep = (score >= conf_thr).nonzero().squeeze(1)
            if len(keep) > PRE_NMS_TOP_K:
                keep = keep[score[keep].topk(PRE_NMS_TOP_K).indices]
            boxes = torch.minimum(d[keep, :4].clamp_min(0), limits)
            kept = batched_nms(boxes, score[keep], cls_id[keep], nms_thr)[:max_det]
            results.append(
                torch.cat(
                    (boxes[kept], score[keep][kept, None], cls_id[keep][kept, None].float()), dim=1
                )
            )
        return results
