"""A small YOLOX-like 2D detector in plain PyTorch (no torchvision).

CSPDarknet backbone, PAFPN neck and a decoupled anchor-free head at strides 8/16/32, trained
with SimOTA assignment and the YOLOX losses. Input: (B, 3, H, W) float RGB in [0, 1],
letterboxed to ``DetectorConfig.input_hw`` (top-left, padding 114/255); boxes are xyxy in
input pixels.

Typical use::

    model = YoloxDetector(DetectorConfig.preset("cpu"))
    losses = model.loss(model(images), targets)      # targets: (n_i, 5) [cls, x1, y1, x2, y2]
    dets = model.detect(images)                       # (k, 6) [x1, y1, x2, y2, score, cls]
"""

from __future__ import annotations

from .boxes import box_iou, nms
from .config import DetectorConfig
from .letterbox import letterbox, letterbox_params
from .model import YoloxDetector

__all__ = [
    "DetectorConfig",
    "YoloxDetector",
    "box_iou",
    "letterbox",
    "letterbox_params",
    "nms",
]
