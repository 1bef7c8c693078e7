"""Decoupled anchor-free head: one prediction per grid cell and pyramid level."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from .blocks import BaseConv, conv3x3

#: Initial bias of the objectness and class logits: sigmoid(bias) = 0.01, so the many
#: background cells do not dominate the first steps (focal-loss prior).
PRIOR_BIAS = -math.log((1 - 0.01) / 0.01)


class LevelHead(nn.Module):
    """Head of one pyramid level: (B, C, h, w) -> (B, 5 + num_classes, h, w).

    Output channels: [tx, ty, tw, th, obj_logit, cls_logits...] (raw, see ``model.decode``).
    """

    def __init__(self, c_in: int, hidden: int, num_classes: int, depthwise: bool = False) -> None:
        super().__init__()
        self.stem = BaseConv(c_in, hidden, 1)
        self.cls_convs = nn.Sequential(
            conv3x3(hidden, hidden, depthwise=depthwise),
            conv3x3(hidden, hidden, depthwise=depthwise),
        )
        self.reg_convs = nn.Sequential(
            conv3x3(hidden, hidden, depthwise=depthwise),
            conv3x3(hidden, hidden, depthwise=depthwise),
        )
        self.cls_pred = nn.Conv2d(hidden, num_classes, 1)
        self.reg_pred = nn.Conv2d(hidden, 4, 1)
        self.obj_pred = nn.Conv2d(hidden, 1, 1)
        for layer in (self.cls_pred, self.obj_pred):
            assert layer.bias is not None  # made with a bias
            nn.init.constant_(layer.bias, PRIOR_BIAS)

    def forward(self, x: Tensor) -> Tensor:
        x = self.stem(x)
        reg = self.reg_convs(x)
        return torch.cat(
            (self.reg_pred(reg), self.obj_pred(reg), self.cls_pred(self.cls_convs(x))), 1
        )


class DecoupledHead(nn.Module):
    """One :class:`LevelHead` per level (weights not shared), ``hidden = int(256·width)``."""

    def __init__(
        self,
        channels: tuple[int, ...],
        num_classes: int,
        width: float = 0.25,
        depthwise: bool = False,
    ) -> None:
        super().__init__()
        hidden = int(256 * width)
        self.levels = nn.ModuleList(LevelHead(c, hidden, num_classes, depthwise) for c in channels)

    def forward(self, feats: tuple[Tensor, ...]) -> list[Tensor]:
        """Per level (B, 5 + num_classes, h_l, w_l)."""
        return [head(f) for head, f in zip(self.levels, feats, strict=True)]
