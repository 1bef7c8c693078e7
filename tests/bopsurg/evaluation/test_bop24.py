"""BOP24/BOP25 6D-detection AP: hand-worked cases and equality with the reference toolkit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bopsurg.bop.dataset import BopDataset, save_camera_json
from bopsurg.bop.meshes import compute_model_info, save_models_info, save_ply
from bopsurg.bop.results import PoseEstimates, save_results
from bopsurg.bop.scene import (
    CameraInfo,
    GtInfo,
    GtPose,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from bopsurg.bop.targets import ImageTarget, load_image_targets
from bopsurg.cli.main import main
from bopsurg.evaluation import bop24
from bopsurg.example import DEFAULT_K
from bopsurg.needle import NeedleSpec, needle_mesh
from tests.bopsurg.evaluation import bop24_oracle

KEYS = (
    "bop24_mAP_mssd",
    "bop24_mAP_mssd_mm",
    "bop24_mAP_mspd",
    "bop24_mAP",
    "bop25_mAP",
    "bop25_mAP_mm",
    "bop24_average_time_per_image",
)


def _calc_ap_reference(rec, pre):
    """``score.calc_ap`` of the reference, restated as written there."""
    i = np.argsort(rec)
    mrec = np.concatenate(([0], np.array(rec)[i], [1]))
    mpre = np.concatenate(([0], np.array(pre)[i], [0]))
    out = []
    for rt in np.linspace(0.0, 1.00, 101, endpoint=True):
        out.append(np.max(mpre[mrec >= rt]) if np.any(mrec >= rt) else 0.0)
    return np.mean(out)


def test_ap_of_the_references_own_example_is_hand_worked():
    # score.py's self-test: TP F,T,T,F,T,F over 6 targets. Recall points 0..1/6 see the
    # best precision 2/3, points up to 2/6 too, points up to 3/6 see 3/5, the rest nothing.
    tp = np.array([False, True, True, False, True, False])
    tp_c = np.cumsum(tp)
    rec, pre = tp_c / 6.0, tp_c / np.arange(1, 7)
    expected = (34 * (2 / 3) + 17 * 0.6) / 101
    assert bop24.interpolated_ap(rec, pre) == pytest.approx(expected, abs=1e-15)


@pytest.mark.parametrize("seed", range(20))
def test_ap_equals_the_references_formula(seed):
    rng = np.random.default_rng(seed)
    n_targets = int(rng.integers(1, 12))
    tp = rng.random(int(rng.integers(0, 30))) < 0.5
    tp[np.flatnonzero(tp)[n_targets:]] = False  # never more TP than targets
    tp_c = np.cumsum(tp)
    rec = tp_c / float(n_targets)
    pre = tp_c / np.arange(1, tp.size + 1)
    assert bop24.interpolated_ap(rec, pre) == _calc_ap_reference(rec, pre)


def _hand_dataset(root):
    """Image 0: needle instances g0 (90 % visible) and g1 (5 %); image 1: one needle g0 (all
    visible). Estimates: image 0 exact on g0 (0.9), exact on g1 (0.8), a duplicate of g0
    (0.7), an object absent from the image (0.95); image 1 nothing."""
    model = needle_mesh(NeedleSpec(rings=20, sides=6))
    save_ply(root / "models" / "obj_000001.ply", model)
    save_ply(root / "models" / "obj_000002.ply", model)
    info = compute_model_info(model.pts)
    save_models_info(root / "models" / "models_info.json", {1: info, 2: info})
    poses = [np.array([0.0, 0.0, 150.0]), np.array([40.0, 10.0, 160.0])]
    gts = {0: [GtPose(1, np.eye(3), poses[0]), GtPose(1, np.eye(3), poses[1])]}
    gts[1] = [GtPose(1, np.eye(3), poses[0])]

    def gi(vf):
        return GtInfo((1, 1, 5, 5), (1, 1, 5, 5), 100, 100, round(100 * vf), vf)

    infos = {0: [gi(0.9), gi(0.05)], 1: [gi(1.0)]}
    scene = root / "test" / "000001"
    save_scene_gt(scene / "scene_gt.json", gts)
    save_scene_gt_info(scene / "scene_gt_info.json", infos)
    save_scene_camera(scene / "scene_camera.json", {i: CameraInfo(K=DEFAULT_K.copy()) for i in gts})
    save_camera_json(root, DEFAULT_K, 640, 480)
    est = PoseEstimates.from_arrays(
        scene_id=np.ones(4, dtype=np.int64),
        im_id=np.zeros(4, dtype=np.int64),
        obj_id=np.array([1, 1, 1, 2]),
        score=np.array([0.9, 0.8, 0.7, 0.95]),
        R=np.tile(np.eye(3), (4, 1, 1)),
        t=np.stack([poses[0], poses[1], poses[0], poses[0]]),
        time=np.full(4, 0.25),
    )
    save_results(root / "r.csv", est)
    return BopDataset(root, "test"), est


def test_hand_worked_detection_ap(tmp_path):
    ds, est = _hand_dataset(tmp_path)
    res = bop24.evaluate_bop24(ds, est)
    # Targets: image 0 g0 and image 1 g0 (g1 is 5 % visible). The estimate on g1 is ignored,
    # the absent object is never evaluated, the duplicate is a FP: ranked TP, FP.
    # Precision 1 up to recall 0.5 (51 of the 101 points), then nothing.
    for key in ("bop24_mAP_mssd", "bop24_mAP_mssd_mm", "bop24_mAP_mspd", "bop24_mAP"):
        assert res.scores[key] == pytest.approx(51 / 101, abs=1e-15), key
    assert res.scores["bop25_mAP"] == res.scores["bop24_mAP_mssd"]
    assert res.scores["bop25_mAP_mm"] == res.scores["bop24_mAP_mssd_mm"]
    assert res.scores["bop24_average_time_per_image"] == 0.25
    assert res.curves["mssd"].obj_ids == [1]  # object 2 has no targets: not averaged
    assert res.curves["mssd"].targets_count == [2]


def test_only_target_images_are_evaluated(tmp_path):
    ds, est = _hand_dataset(tmp_path)
    res = bop24.evaluate_bop24(ds, est, [ImageTarget(1, 1)])
    # Image 1 alone: one target, no estimate -> AP 0.
    assert res.scores["bop24_mAP"] == 0.0
    res = bop24.evaluate_bop24(ds, est, [ImageTarget(1, 0)])
    assert res.scores["bop24_mAP_mssd"] == 1.0  # TP first, then the duplicate FP at recall 1


def test_per_image_cap_keeps_the_best_scores(tmp_path):
    ds, est = _hand_dataset(tmp_path)
    # With one estimate per image only the absent object (0.95) is kept: nothing evaluated.
    assert bop24.evaluate_bop24(ds, est, max_per_image=1).scores["bop24_mAP"] == 0.0
    # With two, the TP on g0 survives.
    assert bop24.evaluate_bop24(ds, est, max_per_image=2).scores["bop24_mAP"] == pytest.approx(
        51 / 101
    )


def test_target_image_not_in_split_is_an_error(tmp_path):
    ds, est = _hand_dataset(tmp_path)
    with pytest.raises(Exception, match="target image 7 of scene 1"):
        bop24.evaluate_bop24(ds, est, [ImageTarget(1, 7)])


def _fixture():
    return json.loads(bop24_oracle.FIXTURE.read_text())


@pytest.mark.parametrize("seed", bop24_oracle.SEEDS)
def test_scores_equal_the_reference_toolkit(tmp_path, seed):
    """Numbers of ``scripts/eval_bop24_pose.py`` (see bop24_oracle.py) to 1e-9."""
    ds, est, targets = bop24_oracle.build_case(tmp_path / "ds", seed)
    assert load_image_targets(tmp_path / "ds" / "test_targets_bop24.json") == targets
    ref = _fixture()["cases"][str(seed)]
    res = bop24.evaluate_bop24(ds, est)
    for key in KEYS:
        assert res.scores[key] == pytest.approx(ref["scores"][key], abs=1e-9), key
    # Per object and threshold too, so that a compensating error cannot hide.
    for name, curve in res.curves.items():
        prefix = "error=mssd" if name.startswith("mssd") else "error=mspd"
        for j, th in enumerate(curve.thresholds):
            key = f"{prefix}_ntop=0/scores_th={th:.3f}_min-visib=0.100"
            ref_obj = ref["per_object_ap"][key]
            for k, obj_id in enumerate(curve.obj_ids):
                assert curve.ap[k, j] == pytest.approx(ref_obj[str(obj_id)], abs=1e-9), (
                    key,
                    obj_id,
                )
    # The case must exercise what it claims to.
    assert 0.0 < res.scores["bop24_mAP_mssd"] < 1.0
    assert len(res.curves["mssd"].obj_ids) == 2
    assert np.bincount(est.im_id[est.scene_id == ds.scene_ids[0]]).max() > 100


def test_cli_task_bop24(tmp_path, capsys):
    _hand_dataset(tmp_path)
    out = tmp_path / "out"
    assert main(["eval", str(tmp_path), str(tmp_path / "r.csv"), "--out", str(out)]) == 0
    scores = json.loads((out / "scores.json").read_text())
    assert scores["bop24_mAP"] == pytest.approx(51 / 101)
    assert "bop19_average_recall_mssd" in scores
    out2 = tmp_path / "out2"
    args = ["eval", str(tmp_path), str(tmp_path / "r.csv"), "--out", str(out2), "--task", "bop19"]
    assert main(args) == 0
    scores = json.loads((out2 / "scores.json").read_text())
    assert "bop24_mAP" not in scores
    assert "bop19_average_recall_mssd" in scores
    capsys.readouterr()
    bad = tmp_path / "bad_targets.json"
    bad.write_text('[{"scene_id": 1}]')
    args = ["eval", str(tmp_path), str(tmp_path / "r.csv"), "--out", str(out2)]
    assert main([*args, "--targets-bop24", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "bad_targets.json" in err
    assert "0/im_id" in err
    assert len(err.splitlines()) == 1
