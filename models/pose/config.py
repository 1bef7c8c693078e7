"""Configuration of the GDR-Net-like pose head: sizes, DZI jitter, SITE units, loss weights.

One frozen dataclass that the data loader, the network, the losses and the decoders all read,
so a size (``roi_in``, ``num_regions``) is set in exactly one place. Presets:

- ``"cpu"`` (default): ResNet-18 layout at half width, ROI 128 → 32×32 maps, 32 regions.
- ``"paper"``: ResNet-34 layout, ROI 256 → 64×64 maps, 64 regions, head 256 (GDR-Net sizes).
- ``"test"``: a tiny network (ROI 64 → 16×16 maps, 8 regions) for unit tests.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

#: Fields that only shape training (loss weights, train-time DZI jitter): a run may change
#: them and still start from (``recipe.init``) a checkpoint trained with other values.
TRAINING_ONLY = frozenset(
    {"w_mask", "w_xyz", "w_region", "w_pm", "w_centroid", "w_z", "mask_loss", "dzi_scale",
     "dzi_shift", "symmetric"}
)  # fmt: skip

NORMS = ("gn", "bn")
MASK_LOSSES = ("bce", "l1")


@dataclass(frozen=True)
class PoseConfig:
    """Sizes and weights of the pose head (lengths in px unless noted)."""

    roi_in: int = 128  # ROI input side S_in, px (multiple of 32: the backbone stride)
    num_regions: int = 32  # R surface regions (FPS points); region logits have R + 1 channels
    backbone_width: int = 32  # stage widths w, 2w, 4w, 8w; stride 32
    blocks: tuple[int, int, int, int] = (2, 2, 2, 2)  # BasicBlocks per stage (ResNet-18)
    head_channels: int = 64
    pnp_channels: int = 128
    pnp_fc: int = 512  # first Patch-PnP FC width; the second is 256
    norm: str = "gn"  # "gn" (GroupNorm, safe for small batches) or "bn"
    mask_attention: bool = False  # multiply the Patch-PnP input by the predicted mask
    # "bce": sigmoid + BCE on the area-averaged mask (the fraction of each map cell the object
    # covers). "l1": GDR-Net's raw L1 on a 0/1 mask; a wire thinner than a cell is mostly
    # background there, so L1's median-seeking optimum is an empty mask (measured: max 0.001).
    mask_loss: str = "bce"
    dzi_pad: float = 1.5  # crop side = pad · max(w, h)
    dzi_scale: float = 0.25  # train: side · U(1 − scale, 1 + scale)
    dzi_shift: float = 0.25  # train: centre + (w, h) · U(−shift, shift)
    z_unit_mm: float = 1000.0  # SITE δz is predicted in metres (as GDR-Net) so it is O(0.1-1)
    symmetric: bool = False  # closest-symmetry PM loss with the given symmetry rotations
    w_mask: float = 1.0
    w_xyz: float = 1.0
    w_region: float = 1.0
    w_pm: float = 1.0
    w_centroid: float = 1.0
    w_z: float = 1.0

    def __post_init__(self) -> None:
        if self.roi_in <= 0 or self.roi_in % 32:
            raise ValueError(f"roi_in must be a positive multiple of 32, got {self.roi_in}")
        if self.norm not in NORMS:
            raise ValueError(f"norm must be one of {NORMS}, got {self.norm!r}")
        if self.mask_loss not in MASK_LOSSES:
            raise ValueError(f"mask_loss must be one of {MASK_LOSSES}, got {self.mask_loss!r}")
        if len(self.blocks) != 4 or min(self.blocks) < 1:
            raise ValueError(f"blocks must be 4 positive counts, got {self.blocks}")
        if self.num_regions < 1:
            raise ValueError(f"num_regions must be >= 1, got {self.num_regions}")
        # a list from JSON/YAML becomes the hashable tuple the frozen dataclass expects
        object.__setattr__(self, "blocks", tuple(int(b) for b in self.blocks))

    @property
    def roi_out(self) -> int:
        """Side of the geometry maps (mask, xyz, region), px: S_in / 4."""
        return self.roi_in // 4

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (``blocks`` as a list)."""
        d = dataclasses.asdict(self)
        d["blocks"] = list(self.blocks)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PoseConfig:
        """Inverse of :meth:`to_dict`; raises ``ValueError`` naming an unknown key."""
        known = {f.name for f in dataclasses.fields(cls)}
        for key in d:
            if key not in known:
                raise ValueError(f"unknown PoseConfig key: {key!r}")
        return cls(**d)

    @classmethod
    def preset(cls, name: str) -> PoseConfig:
        """``"cpu"`` (the defaults), ``"paper"`` (GDR-Net sizes) or ``"test"`` (tiny)."""
        presets: dict[str, dict[str, Any]] = {
            "cpu": {},
            "paper": {
                "roi_in": 256,
                "num_regions": 64,
                "backbone_width": 64,
                "blocks": (3, 4, 6, 3),
                "head_channels": 256,
                "pnp_fc": 1024,
            },
            "test": {
                "roi_in": 64,
                "num_regions": 8,
                "backbone_width": 8,
                "head_channels": 16,
                "pnp_channels": 16,
                "pnp_fc": 64,
            },
        }
        if name not in presets:
            raise ValueError(f"unknown preset {name!r}; choose from {sorted(presets)}")
        return cls(**presets[name])
