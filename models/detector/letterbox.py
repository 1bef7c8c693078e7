"""The letterbox: how an image becomes the detector's input, and how boxes map between the two.

An image of (src_h, src_w) is resized by ``scale = min(dst_h/src_h, dst_w/src_w)`` (aspect
ratio kept) and placed at the **top-left** of the (dst_h, dst_w) network input; the rest
(right and bottom) is filled with YOLOX's grey, :data:`PAD_GREY` = 114 of 255. Because the
image is not centred, mapping boxes between image and input pixels is a pure scale.

Coordinates are continuous pixels: an image of width W spans x in [0, W] and pixel i covers
[i, i + 1]; boxes are xyxy.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import Tensor

#: Letterbox padding grey of a uint8 image (YOLOX's 114 of 255).
PAD_GREY = 114
#: The same grey in [0, 1]: also the fill value of the augmentations' borders.
PAD_VALUE = PAD_GREY / 255.0


def letterbox_params(src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> tuple[float, int, int]:
    """Letterbox an image of ``src_hw`` = (H, W) into a ``dst_hw`` network input.

    Returns:
        (scale, pad_x, pad_y): the resize factor, and the padding in input pixels added on the
        right (pad_x) and at the bottom (pad_y); the image sits at the top-left, so an image
        point (x, y) lands at input (x·scale, y·scale). The resized image is
        (round(H·scale), round(W·scale)) pixels.
    """
    (sh, sw), (dh, dw) = src_hw, dst_hw
    scale = min(dh / sh, dw / sw)
    return scale, dw - round(sw * scale), dh - round(sh * scale)


def letterbox(rgb: np.ndarray, input_hw: tuple[int, int]) -> tuple[np.ndarray, float]:
    """Letterbox a uint8 image.

    Args:
        rgb: (H, W, 3) uint8 RGB.
        input_hw: network input (h, w), px.

    Returns:
        The (h, w, 3) uint8 input (padding :data:`PAD_GREY`) and the scale (input px per
        image px). Shrinking averages pixel areas, so a thin needle does not break into dashes.
    """
    h, w = input_hw
    scale, pad_x, pad_y = letterbox_params(rgb.shape[:2], input_hw)
    nh, nw = h - pad_y, w - pad_x
    out = np.full((h, w, 3), PAD_GREY, np.uint8)
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    out[:nh, :nw] = cv2.resize(rgb, (nw, nh), interpolation=interp)
    return out, scale


def image_to_input_boxes(boxes: Tensor, scale: float) -> Tensor:
    """Boxes (..., 4) xyxy in image pixels -> letterboxed input pixels."""
    return boxes * scale


def input_to_image_boxes(
    boxes: Tensor, scale: float, src_hw: tuple[int, int] | None = None
) -> Tensor:
    """Boxes (..., 4) xyxy in input pixels -> image pixels, clipped to the image if ``src_hw``."""
    out = boxes / scale
    if src_hw is not None:
        h, w = src_hw
        out = torch.minimum(out.clamp_min(0), out.new_tensor([w, h, w, h]))
    return out
