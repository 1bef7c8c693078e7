"""Bootstrap of the COCO scores: unit weights give pycocotools' own numbers, a resampled test
set gives what pycocotools computes on that set with the drawn images copied, intervals are
seeded, and paired comparisons of identical evaluations are exactly zero."""

from __future__ import annotations

import contextlib
import copy
import io
import json

import numpy as np
import pytest

from bopsurg.cli.main import main
from bopsurg.evaluation.coco_bootstrap import (
    COCO_SAMPLES_FILENAME,
    CocoSamples,
    compare_coco,
    confidence_intervals,
    replicate_scores,
)
from bopsurg.evaluation.coco_eval import STATS, evaluate_coco_samples, merged_ground_truth
from tests.bopsurg.evaluation import coco_oracle

pytest.importorskip("pycocotools")


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """The oracle's case (3 objects, size classes, misses, duplicates, FPs) with scores made
    unique, so copies of an image are the only ties in the ranking."""
    ds, results = coco_oracle.build_case(tmp_path_factory.mktemp("coco") / "ds", 11)
    rng = np.random.default_rng(5)
    for r, s in zip(results, rng.permutation(len(results)), strict=True):
        r["score"] = float(0.05 + 0.9 * s / len(results))
    return ds, results


def _cocoeval(gt, dets, iou_type):
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = copy.deepcopy(gt)
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(copy.deepcopy(dets))
        ev = COCOeval(coco_gt, coco_dt, iou_type)
        ev.params.imgIds = sorted(coco_gt.getImgIds())
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return ev


def test_unit_weights_give_pycocotools_stats(case):
    ds, results = case
    scores, samples = evaluate_coco_samples(ds, results, ["coco-bbox", "coco-segm"])
    assert samples is not None
    assert samples.prefixes == ["bbox", "bbox_modal", "segm"]
    full = replicate_scores(samples, np.ones((1, len(samples.images))))
    for key, value in scores.items():
        if key.endswith("average_time_per_image"):
            continue
        expected = np.nan if value == -1 else value
        np.testing.assert_allclose(full[key][0], expected, atol=1e-12, err_msg=key)
    assert sum(np.isfinite(full[f"bop22_coco_bbox_{s}"][0]) for s in STATS) >= 10


def test_a_resampled_set_equals_pycocotools_on_the_copied_images(case):
    """Replicate weights 0, 1, 2, 3 per image: pycocotools on the GT and results with each
    image copied that often (new image and annotation ids) gives the replicate's scores."""
    ds, results = case
    gt, ids = merged_ground_truth(ds, ds.image_targets(), None)
    dets = [
        {"image_id": ids[(r["scene_id"], r["image_id"])], "category_id": r["category_id"],
         "score": r["score"], "bbox": r["bbox"]}
        for r in results if (r["scene_id"], r["image_id"]) in ids
    ]  # fmt: skip
    ev = _cocoeval(gt, dets, "bbox")
    key_of = {v: k for k, v in ids.items()}
    samples = CocoSamples.from_cocoevals([("bbox", ev)], [key_of[i] for i in ev.params.imgIds])
    rng = np.random.default_rng(3)
    for _ in range(3):
        w = rng.integers(0, 4, len(samples.images))
        w[0] = 2  # at least one copy
        copied = {**gt, "images": [], "annotations": []}
        copied_dets = []
        ann_id = 1
        for pos, im_id in enumerate(ev.params.imgIds):
            for c in range(int(w[pos])):
                new_id = 1000 * (c + 1) + im_id
                im = next(i for i in gt["images"] if i["id"] == im_id)
                copied["images"].append({**im, "id": new_id})
                for a in (a for a in gt["annotations"] if a["image_id"] == im_id):
                    copied["annotations"].append({**a, "id": ann_id, "image_id": new_id})
                    ann_id += 1
                copied_dets += [{**d, "image_id": new_id} for d in dets if d["image_id"] == im_id]
        expected = _cocoeval(copied, copied_dets, "bbox").stats
        got = replicate_scores(samples, w[None, :].astype(np.float64))
        for stat, value in zip(STATS, expected, strict=True):
            want = np.nan if value == -1 else value
            np.testing.assert_allclose(got[f"bop22_coco_bbox_{stat}"][0], want, atol=1e-12)


def test_intervals_are_seeded_and_contain_the_score(case, tmp_path):
    ds, results = case
    scores, samples = evaluate_coco_samples(ds, results, ["coco-bbox"])
    assert samples is not None
    ci = confidence_intervals(samples, 200, seed=1)
    assert ci == confidence_intervals(samples, 200, seed=1)
    assert ci != confidence_intervals(samples, 200, seed=2)
    lo, hi = ci["bop22_coco_bbox_AP"]
    assert lo < scores["bop22_coco_bbox_AP"] < hi
    by_scene = confidence_intervals(samples, 200, seed=1, unit="scene")
    assert by_scene["bop22_coco_bbox_AP"] != ci["bop22_coco_bbox_AP"]
    samples.save(tmp_path / "s.npz")
    again = CocoSamples.load(tmp_path / "s.npz")
    assert confidence_intervals(again, 200, seed=1) == ci


def test_identical_evaluations_do_not_differ_and_a_worse_one_does(case):
    ds, results = case
    _, a = evaluate_coco_samples(ds, results, ["coco-bbox"])
    worse = [{**r, "bbox": [r["bbox"][0] + 0.4 * r["bbox"][2], *r["bbox"][1:]]} for r in results]
    _, b = evaluate_coco_samples(ds, worse, ["coco-bbox"])
    assert a is not None
    assert b is not None
    same = compare_coco(a, a, 200)
    assert all(c.diff == 0 and c.ci == (0.0, 0.0) for c in same.values() if np.isfinite(c.a))
    res = compare_coco(a, b, 200)
    c = res["bop22_coco_bbox_AP"]
    assert c.diff < 0
    assert c.ci[1] < 0
    assert c.p_value < 0.05


def test_eval_writes_intervals_and_compare_reads_them(case, tmp_path, capsys):
    ds, results = case
    worse = [{**r, "bbox": [r["bbox"][0] + 0.4 * r["bbox"][2], *r["bbox"][1:]]} for r in results]
    for name, res in (("a", results), ("b", worse)):
        (tmp_path / f"{name}.json").write_text(json.dumps(res))
        argv = ["eval", str(ds.root), str(tmp_path / f"{name}.json"), "--out",
                str(tmp_path / name), "--bootstrap", "100", "--no-progress"]  # fmt: skip
        assert main(argv) == 0
    scores = json.loads((tmp_path / "a" / "scores.json").read_text())
    lo, hi = scores["ci95"]["bop22_coco_segm_AP"]
    assert lo <= scores["bop22_coco_segm_AP"] <= hi
    assert scores["bootstrap"]["replicates"] == 100
    assert (tmp_path / "a" / COCO_SAMPLES_FILENAME).exists()
    capsys.readouterr()
    out = tmp_path / "cmp"
    argv = ["compare", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out),
            "--bootstrap", "100"]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "bop22_coco_bbox_AP " in text
    cmp = json.loads((out / "compare.json").read_text())
    (entry,) = cmp["comparisons"].values()
    assert entry["bop22_coco_bbox_AP"]["diff"] < 0
    assert entry["bop22_coco_bbox_AP"]["ci"][1] < 0
    assert entry["bop22_coco_segm_AP"]["diff"] == 0  # the masks are the same
