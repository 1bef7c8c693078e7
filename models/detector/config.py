"""Detector configuration: model size, input size and named presets.

The sizes follow YOLOX (``depth`` scales the number of bottlenecks, ``width`` the channels).
The network input is ``input_hw = (H, W)`` in pixels; both must be multiples of the largest
stride (32) so that every pyramid level has an integer size.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

#: The strides of P3, P4 and P5: fixed by the CSPDarknet/PAFPN architecture.
ARCH_STRIDES: tuple[int, ...] = (8, 16, 32)


#: Fields a fine-tuning run (``recipe.init``) may change: the input size, since the network
#: is convolutional (the same weights run at any multiple of 32; a detector trained small
#: can be trained on at a larger input, where a thin needle has more pixels).
TRAINING_ONLY = frozenset({"input_hw"})


@dataclass(frozen=True)
class DetectorConfig:
    """Size of a YOLOX-like detector.

    Attributes:
        num_classes: number of object classes (class ids 0 .. num_classes - 1).
        depth: bottleneck multiplier (YOLOX nano/tiny/s: 0.33).
        width: channel multiplier (nano 0.25, tiny 0.375, s 0.5).
        depthwise: depthwise-separable 3×3 convs (YOLOX-nano); saves parameters, not CPU time.
        input_hw: network input (H, W) in pixels, multiples of 32. The default (256, 320) holds
            a 640×480 image letterboxed at scale 0.5 (320×240 plus 16 rows of padding).
        strides: output strides of the pyramid levels in pixels; must be (8, 16, 32).
    """

    num_classes: int = 1
    depth: float = 0.33
    width: float = 0.25
    depthwise: bool = False
    input_hw: tuple[int, int] = (256, 320)
    strides: tuple[int, ...] = ARCH_STRIDES

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        # CPU default: plain convs, 640×480 halved (about 2.2 M parameters).
        "cpu": {},
        # YOLOX-nano-like: depthwise convs (about 0.9 M parameters).
        "nano": {"depthwise": True, "input_hw": (416, 416)},
        "tiny": {"width": 0.375, "input_hw": (416, 416)},
        # YOLOX-S at full 640×480 resolution (GPU).
        "s": {"width": 0.5, "input_hw": (480, 640)},
        # Unit tests: a few hundred thousand parameters, 64×96 input.
        "test": {"width": 0.125, "depth": 0.33, "input_hw": (64, 96)},
    }

    def __post_init__(self) -> None:
        # Accept lists (from JSON) but store tuples so the config stays hashable.
        object.__setattr__(self, "input_hw", tuple(int(v) for v in self.input_hw))
        object.__setattr__(self, "strides", tuple(int(v) for v in self.strides))
        if self.num_classes < 1:
            raise ValueError(f"num_classes must be >= 1, got {self.num_classes}")
        if self.depth <= 0 or self.width <= 0:
            raise ValueError(f"depth and width must be > 0, got {self.depth}, {self.width}")
        if self.strides != ARCH_STRIDES:
            raise ValueError(
                f"strides must be {ARCH_STRIDES} (the architecture's), got {self.strides}"
            )
        if len(self.input_hw) != 2:
            raise ValueError(f"input_hw must be (H, W), got {self.input_hw}")
        step = max(self.strides)
        if any(v <= 0 or v % step for v in self.input_hw):
            raise ValueError(f"input_hw {self.input_hw} must be positive multiples of {step}")

    @classmethod
    def preset(cls, name: str = "cpu", **overrides: Any) -> DetectorConfig:
        """A named preset ("cpu", "nano", "tiny", "s", "test"), with optional field overrides."""
        if name not in cls.PRESETS:
            raise ValueError(f"unknown detector preset {name!r}; choose from {sorted(cls.PRESETS)}")
        return cls(**{**cls.PRESETS[name], **overrides})

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (tuples become lists)."""
        return {
            f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v
            for f in dataclasses.fields(self)
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DetectorConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError`` naming them."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown DetectorConfig key(s): {', '.join(unknown)}")
        return cls(**d)
