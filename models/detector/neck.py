"""PAFPN neck: a top-down then a bottom-up path over the C3, C4, C5 features."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .blocks import BaseConv, CSPLayer, conv3x3


class PAFPN(nn.Module):
    """Path-aggregation FPN (YOLOX layout). Input and output channels are equal per level.

    ``channels`` = (c3, c4, c5) of the backbone; outputs P3, P4, P5 have the same channels
    and strides (8, 16, 32).
    """

    def __init__(
        self, channels: tuple[int, int, int], depth: float = 0.33, depthwise: bool = False
    ) -> None:
        super().__init__()
        c3, c4, c5 = channels
        n = round(3 * depth)

        def csp(c_in: int, c_out: int) -> CSPLayer:
            return CSPLayer(c_in, c_out, n=n, shortcut=False, depthwise=depthwise)

        # top-down
        self.lateral_conv0 = BaseConv(c5, c4, 1)
        self.csp_p4 = csp(2 * c4, c4)
        self.reduce_conv1 = BaseConv(c4, c3, 1)
        self.csp_p3 = csp(2 * c3, c3)
        # bottom-up
        self.bu_conv2 = conv3x3(c3, c3, stride=2, depthwise=depthwise)
        self.csp_n3 = csp(2 * c3, c4)
        self.bu_conv1 = conv3x3(c4, c4, stride=2, depthwise=depthwise)
        self.csp_n4 = csp(2 * c4, c5)
        self.out_channels = (c3, c4, c5)

    def forward(self, feats: tuple[Tensor, Tensor, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """(C3, C4, C5) -> (P3, P4, P5), same shapes."""
        c3, c4, c5 = feats
        lat5 = self.lateral_conv0(c5)  # c4 channels at stride 32
        f4 = self.csp_p4(torch.cat((F.interpolate(lat5, scale_factor=2.0), c4), dim=1))
        lat4 = self.reduce_conv1(f4)  # c3 channels at stride 16
        p3 = self.csp_p3(torch.cat((F.interpolate(lat4, scale_factor=2.0), c3), dim=1))
        p4 = self.csp_n3(torch.cat((self.bu_conv2(p3), lat4), dim=1))
        p5 = self.csp_n4(torch.cat((self.bu_conv1(p4), lat5), dim=1))
        return p3, p4, p5
