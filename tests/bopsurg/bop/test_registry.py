"""The BOP dataset registry: per-dataset defaults, and `bopsurg check` / `bopsurg eval` on tiny
datasets in each standard dataset's layout (made here: one scene, two images, a cube), run
without flags."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from bopsurg.bop import (
    CameraInfo,
    GtInfo,
    GtPose,
    ObjectModel,
    compute_model_info,
    save_json,
    save_models_info,
    save_ply,
    save_rgb,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from bopsurg.bop.check import check_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.registry import (
    DATASETS,
    TARGETS_BOP19,
    TARGETS_BOP24,
    VSD_TAUS,
    dataset_spec,
    recognise,
)
from bopsurg.bop.results import PoseEstimates, save_results
from bopsurg.cli.main import main
from bopsurg.errors import DatasetError
from bopsurg.evaluation import bop19
from tests.bopsurg.bop.conftest import CUBE_FACES, CUBE_PTS
from tests.helpers import estimates_from_gt

STANDARD = ["lmo", "tless", "ycbv", "itodd", "hb", "icbin", "tudl", "hope", "hot3d", "handal"]
STANDARD += ["ipd", "xyzibd"]
#: Scenes of each fixture: (scene_id, stream); HOT3D has a Quest 3 and an Aria scene.
HOT3D_SCENES = ((1288, "gray1"), (3365, "rgb"))


def build(root: Path, name: str) -> Path:
    """A tiny dataset in ``name``'s layout under ``root/name``: the registry's split folder,
    camera file, image size and folders, streams and targets files."""
    spec = dataset_spec(name)
    root = root / name
    cube = ObjectModel(pts=CUBE_PTS * 40, faces=CUBE_FACES)
    save_ply(root / "models_eval" / "obj_000001.ply", cube)
    save_models_info(root / "models_eval" / "models_info.json", {1: compute_model_info(cube.pts)})
    split_type = spec.split_types.get("test")
    split = "test" if split_type is None else f"test_{split_type}"
    scenes = (
        HOT3D_SCENES if name == "hot3d" else ((1, spec.streams[0].name if spec.streams else None),)
    )
    for scene_id, stream in scenes:
        _scene(root / split / f"{scene_id:06d}", spec.image_size(split_type, stream), name, stream)
    if name != "hot3d":  # HOT3D has no dataset-level camera
        w, h = spec.image_size(split_type)
        cam = {"cx": w / 2, "cy": h / 2, "depth_scale": 0.1, "fx": w, "fy": w, "height": h}
        save_json(root / spec.camera_file(split_type), cam | {"width": w})
    ims = [(s, i) for s, _ in scenes for i in (0, 1)]
    if TARGETS_BOP19 in spec.targets:
        save_json(root / TARGETS_BOP19, [
            {"im_id": i, "inst_count": 1, "obj_id": 1, "scene_id": s} for s, i in ims])  # fmt: skip
    save_json(root / TARGETS_BOP24, [{"im_id": i, "scene_id": s} for s, i in ims])
    return root


def _scene(d: Path, size: tuple[int, int], name: str, stream: str | None) -> None:
    w, h = size
    K = np.array([[w, 0, w / 2], [0, w, h / 2], [0, 0, 1.0]])
    spec = dataset_spec(name)
    sfx = "" if stream is None else f"_{stream}"
    folder = spec.stream(stream).images[0] if stream else ("gray" if spec.gray else "rgb")
    ext = ".jpg" if name == "handal" else ".tif" if name == "itodd" else ".png"
    cams, gts, infos = {}, {}, {}
    for im_id in (0, 1):
        if name == "hot3d":  # the BOP24 H3 camera: a model instead of cam_K
            params = [w, w, w / 2, h / 2] + [0.0] * 12
            model = {"projection_model_type": "CameraModelType.FISHEYE624",
                     "projection_params": params, "image_width": w, "image_height": h}  # fmt: skip
            cams[im_id] = CameraInfo(K=K, extra={"cam_model": model})
        else:
            cams[im_id] = CameraInfo(K=K, depth_scale=0.1)
        R = np.eye(3) if im_id == 0 else np.diag([1.0, -1.0, -1.0])
        gts[im_id] = [GtPose(obj_id=1, R=R, t=np.array([10.0, -5.0, 600.0]))]
        infos[im_id] = [GtInfo((10, 10, 9, 9), (10, 10, 9, 7), 100, 100, 80, 0.8)]
        image = d / folder / f"{im_id:06d}{ext}"
        if ext == ".tif":  # ITODD's grey images (bopsurg writes no TIFF)
            image.parent.mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(image), np.zeros((h, w), np.uint8))
        else:
            save_rgb(image, np.zeros((h, w, 3), np.uint8))
    save_scene_camera(d / f"scene_camera{sfx}.json", cams)
    save_scene_gt(d / f"scene_gt{sfx}.json", gts)
    save_scene_gt_info(d / f"scene_gt_info{sfx}.json", infos)


def test_the_reference_parameters():
    assert dataset_spec("itodd").vsd_delta_mm == 5.0
    assert {d.vsd_delta_mm for n, d in DATASETS.items() if n != "itodd"} == {15.0}
    # np.arange(0.05, 0.51, 0.05), the reference's τ and thresholds, float for float
    assert list(VSD_TAUS) == np.arange(0.05, 0.51, 0.05).tolist() == list(bop19.VSD_TAUS)
    assert dataset_spec("tless").image_size() == (720, 540)
    assert dataset_spec("tless").image_size("canon") == (2560, 1920)
    assert dataset_spec("tless").image_size("primesense", split="train") == (400, 400)
    assert dataset_spec("tless").image_size("pbr", split="train") == (720, 540)
    assert dataset_spec("hb").image_size("kinect") == (1920, 1080)
    assert dataset_spec("itodd").image_size() == (1280, 960)
    assert dataset_spec("hot3d").image_size(None, "rgb") == (1408, 1408)
    assert dataset_spec("xyzibd").max_estimates_per_image == 200
    assert dataset_spec("lmo").max_estimates_per_image == 100
    assert not dataset_spec("hot3d").vsd
    assert not dataset_spec("ipd").vsd
    assert dataset_spec("ycbv").camera_file() == "camera_uw.json"
    assert dataset_spec("tless").camera_file("kinect") == "camera_kinect.json"
    assert dataset_spec("lmo").camera_file() == "camera.json"
    assert dataset_spec("hot3d").targets == (TARGETS_BOP24,)
    assert set(STANDARD) <= set(DATASETS)


def test_a_dataset_is_recognised_by_folder_name_or_by_name(tmp_path):
    assert recognise(tmp_path / "TLESS").name == "tless"
    assert recognise(tmp_path / "mydata") is None
    assert recognise(tmp_path / "mydata", "YCBV").name == "ycbv"
    assert recognise(tmp_path / "lmo", "none") is None
    with pytest.raises(KeyError, match="unknown BOP dataset 'lm0'; known: lm, lmo"):
        recognise(tmp_path, "lm0")
    (tmp_path / "test").mkdir()
    with pytest.raises(DatasetError, match="unknown BOP dataset 'nope'"):
        BopDataset(tmp_path, name="nope")


@pytest.mark.parametrize("name", STANDARD)
def test_check_and_eval_run_without_flags(tmp_path, name, capsys):
    root = build(tmp_path, name)
    assert check_dataset(root) == []
    assert main(["check", str(root)]) == 0
    ds = BopDataset(root)  # split type, streams, size from the registry
    assert ds.spec is dataset_spec(name)
    first = ds.scene(ds.scene_ids[0]).stream
    assert ds.image_size() == ds.spec.image_size(ds.split_type, first and first.name)
    csv = tmp_path / "res.csv"
    save_results(csv, estimates_from_gt(ds))
    out = tmp_path / "eval"
    assert main(["eval", str(root), str(csv), "--out", str(out), "--bootstrap", "0"]) == 0
    scores = json.loads((out / "scores.json").read_text())
    assert scores["bop19_average_recall_mssd"] == 1.0
    assert scores["bop19_average_recall_mspd"] == 1.0
    assert scores["bop24_mAP_mssd"] == 1.0
    capsys.readouterr()


def test_the_split_type_and_camera_file_come_from_the_registry(tmp_path):
    root = build(tmp_path, "tless")
    ds = BopDataset(root)
    assert ds.split_dir == root / "test_primesense"
    assert ds.camera_file == root / "camera_primesense.json"
    assert ds.camera_json["width"] == 720
    assert ds.vsd_delta_mm == 15.0
    with pytest.raises(DatasetError, match="split folder not found"):
        BopDataset(root, split_type="kinect")  # an explicit type wins


def test_hot3d_reads_each_scene_through_its_stream(tmp_path):
    ds = BopDataset(build(tmp_path, "hot3d"))
    quest, aria = (ds.scene(s) for s, _ in HOT3D_SCENES)
    assert (quest.stream.name, aria.stream.name) == ("gray1", "rgb")
    assert quest.gt_path.name == "scene_gt_gray1.json"
    assert aria.rgb_path(1) == aria.scene_dir / "rgb" / "000001.png"
    assert quest.mask_visib_path(0, 0).parent.name == "mask_visib_gray1"
    assert quest.depth_dir is None
    assert ds.image_size(1288) == (1280, 1024)
    assert ds.image_size(3365) == (1408, 1408)
    assert quest.camera[0].K[0, 0] == 1280.0  # from the H3 cam_model
    assert not ds.evaluates_vsd
    assert BopDataset(ds.root, stream="rgb").scene(1288).gt_path.name == "scene_gt_rgb.json"
    with pytest.raises(DatasetError, match="hot3d has no stream 'depth'"):
        BopDataset(ds.root, stream="depth").scene(1288)


def test_the_dataset_flag_names_a_dataset_in_any_folder(tmp_path, capsys):
    root = build(tmp_path, "itodd").rename(tmp_path / "scan_2024")
    assert BopDataset(root).spec is None  # not recognised: the generic reading
    ds = BopDataset(root, name="itodd")
    assert ds.vsd_delta_mm == 5.0
    assert main(["check", str(root), "--dataset", "itodd"]) == 0
    # a folder named like a standard dataset whose images are not that dataset's size
    lmo = build(tmp_path, "hope").rename(tmp_path / "lmo")
    problems = [str(p) for p in check_dataset(lmo)]
    assert problems
    assert all("size 1920x1080 != 640x480 of the lmo dataset" in p for p in problems)
    assert check_dataset(lmo, dataset="none") == []
    assert main(["check", str(lmo), "--dataset", "nope"]) == 1
    assert "unknown BOP dataset 'nope'" in capsys.readouterr().out


def test_eval_takes_vsd_delta_and_the_dataset_flag_from_the_registry(tmp_path, monkeypatch):
    import bopsurg.evaluation.runner as runner

    seen = {}

    class Stop(Exception):
        pass

    def begin_evaluation(dataset, est, **options):
        seen.update(options, spec=dataset.spec.name)
        raise Stop

    monkeypatch.setattr(runner, "begin_evaluation", begin_evaluation)
    root = build(tmp_path, "itodd").rename(tmp_path / "scan")
    csv = tmp_path / "res.csv"
    save_results(csv, estimates_from_gt(BopDataset(root, name="itodd")))
    args = ["eval", str(root), str(csv), "--out", str(tmp_path / "ev"), "--dataset", "itodd"]
    with pytest.raises(Stop):
        main(args)
    assert (seen["spec"], seen["vsd_delta"]) == ("itodd", 5.0)
    with pytest.raises(Stop):
        main([*args, "--vsd-delta", "7.5"])
    assert seen["vsd_delta"] == 7.5


def test_no_vsd_where_the_reference_has_none(tmp_path, caplog):
    from bopsurg.cli.eval_cmd import _renderer

    root = build(tmp_path, "ipd")
    (root / "test" / "000001" / "depth").mkdir()
    with caplog.at_level("INFO"):
        assert _renderer("auto", BopDataset(root)) is None
    assert "AR_VSD skipped: not evaluated on ipd" in caplog.text


@pytest.mark.parametrize(("name", "kept"), [("xyzibd", True), ("lmo", False)])
def test_bop24_keeps_200_estimates_per_image_on_xyzibd(tmp_path, name, kept):
    """149 far-off estimates outscore the GT pose in each image: XYZ-IBD's cap of 200 keeps
    it (AP 1/150 > 0), the usual 100 drops it (AP 0)."""
    root = build(tmp_path, name)
    gt = estimates_from_gt(BopDataset(root))
    n, wrong = len(gt), 149
    est = PoseEstimates.from_arrays(
        scene_id=np.repeat(gt.scene_id, wrong + 1),
        im_id=np.repeat(gt.im_id, wrong + 1),
        obj_id=np.repeat(gt.obj_id, wrong + 1),
        score=np.tile(np.r_[np.full(wrong, 0.9), 0.1], n),
        R=np.repeat(gt.R, wrong + 1, axis=0),
        t=np.repeat(gt.t, wrong + 1, axis=0)
        + np.tile(np.r_[np.full(wrong, 500.0), 0.0], n)[:, None],
        time=np.full(n * (wrong + 1), 0.1),
    )
    csv = tmp_path / "res.csv"
    save_results(csv, est)
    out = tmp_path / "ev"
    assert main(["eval", str(root), str(csv), "--out", str(out), "--bootstrap", "0"]) == 0
    mAP = json.loads((out / "scores.json").read_text())["bop24_mAP_mssd"]
    assert (mAP > 0) is kept
    assert mAP < 0.05


@pytest.mark.slow  # worker processes
def test_eval_workers_read_the_dataset_as_the_caller_does(tmp_path):
    """Worker processes open the dataset again: a renamed HOT3D folder needs the name."""
    root = build(tmp_path, "hot3d").rename(tmp_path / "scan")
    csv = tmp_path / "res.csv"
    save_results(csv, estimates_from_gt(BopDataset(root, name="hot3d")))
    out = tmp_path / "ev"
    args = ["eval", str(root), str(csv), "--out", str(out), "--dataset", "hot3d"]
    assert main([*args, "--workers", "2", "--bootstrap", "0", "--no-progress"]) == 0
    assert json.loads((out / "scores.json").read_text())["bop19_average_recall_mssd"] == 1.0
