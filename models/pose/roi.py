"""Square ROIs: Dynamic Zoom-In boxes, batched crops and the ROI's 2D image coordinates.

A ROI is a square of side ``side`` px centred at ``centre`` px, resampled to ``S × S``. As in
CenterNet's affine (and GDR-Net's crops), output pixel u takes the image at
``centre + (u − S/2) · side/S`` (OpenCV pixel-centre coordinates), so the crop equals
``cv2.warpAffine`` with that transform. Crops use ``F.affine_grid`` + ``F.grid_sample``
(no torchvision), run batched, and follow the device of their inputs.

Boxes are BOP boxes ``(x, y, w, h)`` in px with ``w = x_max − x_min`` over pixel indices, so the
box centre is ``(x + w/2, y + h/2)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

if TYPE_CHECKING:
    from bopsurg.models.pose.config import PoseConfig


def dzi_boxes(
    boxes_xywh: torch.Tensor,
    gen: torch.Generator | None,
    cfg: PoseConfig | tuple[float, float, float],
    image_hw: tuple[int, int],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dynamic Zoom-In: the square crop (centre, side) of each box, jittered at train time.

    Train (``gen`` given): ``side = pad · max(w, h) · U(1 − scale, 1 + scale)`` and
    ``centre = box centre + (w, h) · U(−shift, shift)²``. Test (``gen=None``): no jitter,
    ``side = pad · max(w, h)``. The side is clipped to ``[1, max(H, W)]`` px. SITE targets must
    use the returned centre but the box's own (un-jittered) w and h.

    Args:
        boxes_xywh: (B, 4) BOP boxes (x, y, w, h), px.
        gen: random generator for the jitter (any device), or None at test time.
        cfg: a :class:`PoseConfig` or ``(scale, shift, pad)``.
        image_hw: (H, W) of the image, px.

    Returns:
        centre (B, 2) px and side (B,) px, on the device and dtype of ``boxes_xywh``.
    """
    if isinstance(cfg, tuple):
        scale, shift, pad = cfg
    else:
        scale, shift, pad = cfg.dzi_scale, cfg.dzi_shift, cfg.dzi_pad
    xy, wh = boxes_xywh[:, :2], boxes_xywh[:, 2:]
    centre = xy + 0.5 * wh
    side = pad * wh.max(dim=1).values
    if gen is not None:
        n = boxes_xywh.shape[0]
        u = torch.rand((n, 3), generator=gen, device=gen.device, dtype=boxes_xywh.dtype)
        u = u.to(boxes_xywh.device)
        centre = centre + wh * shift * (2.0 * u[:, :2] - 1.0)
        side = side * (1.0 + scale * (2.0 * u[:, 2] - 1.0))
    return centre, side.clamp(1.0, float(max(image_hw)))


def crop_theta(
    centre: torch.Tensor, side: torch.Tensor, out_size: int, image_hw: tuple[int, int]
) -> torch.Tensor:
    """``F.affine_grid`` matrices of the ROI crops (``align_corners=False``).

    ``θ = [[s/W, 0, (2c_x + 1 − s/S)/W − 1], [0, s/H, (2c_y + 1 − s/S)/H − 1]]``: output pixel u
    samples image x = ``c_x + (u − S/2) · s/S`` (the CenterNet affine), same for y.

    Args:
        centre: (B, 2) crop centres, px.
        side: (B,) crop sides, px.
        out_size: S, the output side, px.
        image_hw: (H, W) of the source images, px.

    Returns:
        (B, 2, 3) affine matrices in normalised coordinates, dtype of ``centre``.
    """
    img_h, img_w = image_hw
    zero = torch.zeros_like(side)
    row_x = [side / img_w, zero, (2.0 * centre[:, 0] + 1.0 - side / out_size) / img_w - 1.0]
    row_y = [zero, side / img_h, (2.0 * centre[:, 1] + 1.0 - side / out_size) / img_h - 1.0]
    return torch.stack([torch.stack(row_x, dim=1), torch.stack(row_y, dim=1)], dim=1)


def crop(
    images: torch.Tensor,
    centre: torch.Tensor,
    side: torch.Tensor,
    out_size: int,
    mode: str = "bilinear",
    *,
    index: torch.Tensor | None = None,
) -> torch.Tensor:
    """Square ROI crops of images (zeros outside the image).

    Use ``"bilinear"`` for RGB and ``"nearest"`` for masks, region labels and xyz maps. Integer
    and bool inputs are sampled as float and returned in their own dtype.

    Args:
        images: (B, C, H, W) one image per ROI, or (N, C, H, W) with ``index``.
        centre: (B, 2) crop centres, px.
        side: (B,) crop sides, px.
        out_size: S, the output side, px.
        mode: ``"bilinear"`` or ``"nearest"``.
        index: (B,) long, the image of each ROI (several ROIs may share one image).

    Returns:
        (B, C, S, S) crops.
    """
    if index is not None and len(index) > 1:
        return _crop_shared(images, centre, side, out_size, mode, index)
    if index is not None:  # one ROI: a view of its image (a gathered copy costs more)
        images = images.narrow(0, int(index[0]), 1)
    n, c, img_h, img_w = images.shape
    src = images if images.is_floating_point() else images.float()
    theta = crop_theta(centre, side, out_size, (img_h, img_w)).to(src.dtype)
    grid = F.affine_grid(theta, [n, c, out_size, out_size], align_corners=False)
    out = F.grid_sample(src, grid, mode=mode, padding_mode="zeros", align_corners=False)
    if images.is_floating_point():
        return out
    return out.round().to(images.dtype)


def _crop_shared(
    images: torch.Tensor,
    centre: torch.Tensor,
    side: torch.Tensor,
    out_size: int,
    mode: str,
    index: torch.Tensor,
) -> torch.Tensor:
    """:func:`crop` of ROIs on images shared between them: the ROIs of each image crop an
    expanded view of it (grid_sample needs one image per grid; a gathered copy per ROI costs
    more than the sampling), the same crops as from the gathered copies."""
    uniq, inverse = torch.unique(index, return_inverse=True)
    if len(uniq) == len(index):
        return crop(images[index], centre, side, out_size, mode)
    parts = []
    for k in range(len(uniq)):
        rows = (inverse == k).nonzero().squeeze(1)
        view = images[uniq[k] : uniq[k] + 1].expand(len(rows), -1, -1, -1)
        parts.append((rows, crop(view, centre[rows], side[rows], out_size, mode)))
    out = parts[0][1].new_empty((len(index), *parts[0][1].shape[1:]))
    for rows, part in parts:
        out[rows] = part
    return out


def roi_grid_to_image(centre: torch.Tensor, side: torch.Tensor, out_size: int) -> torch.Tensor:
    """Image position of every ROI pixel: ``centre + (u − S/2) · side/S``.

    Args:
        centre: (B, 2) crop centres, px.
        side: (B,) crop sides, px.
        out_size: S, the ROI side, px (``roi_out`` for the geometry maps).

    Returns:
        (B, S, S, 2) image (x, y), px, indexed [b, row, col].
    """
    S = out_size
    steps = torch.arange(S, dtype=centre.dtype, device=centre.device) - S / 2
    offsets = steps[None, :] * (side / S)[:, None]  # (B, S)
    x = centre[:, 0, None] + offsets  # varies along columns
    y = centre[:, 1, None] + offsets  # varies along rows
    n = centre.shape[0]
    return torch.stack([x[:, None, :].expand(n, S, S), y[:, :, None].expand(n, S, S)], dim=-1)


def roi_coord_2d(
    centre: torch.Tensor, side: torch.Tensor, out_size: int, image_hw: tuple[int, int]
) -> torch.Tensor:
    """Image-normalised coordinates of the ROI pixels (the Patch-PnP's "where is the crop").

    Convention: image pixel (u, v) has coordinates ``((u + ½)/W, (v + ½)/H)``, so the image spans
    exactly [0, 1]² (GDR-Net uses ``linspace(0, 1, W)`` instead, a ~1/W difference). Computed
    analytically; equals bilinearly cropping the coordinate image with :func:`crop` wherever
    the ROI lies inside the image, and keeps extending linearly outside it (no zero padding).

    Args:
        centre: (B, 2) crop centres, px.
        side: (B,) crop sides, px.
        out_size: S, the map side, px (``roi_out``).
        image_hw: (H, W) of the image, px.

    Returns:
        (B, 2, S, S): channel 0 is x, channel 1 is y.
    """
    img_h, img_w = image_hw
    wh = torch.tensor([img_w, img_h], dtype=centre.dtype, device=centre.device)
    coords = (roi_grid_to_image(centre, side, out_size) + 0.5) / wh
    return coords.permute(0, 3, 1, 2).contiguous()
