"""CSPDarknet backbone: image (B, 3, H, W) -> features C3, C4, C5 at strides 8, 16, 32."""

from __future__ import annotations

from torch import Tensor, nn

from .blocks import CSPLayer, Focus, SPPBottleneck, conv3x3


class CSPDarknet(nn.Module):
    """YOLOX's CSPDarknet.

    With ``base = int(64·width)`` the outputs have 4·base, 8·base and 16·base channels
    (64/128/256 for width 0.25). H and W must be multiples of 32.
    """

    def __init__(self, depth: float = 0.33, width: float = 0.25, depthwise: bool = False) -> None:
        super().__init__()
        base = int(64 * width)
        d = max(round(3 * depth), 1)

        def stage(c_in: int, c_out: int, n: int) -> nn.Sequential:
            return nn.Sequential(
                conv3x3(c_in, c_out, stride=2, depthwise=depthwise),
                CSPLayer(c_out, c_out, n=n, depthwise=depthwise),
            )

        self.stem = Focus(3, base, k=3)  # stride 2
        self.dark2 = stage(base, 2 * base, d)  # stride 4
        self.dark3 = stage(2 * base, 4 * base, 3 * d)  # stride 8
        self.dark4 = stage(4 * base, 8 * base, 3 * d)  # stride 16
        self.dark5 = nn.Sequential(  # stride 32
            conv3x3(8 * base, 16 * base, stride=2, depthwise=depthwise),
            SPPBottleneck(16 * base, 16 * base),
            CSPLayer(16 * base, 16 * base, n=d, shortcut=False, depthwise=depthwise),
        )
        self.out_channels = (4 * base, 8 * base, 16 * base)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(B, 3, H, W) -> C3 (B, 4b, H/8, W/8), C4 (B, 8b, H/16, W/16), C5 (B, 16b, H/32, W/32)."""
        c2 = self.dark2(self.stem(x))
        c3 = self.dark3(c2)
        c4 = self.dark4(c3)
        c5 = self.dark5(c4)
        return c3, c4, c5
