"""`evaluate` on the embedded example: errors, the paper's table, outputs, edge cases."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from bopsurg import metrics
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import PoseEstimates, load_results
from bopsurg.evaluation.runner import error_columns, evaluate, write_evaluation
from bopsurg.evaluation.summary import describe, format_table
from bopsurg.example import ExampleSpec, write_example_dataset
from tests.helpers import estimates_from_gt


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    ex = write_example_dataset(
        tmp_path_factory.mktemp("ex"),
        ExampleSpec(seed=3, scenes=2, images_per_scene=8, duplicate_fraction=0.3),
    )
    return ex, BopDataset(ex.root, ex.split), load_results(ex.results)


def test_errors_rows_are_the_metrics_of_the_matched_pairs(example):
    _, ds, est = example
    res = evaluate(ds, est)
    assert len(res.errors) == len(est)
    matched = res.errors[res.errors["gt_id"] >= 0]
    assert len(matched) > 0
    pts = ds.model(1).pts
    for row in matched.itertuples():
        k = np.flatnonzero(
            (est.scene_id == row.scene_id) & (est.im_id == row.im_id) & (est.score == row.score)
        )[0]
        g = ds.scene(row.scene_id).gt[row.im_id][row.gt_id]
        assert row.mssd == pytest.approx(
            metrics.mssd(est.R[k], est.t[k], g.R, g.t, pts)[0], rel=1e-12
        )
        assert row.re == pytest.approx(metrics.re(est.R[k], g.R)[0], rel=1e-12)
        assert row.te == pytest.approx(metrics.te(est.t[k], g.t)[0], rel=1e-12)
        assert row.adi <= row.add + 1e-12


def test_duplicate_with_lower_score_is_left_unmatched(example):
    _, ds, est = example
    res = evaluate(ds, est)
    e = res.errors
    dup = e.groupby(["scene_id", "im_id"]).filter(lambda g: len(g) > 1)
    assert len(dup) > 0, "the example must contain duplicate detections"
    for _, g in dup.groupby(["scene_id", "im_id"]):
        best = g.sort_values("score", ascending=False).iloc[0]
        assert best["gt_id"] == 0
        assert (g[g["score"] < best["score"]]["gt_id"] == -1).all()


def test_table_is_described_over_visible_instances(example):
    _, ds, est = example
    res = evaluate(ds, est, min_visib=0.3)
    rows = res.gt_rows[res.gt_rows["visib_fract"] >= 0.3]
    for m in ("re", "te", "mssd"):
        expected = describe(rows[m].dropna().to_numpy())
        got = res.summary["table"][m]
        assert got["n"] == expected["n"]
        assert got["median"] == pytest.approx(expected["median"])
        assert got["std"] == pytest.approx(np.std(rows[m].dropna().to_numpy()))
    assert res.summary["gt_instances"] == len(rows)
    assert res.summary["missed"] == int(rows["re"].isna().sum())
    assert "RE [deg]" in format_table(res.summary, res.scores)


def test_perfect_estimates_score_one(example):
    _, ds, _ = example
    est = estimates_from_gt(ds, time=-1.0)
    res = evaluate(ds, est)
    assert res.scores["bop19_average_recall_mssd"] == 1.0
    assert res.scores["bop19_average_recall_mspd"] == 1.0
    assert res.scores["bop19_average_time_per_image"] == -1.0
    assert (
        np.nanmax(res.errors[["re", "te", "mssd", "mspd", "add", "adi"]].to_numpy()) < 1e-5
    )  # acos near 1


def test_no_estimates_for_an_image_counts_as_missed(example):
    _, ds, est = example
    keep = ~((est.scene_id == ds.scene_ids[0]) & (est.im_id == 0))
    sub = PoseEstimates.from_arrays(
        scene_id=est.scene_id[keep], im_id=est.im_id[keep], obj_id=est.obj_id[keep],
        score=est.score[keep], R=est.R[keep], t=est.t[keep], time=est.time[keep],
    )  # fmt: skip
    full, part = evaluate(ds, est), evaluate(ds, sub)
    assert part.summary["gt_instances"] == full.summary["gt_instances"]
    assert part.summary["missed"] >= full.summary["missed"]
    assert part.scores["bop19_average_recall_mssd"] <= full.scores["bop19_average_recall_mssd"]


def test_outputs_are_written(example, tmp_path):
    _, ds, est = example
    res = evaluate(ds, est)
    write_evaluation(res, tmp_path, meta={"dataset": "x"})
    errors = pd.read_csv(tmp_path / "errors.csv")
    assert tuple(errors.columns) == error_columns()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["dataset"] == "x"
    assert set(summary["table"]) == {"re", "te", "mssd"}
    scores = json.loads((tmp_path / "scores.json").read_text())
    assert len(scores["details"]["mssd"]["recalls"]) == 10
    assert not list(tmp_path.glob(".*tmp*"))  # no temp files left behind


def test_outputs_are_standard_json_when_nothing_matches(example, tmp_path):
    _, ds, est = example
    far = PoseEstimates.from_arrays(
        scene_id=est.scene_id[:1], im_id=est.im_id[:1], obj_id=est.obj_id[:1],
        score=est.score[:1], R=est.R[:1], t=est.t[:1] + 500.0, time=est.time[:1],
    )  # fmt: skip
    res = evaluate(ds, far, min_visib=1.1)  # no GT instance passes: statistics are NaN
    write_evaluation(res, tmp_path)
    text = (tmp_path / "summary.json").read_text()
    assert "NaN" not in text
    assert json.loads(text)["table"]["re"]["mean"] is None


def test_distributed_evaluation_equals_the_single_pass(example, tmp_path):
    from bopsurg.evaluation.runner import evaluate_distributed
    from bopsurg.executors import LocalExecutor

    _, ds, est = example
    one = evaluate(ds, est)
    for workers in (1, 2):
        parts = evaluate_distributed(ds, est, executor=LocalExecutor(workers))
        assert parts.scores == one.scores
        pd.testing.assert_frame_equal(parts.errors, one.errors)
        a, b = tmp_path / f"one{workers}", tmp_path / f"parts{workers}"
        write_evaluation(one, a)
        write_evaluation(parts, b)
        for name in ("errors.csv", "summary.json", "scores.json"):
            assert (a / name).read_bytes() == (b / name).read_bytes()
