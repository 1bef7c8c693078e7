"""A light full-resolution needle segmenter: the evidence the pose fit (:mod:`.fit`) needs.

The pose head sees a 128 px ROI and predicts 32×32 maps, one cell ≈ 5 image px for a wire
4 px wide. This net sees the same square ROI (the detection box × ``pad``, around its centre)
resampled to ``roi`` px, so one output pixel is at most about one image px for the needle
sizes of the data, and predicts the needle's visible mask at that resolution: a small U-Net
(three stride-2 stages down, bilinear up with skips), BatchNorm + ReLU, one logit per pixel.
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

    roi: int = 160  # ROI side the crop is resampled to, px (multiple of 8)
    width: int = 8  # channels at full resolution; 2w, 4w, 4w below
    pad: float = 1.5  # crop side = pad · max(w, h) of the box (the pose head's test crop)

    def __post_init__(self) -> None:
        if self.roi <= 0 or self.roi % 8:
            raise ValueError(f"roi must be a positive multiple of 8, got {self.roi}")
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
    """(B, 3, S, S) RGB in [0, 1] → (B, 1, S, S) needle-mask logits."""

    def __init__(self, cfg: SegConfig) -> None:
        super().__init__()
        w = cfg.width
        self.cfg = cfg
        self.enc0 = _block(3, w)
        self.enc1 = _block(w, 2 * w, 2)
        self.enc2 = _block(2 * w, 4 * w, 2)
        self.enc3 = _block(4 * w, 4 * w, 2)
        # one conv per decoder stage: the full-resolution stages dominate the run time
        self.dec2 = _block(8 * w, 4 * w, convs=1)
        self.dec1 = _block(6 * w, 2 * w, convs=1)
        self.dec0 = _block(3 * w, w, convs=1)
        self.out = nn.Conv2d(w, 1, 1)

    @staticmethod
    def _up(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e0 = self.enc0(x)
        e1 = self.enc1(e0)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        d2 = self.dec2(torch.cat([self._up(e3, e2), e2], 1))
        d1 = self.dec1(torch.cat([self._up(d2, e1), e1], 1))
        d0 = self.dec0(torch.cat([self._up(d1, e0), e0], 1))
        return self.out(d0)


def seg_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """BCE + soft Dice on the (soft, area-sampled) visible mask: the wire covers a few % of
    the ROI, and Dice keeps the thin foreground from being traded for background."""
    bce = F.binary_cross_entropy_with_logits(logits, target)
    p = torch.sigmoid(logits)
    inter = (p * target).sum((1, 2, 3))
    dice = 1 - (2 * inter + 1) / (p.sum((1, 2, 3)) + target.sum((1, 2, 3)) + 1)
    return bce + dice.mean()
