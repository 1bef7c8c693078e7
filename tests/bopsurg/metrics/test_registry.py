"""The metric registry: one entry reaches eval's dispatch, errors.csv, the table and --help."""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
import pytest

from bopsurg import metrics
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import load_results
from bopsurg.cli import eval_cmd
from bopsurg.errors import BopsurgError
from bopsurg.evaluation.runner import error_columns, evaluate, write_evaluation
from bopsurg.evaluation.summary import format_table
from bopsurg.example import ExampleSpec, write_example_dataset
from bopsurg.metrics.registry import (
    METRICS,
    Metric,
    Need,
    PairBatch,
    help_lines,
    metric,
    rerun_metrics,
    table_metrics,
)


def _proj(b: PairBatch) -> np.ndarray:
    assert b.pts is not None
    assert b.K is not None
    return metrics.proj(b.R_est, b.t_est, b.R_gt, b.t_gt, b.K, b.pts)


PROJ = Metric(
    "proj", "PROJ", "px", "mean projection distance", _proj,
    frozenset({Need.MODEL_POINTS, Need.CAMERA}), in_table=True,
)  # fmt: skip


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    ex = write_example_dataset(
        tmp_path_factory.mktemp("ex"), ExampleSpec(seed=5, scenes=1, images_per_scene=6)
    )
    return BopDataset(ex.root, ex.split), load_results(ex.results)


def test_registry_lists_the_columns_of_errors_csv_in_order():
    assert tuple(METRICS) == ("re", "te", "mssd", "mspd", "add", "adi")
    assert [m.name for m in table_metrics()] == ["re", "te", "mssd"]
    assert [m.name for m in rerun_metrics()] == ["re", "te", "mssd", "mspd"]
    assert metric("mspd").needs == {Need.MODEL_POINTS, Need.SYMMETRIES, Need.CAMERA}
    with pytest.raises(KeyError, match="choose from re, te"):
        metric("nope")


def test_one_registry_entry_is_evaluated_written_tabled_and_documented(
    example, tmp_path, monkeypatch
):
    ds, est = example
    monkeypatch.setitem(METRICS, "proj", PROJ)
    res = evaluate(ds, est)
    matched = res.errors[res.errors["gt_id"] >= 0]
    assert len(matched) > 0
    # the value is the metric's own, for the pair the matching chose
    row = matched.iloc[0]
    k = int(np.flatnonzero((est.im_id == row.im_id) & (est.score == row.score))[0])
    g = ds.scene(int(row.scene_id)).gt[int(row.im_id)][int(row.gt_id)]
    K = ds.scene(int(row.scene_id)).camera[int(row.im_id)].K
    expected = metrics.proj(est.R[k], est.t[k], g.R, g.t, K, ds.model(1).pts)[0]
    assert row["proj"] == pytest.approx(expected, rel=1e-12)

    write_evaluation(res, tmp_path)
    written = pd.read_csv(tmp_path / "errors.csv")
    assert "proj" in error_columns()
    assert tuple(written.columns) == error_columns()
    assert res.summary["table"]["proj"]["unit"] == "px"
    assert "PROJ [px]" in format_table(res.summary)
    assert "PROJ med" in format_table(res.summary)
    assert any(line.startswith("  proj [px]") for line in help_lines("  "))

    sub = argparse.ArgumentParser().add_subparsers()
    eval_cmd.register(sub)
    (parser,) = sub.choices.values()
    assert "proj [px]" in parser.format_help()


def test_unregistered_metric_is_a_one_line_error(example):
    ds, est = example
    with pytest.raises(BopsurgError, match=r"unknown metric\(s\) \['proj'\]; choose from re"):
        evaluate(ds, est, instance_metrics=("re", "proj"))
