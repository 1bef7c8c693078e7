"""scene_gt_coco.json: RLE coding, the annotations written by annotate, and their check."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bopsurg.bop.check import check_dataset
from bopsurg.bop.coco import (
    SCENE_GT_COCO,
    load_scene_gt_coco,
    mask_bbox,
    mask_to_rle,
    rle_bbox,
    rle_to_mask,
)
from bopsurg.bop.scene import GtPose
from bopsurg.bop.targets import ImageTarget, load_image_targets
from bopsurg.errors import DatasetError
from tests.bopsurg.test_annotate import _annotate, _dataset, _px


def test_rle_hand_worked():
    # Column-major runs, starting with background.
    assert mask_to_rle(np.array([[0, 1], [1, 1]]))["counts"] == [1, 3]
    assert mask_to_rle(np.array([[1, 0], [0, 0]]))["counts"] == [0, 1, 3]
    assert mask_to_rle(np.zeros((2, 3)))["counts"] == [6]
    assert mask_to_rle(np.zeros((2, 3)))["size"] == [2, 3]
    m = np.zeros((4, 5), bool)
    m[1:3, 2:5] = True
    assert mask_bbox(m) == [2, 1, 3, 2]


@pytest.mark.parametrize("seed", range(30))
def test_rle_round_trip_and_pycocotools_agree(seed):
    mask_utils = pytest.importorskip("pycocotools.mask")
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(1, 12, 2))
    m = rng.random((h, w)) < rng.random()
    rle = mask_to_rle(m)
    assert np.array_equal(rle_to_mask(rle), m)
    compressed = mask_utils.frPyObjects(rle, h, w)
    assert np.array_equal(mask_utils.decode(compressed).astype(bool), m)
    assert int(mask_utils.area(compressed)) == int(m.sum())
    if m.any():
        assert mask_utils.toBbox(compressed).tolist() == rle_bbox(rle)


def _two_squares(root):
    """A fully visible square (cols 25-34) in front of one half hidden (cols 30-39, 35-39
    visible), plus an image-less-visible third one hidden behind the first."""
    near = GtPose(1, np.eye(3), _px(30, 24, 80.0))
    far = GtPose(1, np.eye(3), _px(35, 24, 120.0))
    hidden = GtPose(1, np.eye(3), _px(30, 24, 150.0))
    _dataset(root, [near, far, hidden])
    _annotate(root, delta=1.0)
    return root / "test" / "000001"


def test_annotate_writes_scene_gt_coco_and_bop24_targets(tmp_path):
    sdir = _two_squares(tmp_path)
    coco = load_scene_gt_coco(sdir / SCENE_GT_COCO)
    assert coco["images"] == [{"id": 0, "file_name": "rgb/000000.png", "width": 64, "height": 48}]
    anns = coco["annotations"]
    assert [a["id"] for a in anns] == [1, 2]  # the hidden instance has no visible pixel
    assert [a["area"] for a in anns] == [100, 50]
    assert [a["bbox"] for a in anns] == [[25, 19, 10, 10], [30, 19, 10, 10]]  # amodal
    assert rle_bbox(anns[1]["segmentation"]) == [35, 19, 5, 10]  # modal
    assert [a["ignore"] for a in anns] == [False, False]
    assert coco["categories"] == [{"id": 1, "name": "1", "supercategory": "bopsurg"}]
    assert load_image_targets(tmp_path / "test_targets_bop24.json") == [ImageTarget(1, 0)]
    assert check_dataset(tmp_path) == []


def test_check_reports_a_bad_scene_gt_coco(tmp_path):
    sdir = _two_squares(tmp_path)
    path = sdir / SCENE_GT_COCO
    content = json.loads(path.read_text())
    content["annotations"][1]["segmentation"]["counts"][0] += 1
    content["annotations"][0]["image_id"] = 9
    del content["categories"]
    path.write_text(json.dumps(content))
    assert [str(p) for p in check_dataset(tmp_path)] == [
        f"{path}: categories: missing",
        f"{path}: annotations/0/image_id: image 9 is not in images",
        f"{path}: annotations/1/segmentation: RLE counts sum to 3073, not size [48, 64]",
    ]
    with pytest.raises(DatasetError, match="categories: missing"):
        load_scene_gt_coco(path)
