"""compare --figures and --rerun: the overlaid figures, the recording read back, bad inputs."""

from __future__ import annotations

import builtins
import dataclasses
import importlib.util
import json
import shutil

import numpy as np
import pandas as pd
import pytest

from bopsurg.bop import load_results
from bopsurg.bop.results import PoseEstimates, save_results
from bopsurg.cli.main import main
from bopsurg.errors import BopsurgError
from bopsurg.evaluation import bop24
from bopsurg.evaluation.bootstrap import DetectionSamples
from bopsurg.example import ExampleSpec, write_example_dataset
from bopsurg.viz.evals import (
    EvalFolder,
    comparison_gt,
    entity_keys,
    load_eval_folders,
    method_labels,
)
from bopsurg.viz.rerun_compare import (
    comparison_frames,
    forest_geometry,
    forest_rows,
    worst_regressions,
)
from tests.bopsurg.evaluation.test_bop24 import _hand_dataset
from tests.bopsurg.recordings import read_chunks, scalar_series


def _shifted(est: PoseEstimates, every: int, shift_mm: float) -> PoseEstimates:
    """The estimates with every ``every``-th one moved ``shift_mm`` along the camera x axis."""
    move = np.zeros_like(est.t)
    move[::every, 0] = shift_mm
    fields = {k: getattr(est, k) for k in ("scene_id", "im_id", "obj_id", "score", "R", "time")}
    return PoseEstimates.from_arrays(**fields, t=est.t + move)


@pytest.fixture(scope="module")
def evals(tmp_path_factory):
    """Two evaluations of one example split: the example's results ("good") and the same with
    every second estimate moved 8 mm ("worse")."""
    root = tmp_path_factory.mktemp("cmp")
    ex = write_example_dataset(root / "ex", ExampleSpec(scenes=1, images_per_scene=8))
    save_results(root / "worse.csv", _shifted(load_results(ex.results), 2, 8.0))
    dirs = []
    for name, csv in (("good", ex.results), ("worse", root / "worse.csv")):
        out = root / name
        args = ["eval", str(ex.root), str(csv), "--out", str(out), "--renderer", "none"]
        assert main([*args, "--bootstrap", "20", "--no-progress"]) == 0
        dirs.append(out)
    return ex, dirs


@pytest.fixture(scope="module")
def compared(evals, tmp_path_factory):
    """compare --figures --rerun of the two evaluations."""
    pytest.importorskip("matplotlib")
    pytest.importorskip("rerun")
    _, dirs = evals
    out = tmp_path_factory.mktemp("cmp_out")
    argv = ["compare", *map(str, dirs), "--out", str(out), "--bootstrap", "50"]
    assert main([*argv, "--figures", "--rerun"]) == 0
    return out


def _one_line_error(capsys, argv) -> str:
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert "Traceback" not in captured.err + captured.out
    return lines[0]


# -- figures ------------------------------------------------------------------------------


def test_compare_figures_are_written(compared):
    names = ("fig2_gt_distributions", "fig4_error_histograms", "recall_curves", "bop24_pr_curves")
    for name in names:
        assert (compared / "figures" / f"{name}.png").read_bytes()[:4] == b"\x89PNG"
        assert (compared / "figures" / f"{name}.pdf").read_bytes()[:5] == b"%PDF-"
    assert (compared / "compare.json").is_file()


def test_error_histograms_draw_one_series_and_median_per_method(evals):
    pytest.importorskip("matplotlib")
    from bopsurg.viz.figures import matched_errors, plot_error_histograms

    _, dirs = evals
    errors = {d.name: pd.read_csv(d / "errors.csv") for d in dirs}
    errors["third"] = errors["good"].assign(te=errors["good"]["te"] * 3)
    fig = plot_error_histograms(errors, 0.3)
    for ax, col in zip(fig.axes, ("re", "te", "mssd"), strict=True):
        _, labels = ax.get_legend_handles_labels()
        assert [lab.split(",")[0] for lab in labels] == ["good", "worse", "third"]
        for lab, e in zip(labels, errors.values(), strict=True):
            med = np.median(matched_errors(e, 0.3)[col].dropna())
            assert lab.endswith(f"median {med:.2f}")
        medians = [line.get_xdata()[0] for line in ax.get_lines()]
        assert len(medians) == 3
    fig.clf()
    # One evaluation: as eval --figures draws it (filled bars, no legend).
    fig = plot_error_histograms(errors["good"], 0.3)
    assert all(ax.get_legend() is None for ax in fig.axes)


def test_recall_curves_draw_one_curve_per_method(evals):
    pytest.importorskip("matplotlib")
    from bopsurg.viz.figures import plot_recall_curves

    _, dirs = evals
    errors = {d.name: pd.read_csv(d / "errors.csv") for d in dirs}
    n_gt = json.loads((dirs[0] / "summary.json").read_text())["gt_instances"]
    fig = plot_recall_curves(errors, n_gt, 0.3)
    for ax in fig.axes:
        lines = ax.get_lines()
        assert [line.get_label() for line in lines] == ["good", "worse"]
        # The last step of a curve is the recall over every matched instance.
        assert all(line.get_ydata()[-1] <= 1.0 for line in lines)
    te = fig.axes[1].get_lines()
    assert te[0].get_color() != te[1].get_color()
    fig.clf()


def test_pr_curves_from_samples_equal_those_of_the_evaluation(tmp_path):
    pytest.importorskip("matplotlib")
    from bopsurg.viz.figures import mean_aps, plot_pr_curves, pr_runs

    ds, est = _hand_dataset(tmp_path)
    det = bop24.evaluate_bop24(ds, est)
    DetectionSamples.from_evaluation(det).save(tmp_path / "s.npz")
    samples = DetectionSamples.load(tmp_path / "s.npz")
    assert samples.obj_ids is not None
    assert samples.obj_ids.tolist() == [1]
    assert mean_aps(samples) == pytest.approx(mean_aps(det))
    assert mean_aps(samples)["mssd"] == pytest.approx(det.scores["bop24_mAP_mssd"])
    a, b = pr_runs(det), pr_runs(samples)
    assert a.keys() == b.keys()
    for name in a:
        assert len(a[name]) == len(b[name]) == 3  # one object, three thresholds
        for ra, rb in zip(a[name], b[name], strict=True):
            assert (ra.obj_id, ra.threshold, ra.targets) == (rb.obj_id, rb.threshold, rb.targets)
            assert np.array_equal(ra.tp, rb.tp)
    fig = plot_pr_curves({"eval": det, "samples": samples})
    for ax in fig.axes:
        labels = [line.get_label() for line in ax.get_lines()]
        assert sum(lab.startswith("eval: obj 1") for lab in labels) == 3
        assert sum(lab.startswith("samples: obj 1") for lab in labels) == 3
        assert "eval 0.505" in ax.get_title()
        assert "samples 0.505" in ax.get_title()
    fig.clf()


def test_samples_written_before_object_ids_still_load(tmp_path):
    ds, est = _hand_dataset(tmp_path)
    samples = DetectionSamples.from_evaluation(bop24.evaluate_bop24(ds, est))
    samples.obj_ids = None
    samples.save(tmp_path / "old.npz")
    with np.load(tmp_path / "old.npz") as z:
        assert "obj_ids" not in z.files
    pytest.importorskip("matplotlib")
    from bopsurg.viz.figures import pr_runs

    old = DetectionSamples.load(tmp_path / "old.npz")
    assert old.obj_ids is None
    assert pr_runs(old)["mssd"][0].object_name() == "obj #1"


# -- the recording --------------------------------------------------------------------------


def test_recording_holds_both_methods_on_one_timeline(compared, evals):
    path = compared / "compare.rrd"
    assert path.stat().st_size > 0
    chunks = read_chunks(path)
    expected = {
        *(f"/metrics/{m}/{k}" for m in ("re", "te", "mssd", "mspd") for k in ("good", "worse")),
        *(f"/diff/{m}/worse" for m in ("re", "te", "mssd", "mspd")),
        "/diff/regressions/worse",
        "/frame_info/scene_id",
        "/frame_info/im_id",
        *(
            f"/differences/worse/{g}/{p}"
            for g in ("scores", "table")
            for p in ("points", "intervals", "zero")
        ),
        "/report/differences",
        "/report/regressions",
    }  # fmt: skip
    assert set(chunks) >= expected
    folders = load_eval_folders(evals[1])
    frames = comparison_frames(folders)
    good, worse = (
        scalar_series(chunks, "/metrics/mssd/good"),
        scalar_series(chunks, "/metrics/mssd/worse"),
    )
    assert good.to_numpy() == pytest.approx(frames["mssd/good"].dropna().to_numpy())
    assert worse.to_numpy() == pytest.approx(frames["mssd/worse"].dropna().to_numpy())
    diff = scalar_series(chunks, "/diff/mssd/worse")
    both = good.index.intersection(worse.index)
    assert diff.index.tolist() == both.tolist()
    assert diff.to_numpy() == pytest.approx((worse[both] - good[both]).to_numpy())
    assert (diff > 1.0).any()  # the moved estimates
    # The regression markers: rank 1 on the frame with the largest increase.
    ranks = scalar_series(chunks, "/diff/regressions/worse")
    assert ranks.idxmin() == diff.idxmax()
    text = chunks["/report/regressions"][0].to_record_batch().to_pylist()[0]
    assert f"| 1 | {diff.idxmax()} |" in str(text)


def test_recording_forest_plot_is_the_compared_differences(compared, evals):
    report = json.loads((compared / "compare.json").read_text())
    comparison = report["comparisons"][str(evals[1][1])]
    chunks = read_chunks(compared / "compare.rrd")
    rb = chunks["/differences/worse/table/points"][0].to_record_batch().to_pylist()[0]
    labels = rb["Points2D:labels"]
    xs = [p[0] for p in rb["Points2D:positions"]]
    assert [lab.split(":")[0] for lab in labels] == [
        k for k in comparison if k.split("_")[-1] in ("mean", "std", "median")
    ]
    for lab, x in zip(labels, xs, strict=True):
        assert x == pytest.approx(comparison[lab.split(":")[0]]["diff"], rel=1e-6)


def test_comparison_frames_share_one_numbering():
    def folder(key, rows):
        errors = pd.DataFrame(
            rows, columns=["scene_id", "im_id", "gt_id", "visib_fract", "re", "te", "mssd"]
        )
        return EvalFolder(None, key, key, errors, {}, None, None)  # type: ignore[arg-type]

    a = folder("a", [(1, 0, 0, 1.0, 1.0, 1.0, 2.0), (1, 2, 0, 1.0, 1.0, 1.0, 3.0)])
    b = folder(
        "b",
        [
            (1, 2, 0, 1.0, 1.0, 1.0, 9.0),
            (1, 2, 1, 1.0, 1.0, 1.0, 4.0),  # the frame's largest: 9
            (1, 1, -1, np.nan, np.nan, np.nan, np.nan),  # an unmatched estimate: a frame
            (2, 0, 0, 1.0, 1.0, 1.0, 1.0),
        ],
    )
    frames = comparison_frames([a, b])
    assert frames[["frame", "scene_id", "im_id"]].values.tolist() == [
        [0, 1, 0], [1, 1, 1], [2, 1, 2], [3, 2, 0],
    ]  # fmt: skip
    assert frames["mssd/a"].tolist()[::2] == [2.0, 3.0]
    assert np.isnan(frames["mssd/a"].tolist()[3])
    assert frames["mssd/b"].tolist()[1:] == [pytest.approx(np.nan, nan_ok=True), 9.0, 1.0]
    top = worst_regressions(frames, "a", "b")
    # Frame 0: a matched, b did not (+inf, first); frame 2: 9 - 3; nothing else is worse.
    assert top["frame"].tolist() == [0, 2]
    assert top["diff"].tolist() == [np.inf, 6.0]
    assert worst_regressions(frames, "a", "b", n=1)["frame"].tolist() == [0]
    # The other way round: a missed frame 3, which b matched; frame 2 is better for a.
    assert worst_regressions(frames, "b", "a")["frame"].tolist() == [3]


def test_forest_rows_split_scales_and_geometry_follows_the_intervals():
    from bopsurg.evaluation.bootstrap import Comparison

    comparison = {
        "re_median": Comparison(5.0, 8.0, 3.0, (1.0, 4.0), 0.0),
        "bop24_mAP": Comparison(0.5, 0.4, -0.1, (-0.2, 0.05), 0.3),
        "recall_re<5deg": Comparison(0.5, 0.4, -0.1, (-0.15, -0.05), 0.01),
        "te_std": Comparison(1.0, np.nan, np.nan, (np.nan, np.nan), np.nan),
    }
    rows = forest_rows(comparison)
    assert [r.key for r in rows["table"]] == ["re_median"]
    assert [r.key for r in rows["scores"]] == ["bop24_mAP", "recall_re<5deg"]
    assert [r.significant for r in rows["scores"]] == [False, True]
    geo = forest_geometry(rows["scores"])
    assert geo["points"][:, 0].tolist() == [-0.1, -0.1]
    assert geo["intervals"][1][:, 0].tolist() == [-0.15, -0.05]
    assert geo["points"][1, 1] > geo["points"][0, 1]  # one row below the other
    assert geo["zero"][:, 0].tolist() == [0.0, 0.0]


def test_labels_and_keys_are_unique():
    from pathlib import Path

    assert method_labels([Path("x/a"), Path("y/b")]) == ["a", "b"]
    assert method_labels([Path("x/eval"), Path("y/eval")]) == ["x/eval", "y/eval"]
    assert entity_keys(["x/eval", "x.eval", "é"]) == ["x_eval", "x_eval_2", "eval"]


# -- bad inputs ----------------------------------------------------------------------------


def _installed_output_flags(rrd: str) -> list[list[str]]:
    """The output options (--figures, --rerun FILE) whose dependency is installed: compare
    checks it before reading the folders."""
    flags = [
        flag
        for module, flag in (("matplotlib", ["--figures"]), ("rerun", ["--rerun", rrd]))
        if importlib.util.find_spec(module) is not None
    ]
    if not flags:
        pytest.skip("needs matplotlib (bopsurg[figures]) or rerun-sdk (bopsurg[rerun])")
    return flags


def test_folder_without_errors_csv_is_a_one_line_error(evals, tmp_path, capsys):
    _, dirs = evals
    coco_like = tmp_path / "no_errors"
    shutil.copytree(dirs[1], coco_like)
    (coco_like / "errors.csv").unlink()
    for flag in _installed_output_flags(str(tmp_path / "x.rrd")):
        argv = ["compare", str(dirs[0]), str(coco_like), "--out", str(tmp_path / "o"), *flag]
        line = _one_line_error(capsys, argv)
        assert "errors.csv: missing" in line
    assert not (tmp_path / "x.rrd").exists()
    assert not (tmp_path / "o").exists()  # failed before writing anything


def test_different_test_sets_are_a_one_line_error(evals, tmp_path, capsys):
    _, dirs = evals
    _hand_dataset(tmp_path)
    other = tmp_path / "hand"
    argv = ["eval", str(tmp_path), str(tmp_path / "r.csv"), "--out", str(other)]
    assert main([*argv, "--bootstrap", "0"]) == 0
    capsys.readouterr()
    for flag in _installed_output_flags("x.rrd"):
        argv = ["compare", str(dirs[0]), str(other), "--out", str(tmp_path / "o"), *flag]
        assert "different test sets" in _one_line_error(capsys, argv)


def test_fig2_refuses_datasets_with_different_gt(evals, tmp_path):
    _, dirs = evals
    _hand_dataset(tmp_path)
    folders = load_eval_folders(dirs)
    same = comparison_gt(folders)
    assert same is not None
    distance, visib = same
    assert len(distance) >= folders[0].summary["gt_instances"]
    assert np.all(distance > 0)
    assert np.all((visib >= 0) & (visib <= 1))

    def moved(f, root):
        return dataclasses.replace(f, summary={**f.summary, "dataset": str(root), "split": "test"})

    with pytest.raises(BopsurgError, match="different GT"):
        comparison_gt([folders[0], moved(folders[1], tmp_path)])
    assert comparison_gt([moved(f, tmp_path / "gone") for f in folders]) is None


def test_option_errors_are_one_line(evals, tmp_path, capsys):
    _, dirs = evals
    base = ["compare", *map(str, dirs)]
    assert "give --out" in _one_line_error(capsys, [*base, "--figures"])
    assert "give --out" in _one_line_error(capsys, [*base, "--rerun"])
    line = _one_line_error(capsys, ["compare", "--rerun", *map(str, dirs)])
    assert f"--rerun {dirs[0]}: a folder" in line


MISSING = [
    ("matplotlib", "--figures", "figures need matplotlib"),
    ("rerun", "--rerun", "pip install bopsurg[rerun]"),
]


@pytest.mark.parametrize(("module", "flag", "message"), MISSING)
def test_missing_optional_dependency_is_one_line(
    evals, tmp_path, capsys, monkeypatch, module, flag, message
):
    _, dirs = evals
    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == module or name.startswith(module + "."):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    argv = ["compare", *map(str, dirs), "--out", str(tmp_path / "o"), flag]
    assert message in _one_line_error(capsys, argv)
