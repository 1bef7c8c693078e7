"""Visual error analysis: the rerun recording of an evaluation, read back."""

from __future__ import annotations

import builtins
import dataclasses

import numpy as np
import pytest

pytest.importorskip("rerun")

from rerun.chunk import RrdReader

from bopsurg.bop import BopDataset, load_results
from bopsurg.cli.main import main
from bopsurg.errors import BopsurgError
from bopsurg.estimation import Detections
from bopsurg.evaluation.runner import evaluate
from bopsurg.example import ExampleSpec, write_example_dataset
from bopsurg.viz import frame_table, log_evaluation, select_image_frames
from tests.bopsurg.recordings import read_chunks, scalar_series

EXPECTED = {
    "/world",
    "/world/camera",
    "/world/camera/rgb",
    "/world/camera/gt_silhouette",
    "/world/camera/est_silhouette",
    "/world/gt/obj_000001",
    "/world/est/obj_000001",
    "/metrics/re",
    "/metrics/te",
    "/metrics/mssd",
    "/metrics/visib_fract",
    "/metrics/worst_rank",
    "/frame_info/scene_id",
    "/frame_info/im_id",
    "/histograms/re",
    "/histograms/te",
    "/histograms/mssd",
    "/histograms/medians",
    "/histograms/re_plot",
    "/histograms/te_plot",
    "/histograms/mssd_plot",
    "/world/camera/boxes",
    "/report/summary",
    "/report/worst",
}


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    return write_example_dataset(
        tmp_path_factory.mktemp("viz"), ExampleSpec(scenes=1, images_per_scene=6)
    )


@pytest.fixture(scope="module")
def logged(example, tmp_path_factory):
    dataset = BopDataset(example.root, example.split)
    est = load_results(example.results)
    ev = evaluate(dataset, est)
    boxes = {(1, 0): Detections([1], [0.75], [[10.0, 20.0, 30.0, 40.0]])}
    path = log_evaluation(
        dataset, est, ev, tmp_path_factory.mktemp("rrd") / "eval.rrd", worst=3, detections=boxes
    )
    return ev, path, read_chunks(path)


def test_entities(logged):
    _, path, chunks = logged
    assert path.is_file()
    assert path.stat().st_size > 0
    assert set(chunks) >= EXPECTED


def test_detector_boxes_are_drawn_on_their_frame(logged):
    ev, _, chunks = logged
    frames = frame_table(ev.errors, ev.gt_rows)
    frame = int(frames[(frames["scene_id"] == 1) & (frames["im_id"] == 0)]["frame"].iloc[0])
    rows = {}
    for chunk in chunks["/world/camera/boxes"]:
        rb = chunk.to_record_batch().to_pylist()
        for r in rb:
            rows[r["frame"]] = r
    assert rows[frame]["Boxes2D:centers"] == [[25.0, 40.0]]
    assert rows[frame]["Boxes2D:half_sizes"] == [[15.0, 20.0]]
    assert rows[frame]["Boxes2D:labels"] == ["obj 1 0.75"]
    others = [r for f, r in rows.items() if f != frame]
    assert others
    assert all(not r["Boxes2D:centers"] for r in others)  # cleared on frames without boxes


def test_histograms_count_the_instances_of_the_table(example, logged, tmp_path):
    ev, _, _ = logged
    errors = ev.errors.copy()
    matched = np.flatnonzero(errors["gt_id"] >= 0)
    errors.loc[matched[0], "visib_fract"] = 0.1  # below the table's 0.3: not in Fig. 4 either
    low = dataclasses.replace(ev, errors=errors)
    dataset = BopDataset(example.root, example.split)
    path = log_evaluation(dataset, load_results(example.results), low, tmp_path / "low.rrd")
    store = RrdReader(str(path)).stream().collect()
    bars = [c for c in store.stream() if c.entity_path == "/histograms/mssd"]
    counts = bars[0].to_record_batch().to_pylist()[0]["BarChart:values"][0]["buffer"]
    assert sum(counts) == len(matched) - 1


def test_histogram_plot_marks_the_median():
    from bopsurg.viz.rerun_log import histogram_figure

    values = np.random.default_rng(0).gamma(2.0, 4.0, 500)
    counts, edges = np.histogram(values, bins=30)
    median = float(np.median(values))
    img = histogram_figure(counts, edges, median, "RE [deg]")
    red = (img[:, :, 0] > 200) & (img[:, :, 1] < 40) & (img[:, :, 2] < 40)
    cols = np.flatnonzero(red.sum(axis=0) > 100)  # the vertical line, not the label
    x0, x1 = 40, img.shape[1] - 12
    expected = x0 + (median - edges[0]) / (edges[-1] - edges[0]) * (x1 - x0)
    assert len(cols) > 0
    assert abs(cols.mean() - expected) <= 1.5


def test_mssd_scalars_equal_errors_csv(logged):
    ev, _, chunks = logged
    frames = frame_table(ev.errors, ev.gt_rows)
    matched = ev.errors[ev.errors["gt_id"] >= 0]
    expected = (
        frames[["frame", "scene_id", "im_id"]]
        .merge(matched.groupby(["scene_id", "im_id"])["mssd"].max().reset_index())
        .set_index("frame")["mssd"]
        .sort_index()
    )
    got = scalar_series(chunks, "/metrics/mssd")
    assert len(expected) > 0
    assert list(got.index) == list(expected.index)
    np.testing.assert_allclose(got.to_numpy(), expected.to_numpy(), rtol=0, atol=1e-12)
    ids = scalar_series(chunks, "/frame_info/im_id")
    assert list(ids.to_numpy()) == list(frames["im_id"].to_numpy(float))


def test_worst_rank_marks_largest_mssd(logged):
    ev, _, chunks = logged
    frames = frame_table(ev.errors, ev.gt_rows)
    rank = scalar_series(chunks, "/metrics/worst_rank")
    assert len(rank) == 3
    top = frames.sort_values("mssd", ascending=False).head(3)["frame"].tolist()
    assert [int(f) for f in rank.sort_values().index] == top


def test_select_image_frames():
    mssd = np.arange(2000, dtype=float)
    assert len(select_image_frames(mssd[:10])) == 10
    chosen = select_image_frames(mssd)
    assert len(chosen) == 200
    assert set(range(1900, 2000)) <= set(chosen.tolist())  # the 100 worst
    few = select_image_frames(mssd, max_frames=10)
    assert len(few) == 10
    assert {1999, 1998, 1997, 1996, 1995} <= set(few.tolist())


def test_missing_rerun_is_a_user_error(logged, monkeypatch, tmp_path):
    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    ev = logged[0]
    with pytest.raises(BopsurgError, match="pip install bopsurg\\[rerun\\]"):
        log_evaluation(None, None, ev, tmp_path / "x.rrd")  # type: ignore[arg-type]


def test_cli_eval_rerun_and_viz(example, tmp_path, capsys):
    rrd = tmp_path / "eval.rrd"
    code = main(
        [
            "eval",
            str(example.root),
            str(example.results),
            "--out",
            str(tmp_path / "eval"),
            "--rerun",
            str(rrd),
            "--no-progress",
            "--renderer",
            "none",
        ]
    )
    assert code == 0
    assert rrd.is_file()
    assert f"open it with: rerun {rrd}" in capsys.readouterr().out
    out = tmp_path / "viz.rrd"
    code = main(["viz", str(example.root), str(example.results), "--out", str(out)])
    assert code == 0
    assert out.is_file()
    assert "open it with: rerun" in capsys.readouterr().out
    names = {c.entity_path for c in RrdReader(str(out)).stream().collect().stream()}
    assert "/report/worst" in names
