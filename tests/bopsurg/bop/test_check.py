"""check_dataset: a valid dataset has no problems; each corruption gives its own line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bopsurg.bop import (
    Problem,
    Target,
    check_dataset,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    save_mask,
    save_rgb,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
    save_targets,
)

SCENE = Path("test") / "000001"


def lines(problems: list[Problem]) -> list[str]:
    return [str(p) for p in problems]


def test_valid_dataset_has_no_problems(dataset: Path) -> None:
    assert check_dataset(dataset) == []
    assert check_dataset(dataset, check_images=False, progress=True) == []


def test_broken_json(dataset: Path) -> None:
    path = dataset / SCENE / "scene_gt.json"
    path.write_text(path.read_text()[:-3])
    problems = check_dataset(dataset)
    assert len(problems) == 1, lines(problems)
    assert problems[0].path.startswith(f"{path}:")
    assert "malformed JSON" in problems[0].message


def test_missing_rgb(dataset: Path) -> None:
    path = dataset / SCENE / "rgb" / "000001.png"
    path.unlink()
    assert lines(check_dataset(dataset)) == [f"{path}: image 1 not found"]


def test_wrong_image_size(dataset: Path) -> None:
    path = dataset / SCENE / "rgb" / "000001.png"
    save_rgb(path, np.zeros((10, 10, 3), dtype=np.uint8))
    assert lines(check_dataset(dataset)) == [f"{path}: size 10x10 != 64x48 of camera.json"]


def test_non_orthonormal_rotation(dataset: Path) -> None:
    path = dataset / SCENE / "scene_gt.json"
    gts = load_scene_gt(path)
    g = gts[0][1]
    gts[0][1] = type(g)(g.obj_id, g.R * 1.01, g.t)
    save_scene_gt(path, gts)
    problems = check_dataset(dataset)
    assert len(problems) == 1, lines(problems)
    assert problems[0].field == "0/1/cam_R_m2c"
    assert str(problems[0]).startswith(f"{path}: 0/1/cam_R_m2c: not a rotation matrix: max |R^T R")


def test_wrong_px_count_visib(dataset: Path) -> None:
    path = dataset / SCENE / "scene_gt_info.json"
    infos = load_scene_gt_info(path)
    i = infos[1][0]
    infos[1][0] = type(i)(
        i.bbox_obj, i.bbox_visib, i.px_count_all, i.px_count_valid, 390, 390 / 400
    )
    save_scene_gt_info(path, infos)
    mask = dataset / SCENE / "mask_visib" / "000001_000000.png"
    assert lines(check_dataset(dataset)) == [
        f"{mask}: 400 mask pixels != px_count_visib 390 of scene_gt_info.json 1/0"
    ]


def test_inconsistent_visib_fract_and_bbox(dataset: Path) -> None:
    path = dataset / SCENE / "scene_gt_info.json"
    infos = load_scene_gt_info(path)
    i = infos[0][0]
    infos[0][0] = type(i)(i.bbox_obj, (5, 5, 10, 10), 150, 150, 100, 0.5)
    save_scene_gt_info(path, infos)
    got = lines(check_dataset(dataset))
    assert got == [
        f"{path}: 0/0/visib_fract: 0.5 != px_count_visib / px_count_all = 100/150 = 0.666667",
        f"{dataset / SCENE / 'mask_visib' / '000000_000000.png'}: bounding box [5, 5, 9, 9] "
        "!= bbox_visib [5, 5, 10, 10] of scene_gt_info.json 0/0",
    ]


def test_mask_count_outside_valid_range(dataset: Path) -> None:
    path = dataset / SCENE / "mask" / "000001_000000.png"
    save_mask(path, np.zeros((48, 64), dtype=bool))
    got = lines(check_dataset(dataset))
    assert got[0] == (
        f"{path}: 0 mask pixels outside [px_count_valid, px_count_all] = [400, 400] "
        "of scene_gt_info.json 1/0"
    )
    assert "outside the object's mask/" in got[1]
    assert len(got) == 2


def test_unknown_obj_id(dataset: Path) -> None:
    path = dataset / SCENE / "scene_gt.json"
    gts = load_scene_gt(path)
    g = gts[0][0]
    gts[0][0] = type(g)(99, g.R, g.t)
    save_scene_gt(path, gts)
    assert lines(check_dataset(dataset)) == [
        f"{path}: 0/0/obj_id: unknown obj_id 99: not in models_info.json"
    ]


def test_mismatched_image_ids(dataset: Path) -> None:
    path = dataset / SCENE / "scene_camera.json"
    cams = load_scene_camera(path)
    del cams[1]
    save_scene_camera(path, cams)
    assert lines(check_dataset(dataset)) == [
        f"{dataset / SCENE / 'scene_gt.json'}: images not in scene_camera.json: 1"
    ]


def test_bad_camera(dataset: Path) -> None:
    path = dataset / SCENE / "scene_camera.json"
    text = json.loads(path.read_text())
    text["0"]["cam_K"][0] = -50.0
    text["1"]["depth_scale"] = 0
    text["1"]["cam_K"][8] = 2.0
    path.write_text(json.dumps(text))
    assert sorted(lines(check_dataset(dataset))) == [
        f"{path}: 0/cam_K: fx and fy must be > 0, got -50.0, 50.0",
        f"{path}: 1/cam_K: last row must be 0 0 1, got [0.0, 0.0, 2.0]",
        f"{path}: 1/depth_scale: must be > 0, got 0.0",
    ]


def test_all_problems_are_collected(dataset: Path) -> None:
    (dataset / SCENE / "rgb" / "000000.png").unlink()
    (dataset / SCENE / "depth" / "000001.png").unlink()
    (dataset / SCENE / "mask_visib" / "000000_000001.png").unlink()
    info = dataset / SCENE / "scene_gt_info.json"
    info.write_text(info.read_text().replace('"px_count_all": 400', '"px_count_all": "400"'))
    (dataset / "models" / "models_info.json").write_text('{"1": {"diameter": -1}}')
    got = lines(check_dataset(dataset))
    assert len(got) == 5, got
    assert any("1/diameter: must be > 0" in x for x in got)
    assert any("1/0/px_count_all: expected an integer" in x for x in got)
    assert any("image 0 not found" in x for x in got)
    assert any("depth image 1 not found" in x for x in got)
    assert any("mask_visib of image 0, gt_id 1 not found" in x for x in got)
    assert len(check_dataset(dataset, max_problems=2)) == 2


def test_missing_model_and_folders(dataset: Path, tmp_path: Path) -> None:
    (dataset / "models" / "obj_000001.ply").unlink()
    assert lines(check_dataset(dataset)) == [
        f"{dataset / 'models' / 'obj_000001.ply'}: model of obj_id 1 (listed in "
        "models_info.json) not found"
    ]
    assert lines(check_dataset(dataset, "val")) == [
        f"{dataset / 'models' / 'obj_000001.ply'}: model of obj_id 1 (listed in "
        "models_info.json) not found",
        f"{dataset / 'val'}: split folder not found",
    ]
    assert lines(check_dataset(tmp_path / "none")) == [
        f"{tmp_path / 'none'}: dataset folder not found"
    ]


def test_targets_file(dataset: Path) -> None:
    path = dataset / "test_targets_bop19.json"
    save_targets(path, [Target(1, 0, 1, 2), Target(1, 1, 1, 1)])
    assert check_dataset(dataset) == []
    save_targets(
        path, [Target(1, 0, 1, 3), Target(1, 5, 1, 1), Target(2, 0, 1, 1), Target(1, 1, 7, 1)]
    )
    assert lines(check_dataset(dataset)) == [
        f"{path}: 0/inst_count: 3 > 2 GT instances of obj_id 1 in scene 1 image 0",
        f"{path}: 1/im_id: scene 1 has no image 5",
        f"{path}: 3/obj_id: unknown obj_id 7: not in models_info.json",
        f"{path}: 3/inst_count: 1 > 0 GT instances of obj_id 7 in scene 1 image 1",
        f"{path}: 2/scene_id: scene 2 is not in the split",
    ]


@pytest.mark.parametrize("check_images", [True, False])
def test_problem_str_is_one_line(dataset: Path, check_images: bool) -> None:
    (dataset / SCENE / "scene_camera.json").write_text("{\n\n")
    for p in check_dataset(dataset, check_images=check_images):
        assert "\n" not in str(p)
        assert str(p).count(": ") >= 1


def test_bop24_targets_file(dataset: Path) -> None:
    from bopsurg.bop.targets import ImageTarget, save_image_targets

    path = dataset / "test_targets_bop24.json"
    save_image_targets(path, [ImageTarget(1, 0), ImageTarget(1, 1)])
    assert check_dataset(dataset) == []
    save_image_targets(path, [ImageTarget(1, 5), ImageTarget(2, 0)])
    path.write_text(path.read_text().replace("]", ', {"scene_id": 1}]'))
    assert lines(check_dataset(dataset)) == [
        f"{path}: 2/im_id: missing",
        f"{path}: 0/im_id: scene 1 has no image 5",
        f"{path}: 1/scene_id: scene 2 is not in the split",
    ]
