"""gt_info fields and masks (bop19 rule), by hand-worked examples."""

from __future__ import annotations

import numpy as np
import pytest

from bopsurg.errors import ShapeError
from bopsurg.visibility import bbox_from_mask, instance_visibility, instance_visibility_from_masks

K = np.array([[100.0, 0, 5], [0, 100.0, 4], [0, 0, 1]])


def test_convention_bbox_has_no_plus_one():
    m = np.zeros((6, 8), bool)
    m[2:4, 3:7] = True  # rows 2-3, cols 3-6
    assert bbox_from_mask(m) == (3, 2, 3, 1)
    assert bbox_from_mask(np.zeros((3, 3))) == (-1, -1, -1, -1)


def test_truncation_occlusion_and_missing_depth_by_hand():
    h, w = 8, 10
    large = np.zeros((3 * h, 3 * w))
    # Object: a 4x6 block, rows 6..9 and cols 12..17 of the large canvas, depth 100 mm;
    # in image coordinates rows -2..1 (2 rows truncated above) and cols 2..7.
    large[6:10, 12:18] = 100.0
    depth = np.full((h, w), 200.0)  # background behind the object
    depth[0, 2:4] = 50.0  # an occluder in front of 2 object pixels
    depth[1, 7] = 0.0  # missing depth counts as visible (bop19)
    vis = instance_visibility(depth, large, K, delta=15.0)
    assert vis.info.px_count_all == 24
    assert vis.mask.sum() == 12  # rows 0-1 inside the image
    assert vis.info.px_count_valid == 11  # one pixel without depth
    assert vis.info.px_count_visib == 10  # 12 - 2 occluded
    assert vis.info.visib_fract == pytest.approx(10 / 24)
    assert vis.info.bbox_obj == (2, -2, 5, 3)
    assert vis.info.bbox_visib == (2, 0, 5, 1)
    assert vis.mask_visib[1, 7]
    assert not vis.mask_visib[0, 2]


def test_fully_occluded_gives_minus_one_boxes():
    h, w = 4, 4
    large = np.zeros((12, 12))
    large[5:7, 5:7] = 100.0
    depth = np.full((h, w), 10.0)
    info = instance_visibility(depth, large, K).info
    assert info.px_count_visib == 0
    assert info.visib_fract == 0.0
    assert info.bbox_obj == (-1, -1, -1, -1)
    assert info.bbox_visib == (-1, -1, -1, -1)


def test_from_masks_matches_from_depth():
    h, w = 8, 10
    large = np.zeros((3 * h, 3 * w))
    large[6:10, 12:18] = 100.0
    depth = np.full((h, w), 200.0)
    depth[0, 2:4] = 50.0
    from_depth = instance_visibility(depth, large, K)
    info = instance_visibility_from_masks(large > 0, from_depth.mask_visib)
    assert info == from_depth.info


def test_wrong_canvas_is_a_shape_error():
    with pytest.raises(ShapeError, match="depth_model_large"):
        instance_visibility(np.zeros((4, 4)), np.zeros((4, 4)), K)
