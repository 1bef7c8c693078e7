"""Bootstrap intervals of the BOP24 scores: unit weights give the scores, weights equal
explicit resampling, seeds reproduce, and the paired comparison."""

from __future__ import annotations

import json
from unittest import mock

import numpy as np
import pytest

from bopsurg.bop.results import PoseEstimates, save_results
from bopsurg.cli.main import main
from bopsurg.errors import BopsurgError, InputError
from bopsurg.evaluation import bootstrap, bop24
from bopsurg.evaluation.bootstrap import (
    DetectionSamples,
    bop19_intervals,
    bop19_replicates,
    compare_bop19,
    compare_samples,
    confidence_intervals,
    load_bop19_counts,
    replicate_scores,
    resample_weights,
    resampling_units,
    save_bop19_counts,
    weighted_ap,
    weighted_ap_runs,
)
from bopsurg.evaluation.bop19 import RecallCurve
from bopsurg.evaluation.runner import evaluate, evaluate_distributed
from bopsurg.evaluation.summary_ci import (
    TABLE_SAMPLES_FILENAME,
    compare_tables,
    summary_intervals,
    table_rows,
    weighted_median,
)
from bopsurg.executors import make_executor
from tests.bopsurg.evaluation import bop24_oracle
from tests.bopsurg.evaluation.test_bop24 import KEYS, _hand_dataset


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    ds, est, _ = bop24_oracle.build_case(tmp_path_factory.mktemp("b") / "ds", 0)
    det = bop24.evaluate_bop24(ds, est)
    return ds, est, det, DetectionSamples.from_evaluation(det)


def test_unit_weights_give_the_scores(case):
    _, _, det, samples = case
    reps = replicate_scores(samples, np.ones((3, len(samples.images))))
    for key in KEYS[:-1]:
        assert np.all(reps[key] == det.scores[key]), key


@pytest.mark.parametrize("seed", range(40))
def test_weighted_ap_equals_ap_of_the_repeated_ranking(seed):
    # Drawing an image w times repeats its estimates w times, adjacent in the ranking; all
    # replicates (rows) at once.
    rng = np.random.default_rng(seed)
    n, b = int(rng.integers(1, 25)), 6
    tp = rng.random(n) < rng.random()
    w = rng.integers(0, 4, (b, n)).astype(float)
    total = (w @ tp + rng.integers(0, 3, b)).astype(float)
    total[0] = 0.0  # no targets in a replicate: NaN
    got = weighted_ap(w, tp, total)
    assert np.isnan(got[0])
    for row in range(1, b):
        rep_tp = np.repeat(tp, w[row].astype(int))
        c = np.cumsum(rep_tp)
        if total[row] == 0:
            assert np.isnan(got[row])
            continue
        expected = bop24.interpolated_ap(c / total[row], c / np.arange(1, c.size + 1))
        assert got[row] == pytest.approx(expected, abs=1e-12), row


@pytest.mark.parametrize("seed", range(30))
def test_the_rankings_at_once_equal_each_ranking_alone_bit_for_bit(seed):
    # Rankings of different lengths (padding), without TPs, TPs of weight 0 (images not
    # drawn), replicates without targets; one batch and several (a small block).
    rng = np.random.default_rng(seed)
    n_img, b = int(rng.integers(1, 30)), int(rng.integers(1, 9))
    w = rng.multinomial(n_img, np.full(n_img, 1 / n_img), size=b).astype(np.float64)
    runs = []
    for _ in range(int(rng.integers(1, 7))):
        n = int(rng.integers(0, 40))
        runs.append((rng.integers(0, n_img, n), rng.random(n) < rng.random()))
    total = rng.integers(0, 12, (b, len(runs))).astype(np.float64)
    expected = np.stack(
        [weighted_ap(w[:, img], tp, total[:, r]) for r, (img, tp) in enumerate(runs)], axis=1
    )
    np.testing.assert_array_equal(weighted_ap_runs(w, runs, total), expected)
    with mock.patch.object(bootstrap, "_RUNS_BLOCK", 50):
        np.testing.assert_array_equal(weighted_ap_runs(w, runs, total), expected)


def test_weights_equal_explicit_resampling(case):
    """A replicate's scores equal evaluating the resampled dataset's images by hand: with
    the image weights of one replicate, rebuild each ranking by repetition."""
    _, _, _, samples = case
    w = resample_weights(resampling_units(samples.images, "image"), 1, seed=3)
    reps = replicate_scores(samples, w)
    mean_ap = {}
    run = 0
    for name, ths in samples.error_types.items():
        per_obj = []
        for k in range(samples.targets.shape[1]):
            total = float(w[0] @ samples.targets[:, k])
            aps = []
            for _ in ths:
                lo, hi = samples.offsets[run], samples.offsets[run + 1]
                img, tp = samples.est_image[lo:hi], samples.est_tp[lo:hi]
                rep = np.repeat(tp, w[0, img].astype(int))
                c = np.cumsum(rep)
                aps.append(bop24.interpolated_ap(c / total, c / np.arange(1, c.size + 1)))
                run += 1
            if total > 0:
                per_obj.append(np.mean(aps))
        mean_ap[name] = np.mean(per_obj)
    for key, value in bop24.score_keys(mean_ap).items():
        assert reps[key][0] == pytest.approx(value, abs=1e-12), key


def test_intervals_are_seeded_and_contain_the_score(case, tmp_path):
    _, _, det, samples = case
    path = tmp_path / "s.npz"
    samples.save(path)
    loaded = DetectionSamples.load(path)
    a = confidence_intervals(loaded, 200, seed=1)
    assert a == confidence_intervals(samples, 200, seed=1)
    assert a != confidence_intervals(samples, 200, seed=2)
    for key in KEYS[:-1]:
        lo, hi = a[key]
        assert lo < det.scores[key] < hi, key
    scene = confidence_intervals(samples, 200, seed=1, unit="scene")
    assert scene != a


def test_scene_units_draw_whole_scenes():
    images = np.array([[1, 0], [1, 1], [2, 0], [3, 5], [3, 6]])
    units = resampling_units(images, "scene")
    assert units.tolist() == [0, 0, 1, 2, 2]
    w = resample_weights(units, 50, seed=0)
    assert np.all(w[:, 0] == w[:, 1])
    assert np.all(w[:, 3] == w[:, 4])
    assert np.all(w[:, [0, 2, 3]].sum(axis=1) == 3)  # 3 scenes drawn per replicate


def _pushed_away(est: PoseEstimates, rows) -> PoseEstimates:
    """The estimates with the selected rows moved 0.5 m away (false positives)."""
    far = np.where(np.asarray(rows)[:, None], [0.0, 0.0, 500.0], 0.0)
    fields = {k: getattr(est, k) for k in ("scene_id", "im_id", "obj_id", "score", "R", "time")}
    return PoseEstimates.from_arrays(**fields, t=est.t + far)


def test_paired_comparison(tmp_path, case):
    _, _, _, samples = case
    same = compare_samples(samples, samples, 200)
    for c in same.values():
        assert c.diff == 0.0
        assert c.ci == (0.0, 0.0)
        assert c.p_value == 1.0
    # The same method with every estimate of even images pushed 0.5 m away (all FP): lower
    # AP, a difference the paired bootstrap must call significant.
    ds, est, det, _ = case
    worse_det = bop24.evaluate_bop24(ds, _pushed_away(est, est.im_id % 2 == 0))
    worse = DetectionSamples.from_evaluation(worse_det)
    res = compare_samples(worse, samples, 500, seed=0)
    for key, c in res.items():
        assert c.a == worse_det.scores[key], key
        assert c.b == det.scores[key], key
        assert c.diff == c.b - c.a
        assert c.ci[0] <= c.diff <= c.ci[1], key
    c = res["bop24_mAP"]
    assert c.diff > 0
    assert c.ci[0] > 0
    assert c.p_value < 0.05
    swapped = compare_samples(samples, worse, 500, seed=0)["bop24_mAP"]
    assert swapped.diff == -c.diff
    assert swapped.p_value == c.p_value
    hand_ds, hand_est = _hand_dataset(tmp_path)
    other = DetectionSamples.from_evaluation(bop24.evaluate_bop24(hand_ds, hand_est))
    with pytest.raises(BopsurgError, match="different target images"):
        compare_samples(samples, other)


def test_cli_eval_intervals_and_compare(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    _, est = _hand_dataset(tmp_path)
    save_results(tmp_path / "worse.csv", _pushed_away(est, est.score == 0.9))
    evals = []
    for name in ("r", "worse"):
        out = tmp_path / f"eval_{name}"
        args = ["eval", str(tmp_path), str(tmp_path / f"{name}.csv"), "--out", str(out)]
        assert main([*args, "--bootstrap", "200", "--seed", "4"]) == 0
        evals.append(str(out))
    scores = json.loads((tmp_path / "eval_r" / "scores.json").read_text())
    assert scores["bootstrap"] == {"replicates": 200, "unit": "image", "seed": 4}
    lo, hi = scores["ci95"]["bop24_mAP"]
    assert lo <= scores["bop24_mAP"] <= hi
    lo, hi = scores["ci95"]["bop19_average_recall_mssd"]
    assert lo <= scores["bop19_average_recall_mssd"] <= hi
    assert "95 % interval" in capsys.readouterr().out
    summary = json.loads((tmp_path / "eval_r" / "summary.json").read_text())
    lo, hi = summary["ci95"]["table"]["mssd"]["median"]
    assert lo <= summary["table"]["mssd"]["median"] <= hi
    assert summary["bootstrap"]["replicates"] == 200
    cmp_dir = tmp_path / "cmp"
    assert main(["compare", *evals, "--out", str(cmp_dir), "--bootstrap", "100"]) == 0
    table = capsys.readouterr().out
    assert "bop24_mAP" in table
    report = json.loads((cmp_dir / "compare.json").read_text())
    c = report["comparisons"][evals[1]]["bop24_mAP"]
    # The worse run turns the TP of image 0 into a FP; the duplicate then takes its GT.
    assert c["a"] == pytest.approx(51 / 101)
    assert c["diff"] == pytest.approx(c["b"] - c["a"])
    assert (cmp_dir / "compare.png").stat().st_size > 0
    # One-line errors: a folder without samples, a single folder.
    assert main(["compare", evals[0], str(tmp_path)]) == 2
    assert main(["compare", evals[0]]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2
    assert TABLE_SAMPLES_FILENAME in err[0]
    # The paper's table is compared too, on GT instances: both runs have the same table
    # except image 0's instance, whose estimate the worse run moved 0.5 m away.
    t = report["comparisons"][evals[1]]
    assert t["mssd_median"]["diff"] == pytest.approx(t["mssd_median"]["b"] - t["mssd_median"]["a"])
    assert t["te_mean"]["b"] > t["te_mean"]["a"]
    assert "recall_mssd<5mm" in t
    # BOP19 ARs are compared on the same images with valid GTs (the worse run misses one).
    ar = t["bop19_average_recall_mssd"]
    assert ar["b"] < ar["a"]
    assert ar["diff"] == pytest.approx(ar["b"] - ar["a"])


@pytest.mark.parametrize("seed", range(30))
def test_weighted_median_equals_median_of_the_repeated_values(seed):
    rng = np.random.default_rng(seed)
    n, b = int(rng.integers(1, 15)), 5
    values = rng.choice([1.0, 2.0, 2.5, 7.0], n) if seed % 2 else rng.normal(size=n)
    w = rng.integers(0, 4, (b, n)).astype(float)
    w[0] = 0.0
    got = weighted_median(values, w)
    assert np.isnan(got[0])
    for row in range(1, b):
        rep = np.repeat(values, w[row].astype(int))
        if rep.size:
            assert got[row] == np.median(rep), row


def test_summary_intervals_bracket_the_paper_table(case):
    ds, est, _, _ = case
    res = evaluate(ds, est, instance_metrics=["re", "te", "mssd", "mspd", "add", "adi"])
    ci = summary_intervals(res.gt_rows, 0.3, 300, seed=2)
    assert ci == summary_intervals(res.gt_rows, 0.3, 300, seed=2)
    for m, stats in ci["table"].items():
        for k, (lo, hi) in stats.items():
            assert lo <= res.summary["table"][m][k] <= hi, (m, k)
    for label, (lo, hi) in ci["recall"].items():
        assert lo <= res.summary["recall"][label] <= hi, label
    lo, hi = ci["add_auc"]
    assert lo <= res.summary["add_auc"] <= hi
    by_scene = summary_intervals(res.gt_rows, 0.3, 300, seed=2, unit="scene")
    assert by_scene["table"]["mssd"]["median"] != ci["table"]["mssd"]["median"]


def test_compare_tables_pairs_the_same_instances(case):
    ds, est, _, _ = case
    rows = table_rows(evaluate(ds, est, instance_metrics=["re", "te", "mssd"]).gt_rows, 0.3)
    same = compare_tables(rows, rows, 100)
    assert all(c.diff == 0.0 and c.p_value == 1.0 for c in same.values())
    worse = rows.assign(mssd=rows["mssd"] + 1.0)  # every MSSD 1 mm larger
    c = compare_tables(rows, worse, 200)["mssd_median"]
    assert c.diff == pytest.approx(1.0)
    assert c.ci == pytest.approx((1.0, 1.0))
    with pytest.raises(BopsurgError, match="different GT instances"):
        compare_tables(rows, rows.iloc[1:], 10)


def test_bop19_replicate_hand_worked():
    """Three images with 2, 1, 1 valid GTs; matched at two thresholds: 2, 0, 1 and 1, 1, 0.
    Drawing image 0 twice, image 2 once and image 1 never: recalls (4 + 1) / 5 = 1 and
    (2 + 0) / 5 = 0.4, so AR = 0.7; unit weights give the curve's own AR, 0.6."""
    curve = RecallCurve("mssd", [0.1, 0.2], [0.75, 0.5], [3, 2], 4)
    curve.image_ids = np.array([[1, 0], [1, 1], [2, 0]], dtype=np.int64)
    curve.image_targets = np.array([2, 1, 1], dtype=np.int64)
    curve.image_hits = np.array([[2, 0, 1], [1, 1, 0]], dtype=np.int64)
    reps = bop19_replicates({"mssd": curve}, np.array([[2.0, 0.0, 1.0], [1.0, 1.0, 1.0]]))
    assert reps["bop19_average_recall_mssd"] == pytest.approx([0.7, curve.average_recall])
    assert "bop19_average_recall" not in reps  # the overall AR needs VSD too


def test_bop19_unit_weights_give_the_ars_local_and_distributed(case):
    ds, est, _, _ = case
    local = evaluate(ds, est, progress=False)
    ids = local.curves["mssd"].image_ids
    assert ids is not None
    reps = bop19_replicates(local.curves, np.ones((1, len(ids))))
    for key, value in reps.items():
        assert value[0] == pytest.approx(local.scores[key], abs=1e-15), key
    split = evaluate_distributed(
        ds, est, executor=make_executor("local", workers=2), progress=False
    )
    for name, curve in local.curves.items():
        other = split.curves[name]
        assert other.image_ids is not None
        np.testing.assert_array_equal(other.image_ids, curve.image_ids)
        np.testing.assert_array_equal(other.image_hits, curve.image_hits)
    assert bop19_intervals(local.curves, 50, seed=1) == bop19_intervals(split.curves, 50, seed=1)


def test_bop19_counts_round_trip_and_bad_archive(case, tmp_path):
    ds, est, _, _ = case
    curves = evaluate(ds, est, progress=False).curves
    path = tmp_path / "b19.npz"
    save_bop19_counts(path, curves)
    back = load_bop19_counts(path)
    assert back is not None
    for name, c in curves.items():
        np.testing.assert_array_equal(back[name].image_hits, c.image_hits)
    assert compare_bop19(curves, back, 20)["bop19_average_recall_mssd"].diff == 0.0
    assert load_bop19_counts(tmp_path / "missing.npz") is None
    path.write_bytes(b"not an archive")
    with pytest.raises(InputError, match="BOP19 bootstrap archive"):
        load_bop19_counts(path)
