"""A light full-resolution needle segmenter: the evidence the pose fit (:mod:`.fit`) needs.

The pose head sees a 128 px ROI and predicts 32×32 maps, one cell ≈ 5 image px for a wire
4 px wide. This net sees the same square ROI (the detection box × ``pad``, around its centre)
resampled to ``roi`` px, so one output pixel is at most about one image px for the needle
sizes of the data, and predicts the needle's visible mask at that resolution: a small U-Net
(three or four stride-2 stages down, bilinear up with skips), BatchNorm + ReLU, one logit per
pixel.
With ``amodal`` it predicts a second channel, the needle's full (amodal) mask: the wire
where it is hidden too (behind the jaws, the thread, the tissue). A fit to the visible part
alone can slide and shrink the arc into that part; the full mask keeps the arc whole.

Train and test crop the same way (one bilinear ``grid_sample`` from the full image,
:func:`bopsurg.models.pose.roi.crop`), so the wire's aliasing is the same in both.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class SegConfig:
    """Sizes of the segmenter (px)."""

    roi: int = 160  # ROI side the crop is resampled to, px (a multiple of 2**stages)
    width: int = 8  # channels at full resolution; 2w, 4w, 4w below
    pad: float = 1.5  # crop side = pad · max(w, h) of the box (the pose head's test crop)
    amodal: bool = False  # also predict the full (amodal) mask, as output channel 1
    # stride-2 stages: an output pixel sees about 60 px of the ROI with 3, about 125 px with 4,
    # enough to carry the arc across an occluder as wide as half the needle (the full mask
    # needs that context)
    stages: int = 3
    # what the ROI frames, in training and at test: "visible", the visible (detection) box;
    # "whole", that box grown to the needle's whole projection (in training the full mask's
    # box, at test the start pose's projected arc), so a needle half in tissue has its hidden
    # part in view (MODEL_CARD.md, "Needle refinement")
    frame: str = "visible"

    @property
    def channels(self) -> int:
        """Output channels: 0 the visible mask, 1 the full mask (with ``amodal``)."""
        return 2 if self.amodal else 1

    def __post_init__(self) -> None:
        if self.stages not in (3, 4):
            raise ValueError(f"stages must be 3 or 4, got {self.stages}")
        if self.roi <= 0 or self.roi % 2**self.stages:  # every stage halves it exactly
            raise ValueError(f"roi must be a positive multiple of {2**self.stages}, got {self.roi}")
        if self.frame not in ("visible", "whole"):
            raise ValueError(f"frame must be 'visible' or 'whole', got {self.frame!r}")
        if self.frame == "whole" and not self.amodal:
            raise ValueError("frame 'whole' needs the full (amodal) mask: set amodal")
        if self.width < 1:
            raise ValueError(f"width must be >= 1, got {self.width}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SegConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        for key in d:
            if key not in known:
                raise ValueError(f"unknown SegConfig key: {key!r}")
        return cls(**d)


def _block(cin: int, cout: int, stride: int = 1, convs: int = 2) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(convs):
        layers += [
            nn.Conv2d(cin if i == 0 else cout, cout, 3, stride if i == 0 else 1, 1, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
        ]
    return nn.Sequential(*layers)


class NeedleSegNet(nn.Module):
    """(B, 3, S, S) RGB in [0, 1] → (B, C, S, S) needle-mask logits (C = ``cfg.channels``)."""

    def __init__(self, cfg: SegConfig) -> None:
        super().__init__()
        w = cfg.width
        self.cfg = cfg
        width = [w, 2 * w] + [4 * w] * (cfg.stages - 1)  # channels of enc0 .. enc<stages>
        self.enc0 = _block(3, w)
        for k in range(1, cfg.stages + 1):
            setattr(self, f"enc{k}", _block(width[k - 1], width[k], 2))
        # one conv per decoder stage: the full-resolution stages dominate the run time
        for k in range(cfg.stages - 1, -1, -1):
            setattr(self, f"dec{k}", _block(width[k + 1] + width[k], width[k], convs=1))
        self.out = nn.Conv2d(w, cfg.channels, 1)

    @staticmethod
    def _up(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = [self.enc0(x)]
        for k in range(1, self.cfg.stages + 1):
            skips.append(getattr(self, f"enc{k}")(skips[-1]))
        d = skips.pop()
        for k in range(self.cfg.stages - 1, -1, -1):
            e = skips.pop()
            d = getattr(self, f"dec{k}")(torch.cat([self._up(d, e), e], 1))
        out: torch.Tensor = self.out(d)
        return out


def seg_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """BCE + soft Dice per channel on the (soft, area-sampled) masks (B, C, S, S): the wire
    covers a few % of the ROI, and Dice keeps the thin foreground from being traded for
    background."""
    bce = F.binary_cross_entropy_with_logits(logits, target)
    p = torch.sigmoid(logits)
    inter = (p * target).sum((2, 3))
    dice = 1 - (2 * inter + 1) / (p.sum((2, 3)) + target.sum((2, 3)) + 1)
    return bce + dice.mean()
