"""BOP19 scores: the vectorised evaluation equals a sequential re-statement of the reference."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bopsurg import metrics
from bopsurg.bop.dataset import BopDataset
from bopsurg.evaluation import bop19
from bopsurg.evaluation.bop19_pairs import TargetTable, kept_pairs
from bopsurg.evaluation.matching import greedy_match, valid_gts_localization
from bopsurg.evaluation.runner import evaluate
from bopsurg.evaluation.vsd_pairs import VsdInputs, vsd_errors
from bopsurg.evaluation.vsd_worker import VsdWorker
from tests.bopsurg.evaluation import reference_scoring as ref


def _oracle_inputs(synth):
    gts = {
        (s, i): [ref.Gt(g.obj_id, synth.infos[s][i][k].visib_fract, g) for k, g in enumerate(gl)]
        for s, ims in synth.gts.items()
        for i, gl in ims.items()
    }
    est = synth.est
    ests = [
        ref.Est(int(est.scene_id[k]), int(est.im_id[k]), int(est.obj_id[k]), float(est.score[k]), k)
        for k in range(len(est))
    ]
    targets = [
        {"scene_id": t.scene_id, "im_id": t.im_id, "obj_id": t.obj_id, "inst_count": t.inst_count}
        for t in BopDataset(synth.root, "test").targets()
    ]
    return gts, ests, targets


def test_convention_thresholds_are_the_references_floats():
    assert bop19.MSSD_THRESHOLDS[2] == 0.15000000000000002
    assert bop19.MSSD_THRESHOLDS[6] == 0.35000000000000003
    assert bop19.MSPD_THRESHOLDS == (5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0)


def test_mssd_and_mspd_recalls_equal_the_sequential_reference(synth):
    ds = BopDataset(synth.root, "test")
    result = evaluate(ds, synth.est)
    gts, ests, targets = _oracle_inputs(synth)
    est = synth.est

    def mssd_err(e, g):
        k = e.pose
        diameter = synth.models_info[g.obj_id]["diameter"]
        if np.linalg.norm(est.t[k] - g.pose.t) >= diameter:
            return float("inf")
        syms = metrics.symmetry_transforms(synth.models_info[g.obj_id])
        v = metrics.mssd(est.R[k], est.t[k], g.pose.R, g.pose.t, synth.models[g.obj_id].pts, syms)
        return float(v[0]) / diameter

    def mspd_err(e, g):
        k = e.pose
        syms = metrics.symmetry_transforms(synth.models_info[g.obj_id])
        K = ds.scene(e.scene_id).camera[e.im_id].K
        v = metrics.mspd(
            est.R[k], est.t[k], g.pose.R, g.pose.t, K, synth.models[g.obj_id].pts, syms
        )
        return float(v[0]) * 640.0 / 640

    for name, fn, ths in (
        ("mssd", mssd_err, bop19.MSSD_THRESHOLDS),
        ("mspd", mspd_err, bop19.MSPD_THRESHOLDS),
    ):
        errs = ref.calc_errors(gts, targets, ests, fn)
        expected = [ref.recall(gts, targets, errs, th) for th in ths]
        assert result.curves[name].recalls == pytest.approx(expected, abs=0), name
    # The synthetic set must exercise the interesting cases, or this test proves little.
    r = result.curves["mssd"].recalls
    assert 0.0 < r[0] < r[-1] < 1.0
    assert result.scores["bop19_average_recall_mssd"] == pytest.approx(np.mean(r))
    assert "bop19_average_recall" not in result.scores  # no VSD without a renderer


def test_hand_worked_recall():
    # One image, obj 1 twice (visib 0.9 and 0.2), inst_count 1 -> only GT 0 is valid.
    # Estimates (score order): A err to GT0 = 0.30, to GT1 = 0.01; B err GT0 = 0.04.
    # Threshold 0.05: A takes nothing valid below 0.05 (GT1 invalid) -> B takes GT0 -> recall 1.
    # Threshold 0.35: A takes GT0 (0.30), B finds GT0 matched -> recall 1; targets = 1.
    valid = valid_gts_localization([0, 0], [0.9, 0.2], [1, 1])
    assert valid.tolist() == [True, False]
    rank, est_i, gt_i = [0, 0, 1, 1], [0, 0, 1, 1], [0, 1, 0, 1]
    err = [0.30, 0.01, 0.04, 0.5]
    m = greedy_match(rank, est_i, gt_i, err, 0.05, valid)
    assert m.tolist() == [2, -1]
    m = greedy_match(rank, est_i, gt_i, err, 0.35, valid)
    assert m.tolist() == [0, -1]
    m = greedy_match(rank, est_i, gt_i, err, 0.30, valid)  # strict: 0.30 is not < 0.30
    assert m.tolist() == [2, -1]


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 3), st.integers(0, 3), st.floats(0, 1), st.booleans()),
        min_size=1,
        max_size=40,
    ),
    st.sampled_from([0.1, 0.5, 0.9]),
)
def test_greedy_match_equals_sequential(pairs, threshold):
    # 4 estimates (rank = estimate id) x 4 GTs in a single group; random subset of pairs.
    seen = {}
    for e, g, err, _ in pairs:
        seen[(e, g)] = err
    valid = [True, False, True, True]
    keys = sorted(seen)
    m = greedy_match(
        [k[0] for k in keys], [k[0] for k in keys], [k[1] for k in keys],
        [seen[k] for k in keys], threshold, valid,
    )  # fmt: skip
    errs = [
        {
            "est_id": e,
            "score": 1.0 - e / 10,
            "errors": {g: seen[(e, g)] for g in range(4) if (e, g) in seen},
        }
        for e in range(4)
    ]
    expected = {mm["gt_id"]: mm["est_id"] for mm in ref.match_poses(errs, threshold, valid)}
    got = {g: keys[p][0] for g, p in enumerate(m) if p >= 0}
    assert got == expected


class _WholeImageRenderer:
    """A renderer with ``render_depth`` only (the plugin protocol's minimum)."""

    def __init__(self, inner):
        self.inner = inner

    def render_depth(self, model, R, t, K, width, height):
        return self.inner.render_depth(model, R, t, K, width, height)


def _dataset_with_depth(tmp_path):
    """The example dataset (6 images) with depth images: the needle on a plane, a bar
    occluding, missing measurements."""
    from bopsurg.bop.images import save_depth
    from bopsurg.example import ExampleSpec, write_example_dataset
    from bopsurg.generators.depth_renderer import PyBulletDepthRenderer

    ex = write_example_dataset(tmp_path, ExampleSpec(seed=5, scenes=1, images_per_scene=6))
    ds = BopDataset(ex.root, ex.split)
    renderer = PyBulletDepthRenderer()
    w, h = ds.image_size()
    rng = np.random.default_rng(0)
    for im_id, cam in ds.scene(1).camera.items():
        scene_depth = np.full((h, w), 1000.0)
        scene_depth[:, w // 2 : w // 2 + 40] = 60.0
        scene_depth[rng.random((h, w)) < 0.05] = 0.0  # missing measurements
        for g in ds.scene(1).gt.get(im_id, []):
            d = renderer.render_depth(ds.model(g.obj_id), g.R, g.t, cam.K, w, h)
            scene_depth = np.where(d > 0, np.minimum(scene_depth, d + 2.0), scene_depth)
        save_depth(ds.scene(1).depth_path(im_id), scene_depth / cam.depth_scale)
    return ex, ds, renderer


def test_vsd_errors_equal_whole_image_vsd_of_every_pair(tmp_path):
    """Windows (rendered and decoded) change nothing: the errors of every kept pair are those
    of metrics.vsd on the whole depth images, bit for bit, with a windowed renderer, with
    one that renders whole images only, and on the VSD worker process."""
    pytest.importorskip("pybullet")
    from bopsurg.bop.images import load_depth
    from bopsurg.bop.results import load_results
    from bopsurg.evaluation.pair_errors import ModelCache
    from bopsurg.evaluation.tables import load_gt_table

    ex, ds, renderer = _dataset_with_depth(tmp_path)
    w, h = ds.image_size()
    est = load_results(ex.results)
    gt = load_gt_table(ds)
    pairs = kept_pairs(est, gt, TargetTable.of(ds.targets()))
    e_idx, g_idx = pairs.est_index, pairs.gt_index
    diam = ModelCache(ds, 0.01).diameters(gt.obj_id[g_idx])
    got = [
        vsd_errors(est, gt, e_idx, g_idx, diam, VsdInputs(ds, r))
        for r in (renderer, _WholeImageRenderer(renderer))
    ]
    worker = VsdWorker.start("pybullet")  # the same job on the worker process
    assert worker is not None
    got.append(vsd_errors(est, gt, e_idx, g_idx, diam, VsdInputs(ds, renderer, worker=worker)))
    want = np.ones((10, e_idx.size))
    for p, (e, g) in enumerate(zip(e_idx, g_idx, strict=True)):
        cam = ds.scene(int(gt.scene_id[g])).camera[int(gt.im_id[g])]
        test = load_depth(ds.scene(1).depth_path(int(gt.im_id[g]))) * cam.depth_scale
        model = ds.model(int(gt.obj_id[g]))
        d_est = renderer.render_depth(model, est.R[e], est.t[e], cam.K, w, h)
        d_gt = renderer.render_depth(model, gt.R[g], gt.t[g], cam.K, w, h)
        want[:, p] = metrics.vsd(test, d_est, d_gt, cam.K, 15.0, bop19.VSD_TAUS, float(diam[p]))
    assert e_idx.size >= 3
    assert np.any((want > 0) & (want < 1))  # partial errors: the windows are exercised
    for errors in got:
        np.testing.assert_array_equal(errors, want)


class _FrontWorker:
    """A VSD worker stand-in that has taken the first ``k`` images (their claim files exist)
    and answers their errors: the split with this process is then known in advance."""

    def __init__(self, inputs: VsdInputs, k: int, fail: bool = False) -> None:
        self.inputs, self.k, self.fail = inputs, k, fail
        self.claims: str | None = None

    def submit(self, job, *, progress: bool = False, claims: str | None = None) -> None:
        from pathlib import Path

        assert claims is not None  # no progress bar: the images are shared out
        self.job, self.claims = job, claims
        for i in range(self.k):
            (Path(claims) / str(i)).touch()

    def result(self):
        from bopsurg.evaluation.vsd_images import vsd_errors as job_errors
        from bopsurg.evaluation.vsd_images import window_renderer
        from bopsurg.evaluation.vsd_worker import VsdWorkerError

        if self.fail:
            raise VsdWorkerError("died")
        render = window_renderer(self.inputs.renderer)
        return job_errors(self.job, render, self.job.images[: self.k])

    def close(self) -> None:
        pass


@pytest.mark.parametrize(("k", "fail"), [(0, False), (1, False), (2, False), (1, True)])
def test_vsd_shared_with_the_worker_equals_vsd_here(tmp_path, k, fail):
    """The worker's images and those this process takes from the back make up the errors of
    VSD computed here alone, bit for bit, whatever the split; a worker that fails after
    the split leaves its images to this process."""
    pytest.importorskip("pybullet")
    from bopsurg.bop.results import load_results
    from bopsurg.evaluation.pair_errors import ModelCache
    from bopsurg.evaluation.tables import load_gt_table

    ex, ds, renderer = _dataset_with_depth(tmp_path)
    est = load_results(ex.results)
    gt = load_gt_table(ds)
    pairs = kept_pairs(est, gt, TargetTable.of(ds.targets()))
    e_idx, g_idx = pairs.est_index, pairs.gt_index
    diam = ModelCache(ds, 0.01).diameters(gt.obj_id[g_idx])
    want = vsd_errors(est, gt, e_idx, g_idx, diam, VsdInputs(ds, renderer))
    inputs = VsdInputs(ds, renderer)
    fake = _FrontWorker(inputs, k, fail)
    shared = VsdInputs(ds, renderer, worker=fake)  # type: ignore[arg-type]
    got = vsd_errors(est, gt, e_idx, g_idx, diam, shared)
    np.testing.assert_array_equal(got, want)
    assert fake.claims is not None
    assert len(fake.job.images) >= 3  # k = 2 leaves this process one image
    assert not os.path.exists(fake.claims)  # the claim folder is removed


def test_cli_eval_with_its_vsd_worker_equals_evaluate_in_this_process(tmp_path, monkeypatch):
    """'bopsurg eval' renders VSD on its worker process while it does the rest; the scores
    are those of evaluate() rendering in this process."""
    pytest.importorskip("pybullet")
    import json

    from bopsurg.bop.results import PoseEstimates, load_results, save_results
    from bopsurg.cli.main import main
    from bopsurg.evaluation.tables import load_gt_table

    ex, ds, renderer = _dataset_with_depth(tmp_path)
    answered = []
    collect = VsdWorker.result

    def spy(self):
        errors = collect(self)
        answered.append(errors.shape)
        return errors

    monkeypatch.setattr(VsdWorker, "result", spy)
    gt = load_gt_table(ds)  # estimates: the GT poses moved away by 0 to 3 mm
    shift = np.random.default_rng(1).uniform(0.0, 3.0, size=(len(gt), 1)) * [0.0, 0.0, 1.0]
    est = PoseEstimates.from_arrays(scene_id=gt.scene_id, im_id=gt.im_id, obj_id=gt.obj_id,
                                    score=np.ones(len(gt)), R=gt.R, t=gt.t + shift)  # fmt: skip
    csv = tmp_path / "results.csv"
    save_results(csv, est)
    out = tmp_path / "cli"
    argv = ["eval", str(ex.root), str(csv), "--out", str(out), "--bootstrap", "0"]
    assert main([*argv, "--split", ex.split]) == 0
    assert len(answered) == 1  # the worker computed VSD
    scores = json.loads((out / "scores.json").read_text())
    result = evaluate(ds, load_results(csv), renderer=renderer)
    assert 0.0 < scores["bop19_average_recall_vsd"] < 1.0  # the case exercises VSD
    for key in ("bop19_average_recall_vsd", "bop19_average_recall"):
        assert scores[key] == result.scores[key]
    assert scores["details"]["vsd"]["tp_counts"] == result.curves["vsd"].tp_counts
