"""Visibility of GT instances: BOP's scene_gt_info fields from rendered and measured depth.

Definitions follow the reference toolkit's ``scripts/calc_gt_info.py`` and
``bop_toolkit_lib/visibility.py`` (bop19 rule):

- the object is rendered on a canvas three times the image size with the principal point
  shifted by (W, H), so the part outside the image (truncation) is counted too;
- ``px_count_all``: silhouette pixels on that large canvas;
- ``px_count_valid``: silhouette pixels inside the image with a measured depth > 0;
- ``px_count_visib``: pixels of the visibility mask ``((d_model − d_test ≤ δ) or d_test = 0)
  and d_model > 0`` on distance images (missing depth counts as visible);
- ``visib_fract = px_count_visib / px_count_all`` (0 when nothing is rendered), so it
  counts both occlusion and truncation;
- ``bbox_obj``: (x, y, w, h) of the amodal silhouette, may leave the image; ``bbox_visib``
  of the visible mask; ``w = x_max − x_min`` (no +1); both ``[-1, -1, -1, -1]`` when no pixel
  is visible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.bop.scene import EMPTY_BBOX, GtInfo, bbox_from_mask
from bopsurg.errors import ShapeError
from bopsurg.geometry import depth_to_distance
from bopsurg.metrics import estimate_visib_mask

#: Visibility tolerance δ in mm used by BOP for most datasets (5 mm for ITODD and PBR images).
DEFAULT_DELTA_MM = 15.0


@dataclass(frozen=True)
class InstanceVisibility:
    """Masks and BOP gt_info of one GT instance.

    Attributes:
        mask: (H, W) bool amodal silhouette inside the image (BOP ``mask/``).
        mask_visib: (H, W) bool visible part (BOP ``mask_visib/``).
        info: The scene_gt_info entry.
    """

    mask: NDArray[np.bool_]
    mask_visib: NDArray[np.bool_]
    info: GtInfo


def large_canvas(K: ArrayLike, width: int, height: int) -> tuple[NDArray[np.float64], int, int]:
    """BOP's 3× canvas of an image: the camera that also sees what the image truncates.

    The amodal silhouettes of :func:`instance_visibility` are rendered on it, so that parts
    of an object outside the image count in ``px_count_all``; the image is its centre.

    Args:
        K: (3, 3) camera matrix of the image, px.
        width, height: Image size, px.

    Returns:
        (K with the principal point shifted by (width, height), 3 width, 3 height).
    """
    K_large = np.array(K, dtype=np.float64)
    K_large[0, 2] += width
    K_large[1, 2] += height
    return K_large, 3 * width, 3 * height


def visib_fract(px_count_visib: int, px_count_all: int) -> float:
    """Visible fraction of the projected amodal silhouette (0 when nothing projects)."""
    return float(px_count_visib) / float(px_count_all) if px_count_all > 0 else 0.0


def instance_visibility(
    depth_test: ArrayLike,
    depth_model_large: ArrayLike,
    K: ArrayLike,
    *,
    delta: float = DEFAULT_DELTA_MM,
) -> InstanceVisibility:
    """Masks and gt_info of one GT instance, as ``calc_gt_info.py`` and ``calc_gt_masks.py``.

    Args:
        depth_test: (H, W) measured (or rendered scene) depth of the image, mm, 0 = no data.
        depth_model_large: (3H, 3W) depth of the object alone at its GT pose, rendered with the
            principal point shifted by (W, H), mm, 0 = background.
        K: (3, 3) camera matrix of the image (unshifted).
        delta: Visibility tolerance δ, mm.

    Returns:
        The instance's masks and gt_info.
    """
    d_test = np.asarray(depth_test, dtype=np.float64)
    d_large = np.asarray(depth_model_large, dtype=np.float64)
    h, w = d_test.shape
    if d_large.shape != (3 * h, 3 * w):
        raise ShapeError(
            f"expected the 3x canvas {(3 * h, 3 * w)} for a {(h, w)} image, got {d_large.shape}",
            field="depth_model_large",
        )
    d_model = d_large[h : 2 * h, w : 2 * w]
    mask = d_model > 0
    visib = np.zeros((h, w), dtype=bool)
    # Distances only where the object projects: elementwise, so the same values (bit for
    # bit) as converting the whole images, at a fraction of the cost for small objects.
    rows = np.flatnonzero(mask.any(axis=1))
    px_valid = 0
    if rows.size:
        cols = np.flatnonzero(mask.any(axis=0))
        win = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        origin = (int(rows[0]), int(cols[0]))
        dist_model = depth_to_distance(d_model[win], K, origin)
        dist_test = depth_to_distance(d_test[win], K, origin)
        visib[win] = estimate_visib_mask(dist_test, dist_model, delta, mode="bop19")
        px_valid = int(np.count_nonzero(dist_test[mask[win]] > 0))
    info = _gt_info(d_large > 0, visib, px_valid)
    return InstanceVisibility(mask=mask, mask_visib=visib, info=info)


def instance_visibility_from_masks(
    mask_large: ArrayLike, mask_visib: ArrayLike, *, depth_valid: ArrayLike | None = None
) -> GtInfo:
    """gt_info of one instance from its amodal silhouette on the 3× canvas and its visible mask.

    For data without depth (the visible mask then comes from rendering all GT instances
    against each other) or where masks are already known.

    Args:
        mask_large: (3H, 3W) amodal silhouette on the canvas shifted by (W, H).
        mask_visib: (H, W) visible mask.
        depth_valid: Optional (H, W) bool, True where a depth measurement exists; without it
            every silhouette pixel inside the image counts as valid.

    Returns:
        The scene_gt_info entry.
    """
    large = np.asarray(mask_large, dtype=bool)
    visib = np.asarray(mask_visib, dtype=bool)
    h, w = visib.shape
    if large.shape != (3 * h, 3 * w):
        raise ShapeError(
            f"expected the 3x canvas {(3 * h, 3 * w)} for a {(h, w)} image, got {large.shape}",
            field="mask_large",
        )
    inside = large[h : 2 * h, w : 2 * w]
    valid = inside if depth_valid is None else inside & np.asarray(depth_valid, dtype=bool)
    return _gt_info(large, visib, int(np.count_nonzero(valid)))


def _gt_info(large: NDArray[np.bool_], visib: NDArray[np.bool_], px_valid: int) -> GtInfo:
    """The scene_gt_info entry from the amodal 3× canvas silhouette and the visible mask."""
    h, w = visib.shape
    px_all = int(np.count_nonzero(large))
    px_visib = int(np.count_nonzero(visib))
    visible = px_visib > 0
    return GtInfo(
        bbox_obj=bbox_from_mask(large, (w, h)) if visible else EMPTY_BBOX,
        bbox_visib=bbox_from_mask(visib) if visible else EMPTY_BBOX,
        px_count_all=px_all,
        px_count_valid=px_valid,
        px_count_visib=px_visib,
        visib_fract=visib_fract(px_visib, px_all),
    )
