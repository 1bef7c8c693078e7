"""COCO 2D detection / segmentation scores: hand-worked AP, the reference's scene merging,
content recognition of the results file and the CLI."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from bopsurg.bop.coco import mask_to_rle, write_detection_annotations
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.detections import save_detections
from bopsurg.bop.images import load_mask
from bopsurg.bop.targets import ImageTarget
from bopsurg.cli.main import main
from bopsurg.estimation import Detections
from bopsurg.evaluation.coco_eval import (
    evaluate_coco,
    is_coco_results,
    load_coco_results,
    merged_ground_truth,
)
from tests.bopsurg.bop.test_coco import _two_squares
from tests.bopsurg.evaluation import coco_oracle

pytest.importorskip("pycocotools")

NEAR_BOX = [25, 19, 10, 10]
FAR_AMODAL = [30, 19, 10, 10]


@pytest.fixture
def squares(tmp_path):
    sdir = _two_squares(tmp_path)
    return BopDataset(tmp_path, "test"), sdir


def _res(box, score, scene=1, **extra):
    return {"scene_id": scene, "image_id": 0, "category_id": 1, "score": score, "bbox": box,
            "time": 0.5, **extra}  # fmt: skip


def test_bbox_ap_hand_worked(squares):
    ds, _ = squares
    s = evaluate_coco(ds, [_res(NEAR_BOX, 0.9), _res(FAR_AMODAL, 0.8)], ["coco-bbox"])
    assert s["bop22_coco_bbox_AP"] == pytest.approx(1.0)
    # Against the far square's modal box [35, 19, 5, 10] the amodal box has IoU 0.5: a TP
    # at the 0.5 threshold only. Above it: TP then FP, precision 1 up to recall 0.5.
    expected = (1.0 + 9 * 51 / 101) / 10
    assert s["bop22_coco_bbox_modal_AP"] == pytest.approx(expected, abs=1e-12)
    assert s["bop22_coco_bbox_modal_AP50"] == pytest.approx(1.0)
    assert s["bop22_coco_bbox_modal_AP_small"] == pytest.approx(expected, abs=1e-12)
    assert s["bop22_coco_bbox_AP_large"] == -1.0  # no large GT (COCO's own convention)
    assert s["bop22_coco_average_time_per_image"] == 0.5


def test_segm_ap_hand_worked(squares):
    ds, sdir = squares
    near = load_mask(sdir / "mask_visib" / "000000_000000.png")
    far = load_mask(sdir / "mask_visib" / "000000_000001.png")
    half = far.copy()
    half[:, :37] = False  # 30 of the 50 visible px: IoU 0.6
    results = [
        {**_res(None, 0.9), "segmentation": mask_to_rle(near)},
        {**_res(None, 0.8), "segmentation": mask_to_rle(half)},
    ]
    for r in results:
        del r["bbox"]
    s = evaluate_coco(ds, results, ["coco-segm"])
    # Far: TP at 0.5, 0.55, 0.6 (IoU >= threshold), FP above.
    assert s["bop22_coco_segm_AP"] == pytest.approx((3 + 7 * 51 / 101) / 10, abs=1e-12)


def test_scenes_merge_with_the_references_image_ids(squares, tmp_path):
    ds, sdir = squares
    shutil.copytree(sdir, tmp_path / "test" / "000002")
    write_detection_annotations(BopDataset(tmp_path, "test"))
    ds = BopDataset(tmp_path, "test")
    gt, ids = merged_ground_truth(ds, [ImageTarget(2, 0), ImageTarget(1, 0)], "amodal")
    assert ids == {(2, 0): 0, (1, 0): 1}  # target order; offset = max id so far + 1
    assert [a["id"] for a in gt["annotations"]] == [1, 2, 4, 5]  # offset max id + 1 = 3
    # Only scene 2 detected: half the targets found with precision 1.
    s = evaluate_coco(ds, [_res(NEAR_BOX, 0.9, 2), _res(FAR_AMODAL, 0.8, 2)], ["coco-bbox"])
    assert s["bop22_coco_bbox_AP"] == pytest.approx(51 / 101, abs=1e-12)
    # Only the first target image is evaluated: results of scene 1 are dropped.
    s = evaluate_coco(
        ds, [_res(NEAR_BOX, 0.9, 1), _res(FAR_AMODAL, 0.8, 1)], ["coco-bbox"], [ImageTarget(2, 0)]
    )
    assert s["bop22_coco_bbox_AP"] == -1.0  # nothing left to evaluate, as the reference


@pytest.mark.usefixtures("squares")
def test_detector_output_is_recognised_and_evaluated(tmp_path, capsys):
    det = tmp_path / "det.json"
    boxes = np.array([NEAR_BOX, FAR_AMODAL], float)
    save_detections(det, {(1, 0): Detections(np.array([1, 1]), np.array([0.9, 0.8]), boxes)})
    assert is_coco_results(det)
    csv = tmp_path / "r.csv"
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n")
    assert not is_coco_results(csv)
    assert len(load_coco_results(det)) == 2
    out = tmp_path / "out"
    assert main(["eval", str(tmp_path), str(det), "--out", str(out)]) == 0
    scores = json.loads((out / "scores.json").read_text())
    assert scores["bop22_coco_bbox_AP"] == pytest.approx(1.0)
    assert "bop22_coco_segm_AP" not in scores  # no masks in the results: not a task
    assert scores["ci95"]["bop22_coco_bbox_AP"] == [1.0, 1.0]  # a perfect detector
    assert "95 % intervals" in capsys.readouterr().out
    assert main(["eval", str(tmp_path), str(det), "--out", str(out), "--figures"]) == 0
    assert "nothing to draw for a COCO results JSON" in capsys.readouterr().out
    assert main(["eval", str(tmp_path), str(det), "--out", str(out), "--task", "bop24"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "--task bop24" in err[0]


@pytest.mark.usefixtures("squares")
def test_bad_results_are_one_line_errors(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([_res([1, 2, -3, 4], 0.5)]))
    assert main(["eval", str(tmp_path), str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "bad.json" in err
    assert "0/bbox" in err
    assert len(err.splitlines()) == 1


@pytest.mark.parametrize("seed", coco_oracle.SEEDS)
def test_scores_equal_the_reference_toolkit(tmp_path, seed):
    """Numbers of ``scripts/eval_bop22_coco.py`` (see coco_oracle.py), bbox amodal and
    modal and segm, to 1e-12."""
    ds, results = coco_oracle.build_case(tmp_path / "ds", seed)
    ref = json.loads(coco_oracle.FIXTURE.read_text())["cases"][str(seed)]
    scores = evaluate_coco(ds, results, ["coco-bbox", "coco-segm"])
    for prefix, values in ref.items():
        for stat, value in values.items():
            if stat == "average_time_per_image":
                continue
            key = f"bop22_coco_{prefix}_{stat}"
            assert scores[key] == pytest.approx(value, abs=1e-12), key
    assert scores["bop22_coco_average_time_per_image"] == pytest.approx(0.2)
    # The case must exercise what it claims to.
    assert scores["bop22_coco_bbox_AP"] != scores["bop22_coco_segm_AP"]
    assert scores["bop22_coco_bbox_AP"] != scores["bop22_coco_bbox_modal_AP"]
    targets = json.loads((tmp_path / "ds" / "test_targets_bop24.json").read_text())
    assert len({t["scene_id"] for t in targets[:3]}) == 2  # scenes interleaved
