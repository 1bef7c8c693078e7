"""Convolution blocks of CSPDarknet and PAFPN (YOLOX layout).

Every block maps (B, C_in, H, W) -> (B, C_out, H / stride, W / stride).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class BaseConv(nn.Module):
    """Conv (no bias) + BatchNorm (eps 1e-3, momentum 0.03) + SiLU; 'same' padding."""

    #: The norm applied right after the convolution (it folds into it:
    #: :func:`bopsurg.models.inference.fold_batchnorm`).
    FOLDS = (("conv", "bn"),)

    def __init__(self, c_in: int, c_out: int, k: int = 1, stride: int = 1, groups: int = 1) -> None:
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, stride, (k - 1) // 2, groups=groups, bias=False)
        self.bn = nn.BatchNorm2d(c_out, eps=1e-3, momentum=0.03)
        self.act = nn.SiLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        out: Tensor = self.act(self.bn(self.conv(x)))
        return out


class DWConv(nn.Module):
    """Depthwise k×k conv then pointwise 1×1 conv, each with BN + SiLU (YOLOX-nano)."""

    def __init__(self, c_in: int, c_out: int, k: int = 3, stride: int = 1) -> None:
        super().__init__()
        self.dconv = BaseConv(c_in, c_in, k, stride, groups=c_in)
        self.pconv = BaseConv(c_in, c_out, 1)

    def forward(self, x: Tensor) -> Tensor:
        out: Tensor = self.pconv(self.dconv(x))
        return out


def conv3x3(c_in: int, c_out: int, stride: int = 1, depthwise: bool = False) -> nn.Module:
    """The 3×3 conv used throughout: depthwise-separable or plain."""
    return DWConv(c_in, c_out, 3, stride) if depthwise else BaseConv(c_in, c_out, 3, stride)


class Bottleneck(nn.Module):
    """1×1 conv then 3×3 conv, with a residual connection when ``shortcut`` and shapes match."""

    def __init__(
        self,
        c_in: int,
        c_out: int,
        shortcut: bool = True,
        expansion: float = 1.0,
        depthwise: bool = False,
    ) -> None:
        super().__init__()
        hidden = int(c_out * expansion)
        self.conv1 = BaseConv(c_in, hidden, 1)
        self.conv2 = conv3x3(hidden, c_out, depthwise=depthwise)
        self.use_add = shortcut and c_in == c_out

    def forward(self, x: Tensor) -> Tensor:
        y = self.conv2(self.conv1(x))
        out: Tensor = x + y if self.use_add else y
        return out


class CSPLayer(nn.Module):
    """Cross-stage partial layer: half the channels go through ``n`` bottlenecks, half skip."""

    def __init__(
        self,
        c_in: int,
        c_out: int,
        n: int = 1,
        shortcut: bool = True,
        depthwise: bool = False,
    ) -> None:
        super().__init__()
        hidden = c_out // 2
        self.conv1 = BaseConv(c_in, hidden, 1)
        self.conv2 = BaseConv(c_in, hidden, 1)
        self.conv3 = BaseConv(2 * hidden, c_out, 1)
        self.m = nn.Sequential(
            *(Bottleneck(hidden, hidden, shortcut, 1.0, depthwise) for _ in range(n))
        )

    def forward(self, x: Tensor) -> Tensor:
        out: Tensor = self.conv3(torch.cat((self.m(self.conv1(x)), self.conv2(x)), dim=1))
        return out


class SPPBottleneck(nn.Module):
    """Spatial pyramid pooling: max-pools of several sizes (stride 1) concatenated."""

    def __init__(self, c_in: int, c_out: int, kernels: tuple[int, ...] = (5, 9, 13)) -> None:
        super().__init__()
        hidden = c_in // 2
        self.conv1 = BaseConv(c_in, hidden, 1)
        self.pools = nn.ModuleList(nn.MaxPool2d(k, stride=1, padding=k // 2) for k in kernels)
        self.conv2 = BaseConv(hidden * (len(kernels) + 1), c_out, 1)

    def forward(self, x: Tensor) -> Tensor:
        x = self.conv1(x)
        out: Tensor = self.conv2(torch.cat([x, *(pool(x) for pool in self.pools)], dim=1))
        return out


class Focus(nn.Module):
    """Space-to-depth 2× ((B, C, H, W) -> (B, 4C, H/2, W/2)) followed by a conv.

    H and W must be even.
    """

    def __init__(self, c_in: int, c_out: int, k: int = 3) -> None:
        super().__init__()
        self.conv = BaseConv(4 * c_in, c_out, k)

    def forward(self, x: Tensor) -> Tensor:
        tl, bl = x[..., ::2, ::2], x[..., 1::2, ::2]
        tr, br = x[..., ::2, 1::2], x[..., 1::2, 1::2]
        out: Tensor = self.conv(torch.cat((tl, bl, tr, br), dim=1))
        return out
