"""GDR-Net-like pose network: ResNet backbone, dense geometry head, Patch-PnP (plain torch).

::

    roi_img  B×3×S_in×S_in ──backbone (stride 32)──> B×8w×(S_in/32)²
      ──geometry head──> mask (1), xyz (3, normalised), region logits (R + 1)   @ S_out = S_in/4
      ──Patch-PnP( xyz − 0.5 ‖ roi_coord2d ‖ softmax(region[1:]) )──> rot6d (6, allocentric),
                                                                        site (δx, δy, δz)

Patch-PnP input: the predicted normalised xyz minus 0.5, i.e. object coordinates about the bbox
centre in units of the model's max extent. GDR-Net de-normalises to metres instead; for a
single object the two differ by a constant factor that the first convolution absorbs, and the
network needs no model size. The backbone trains from scratch (no pretrained weights offline).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from bopsurg.models.pose.config import PoseConfig

# fc_rot's bias starts at the identity's 6D code so Gram-Schmidt starts well conditioned
# (GDR-Net starts at ~0, where the normalisation's gradient is huge).
_IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def _groups(channels: int) -> int:
    """GroupNorm groups: at most 32, at least 4 channels each, dividing ``channels``."""
    g = min(32, max(1, channels // 4))
    while channels % g:
        g -= 1
    return g


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "gn":
        return nn.GroupNorm(_groups(channels), channels)
    return nn.BatchNorm2d(channels)


def _conv_norm_act(cin: int, cout: int, norm: str, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 3, stride, 1, bias=False), _norm(norm, cout), nn.GELU()]


class BasicBlock(nn.Module):
    """ResNet basic block: two 3×3 convs and a (projected when needed) shortcut."""

    #: The norms applied right after the convolutions (with ``norm="bn"``, they fold into
    #: them: :func:`bopsurg.models.inference.fold_batchnorm`).
    FOLDS = (("conv1", "norm1"), ("conv2", "norm2"))

    def __init__(self, cin: int, cout: int, stride: int, norm: str) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.norm1 = _norm(norm, cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.norm2 = _norm(norm, cout)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or cin != cout:
            self.shortcut = nn.Sequential(
                nn.Conv2d(cin, cout, 1, stride, bias=False), _norm(norm, cout)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = self.norm2(self.conv2(y))
        return F.relu(y + self.shortcut(x))


class Backbone(nn.Module):
    """ResNet-18/34 layout (stem, 4 stages of BasicBlocks), widths w, 2w, 4w, 8w, stride 32."""

    def __init__(self, cfg: PoseConfig) -> None:
        super().__init__()
        w = cfg.backbone_width
        self.stem = nn.Sequential(
            nn.Conv2d(3, w, 7, 2, 3, bias=False),
            _norm(cfg.norm, w),
            nn.ReLU(),
            nn.MaxPool2d(3, 2, 1),
        )
        stages: list[nn.Module] = []
        cin = w
        for i, n in enumerate(cfg.blocks):
            cout = w * 2**i
            stride = 2 if i else 1  # the stem already has stride 4
            blocks = [BasicBlock(cin, cout, stride, cfg.norm)]
            blocks += [BasicBlock(cout, cout, 1, cfg.norm) for _ in range(n - 1)]
            stages.append(nn.Sequential(*blocks))
            cin = cout
        self.stages = nn.Sequential(*stages)
        self.out_channels = cin
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, S_in, S_in) → (B, 8w, S_in/32, S_in/32)."""
        out: torch.Tensor = self.stages(self.stem(x))
        return out


class GeometryHead(nn.Module):
    """Deconv ×2, then 3 × [2 convs] with bilinear ×2 between them, then a 1×1 output conv."""

    def __init__(self, cin: int, cfg: PoseConfig) -> None:
        super().__init__()
        c = cfg.head_channels
        layers: list[nn.Module] = [
            nn.ConvTranspose2d(cin, c, 3, 2, 1, output_padding=1, bias=False),
            _norm(cfg.norm, c),
            nn.GELU(),
        ]
        for i in range(3):
            if i:
                layers.append(nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False))
            layers += _conv_norm_act(c, c, cfg.norm) + _conv_norm_act(c, c, cfg.norm)
        self.body = nn.Sequential(*layers)
        self.out = nn.Conv2d(c, 1 + 3 + cfg.num_regions + 1, 1)
        for m in self.body.modules():
            if isinstance(m, nn.Conv2d | nn.ConvTranspose2d):
                nn.init.normal_(m.weight, std=0.001)
        nn.init.normal_(self.out.weight, std=0.01)
        assert self.out.bias is not None  # made with a bias
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 8w, S_in/32, S_in/32) → (B, 1 + 3 + R + 1, S_out, S_out)."""
        out: torch.Tensor = self.out(self.body(x))
        return out


class PatchPnP(nn.Module):
    """3 stride-2 convs, flatten, FC pnp_fc, FC 256, then the rot6d and SITE outputs."""

    def __init__(self, cfg: PoseConfig) -> None:
        super().__init__()
        c = cfg.pnp_channels
        cin = 3 + 2 + cfg.num_regions
        self.convs = nn.Sequential(
            *_conv_norm_act(cin, c, cfg.norm, 2),
            *_conv_norm_act(c, c, cfg.norm, 2),
            *_conv_norm_act(c, c, cfg.norm, 2),
        )
        flat = c * (cfg.roi_out // 8) ** 2
        self.fcs = nn.Sequential(
            nn.Flatten(),
            nn.Linear(flat, cfg.pnp_fc),
            nn.LeakyReLU(0.1),
            nn.Linear(cfg.pnp_fc, 256),
            nn.LeakyReLU(0.1),
        )
        self.fc_rot = nn.Linear(256, 6)
        self.fc_t = nn.Linear(256, 3)
        for m in self.modules():
            if isinstance(m, nn.Conv2d | nn.Linear):
                nn.init.normal_(m.weight, std=0.001)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        for fc in (self.fc_rot, self.fc_t):
            nn.init.normal_(fc.weight, std=0.01)
        with torch.no_grad():
            self.fc_rot.bias.copy_(torch.tensor(_IDENTITY_6D))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 5 + R, S_out, S_out) → rot6d (B, 6), site (B, 3)."""
        h = self.fcs(self.convs(x))
        return self.fc_rot(h), self.fc_t(h)


def mask_probability(mask: torch.Tensor, cfg: PoseConfig) -> torch.Tensor:
    """The raw "mask" output as a foreground probability in [0, 1] (sigmoid of the logits for
    ``mask_loss="bce"``, the clamped regression for ``"l1"``)."""
    return torch.sigmoid(mask) if cfg.mask_loss == "bce" else mask.clamp(0.0, 1.0)


class GdrPoseNet(nn.Module):
    """The whole pose head; see the module docstring for the data flow."""

    def __init__(self, cfg: PoseConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.backbone = Backbone(cfg)
        self.head = GeometryHead(self.backbone.out_channels, cfg)
        self.pnp = PatchPnP(cfg)

    def forward(self, roi_img: torch.Tensor, roi_coord2d: torch.Tensor) -> dict[str, torch.Tensor]:
        """Predict the geometry maps and the pose encodings of B ROIs.

        Args:
            roi_img: (B, 3, S_in, S_in) RGB in [0, 1].
            roi_coord2d: (B, 2, S_out, S_out) from :func:`~.roi.roi_coord_2d`.

        Returns:
            ``"mask"`` (B, 1, S_out, S_out) raw (logits with ``mask_loss="bce"``, the
            L1-regressed value with ``"l1"``; :func:`mask_probability` maps both), ``"xyz"``
            (B, 3, S_out, S_out) normalised, ``"region"`` (B, R + 1, S_out, S_out) logits
            (channel 0 = background), ``"rot6d"`` (B, 6) allocentric, ``"site"`` (B, 3).
        """
        maps = self.head(self.backbone(roi_img))
        mask, xyz, region = maps[:, :1], maps[:, 1:4], maps[:, 4:]
        pnp_in = torch.cat([xyz - 0.5, roi_coord2d, F.softmax(region[:, 1:], dim=1)], dim=1)
        if self.cfg.mask_attention:
            pnp_in = pnp_in * mask_probability(mask, self.cfg)
        rot6d, site = self.pnp(pnp_in)
        return {"mask": mask, "xyz": xyz, "region": region, "rot6d": rot6d, "site": site}
