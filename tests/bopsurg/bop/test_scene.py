"""scene_camera.json, scene_gt.json and scene_gt_info.json: layout, round trips, errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bopsurg.bop import (
    CameraInfo,
    GtInfo,
    GtPose,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from bopsurg.errors import DatasetError, ShapeError

EYE = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]


def test_scene_gt_layout_is_reference(tmp_path: Path) -> None:
    path = tmp_path / "scene_gt.json"
    gts = {
        10: [GtPose(obj_id=3, R=np.eye(3), t=[0.0, 0.0, 500.0])],
        2: [GtPose(obj_id=1, R=np.eye(3), t=[1.5, -2.0, 3.0]), GtPose(2, np.eye(3), [0, 0, 1])],
    }
    save_scene_gt(path, gts)
    r = "[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]"
    expected = (
        "{\n"
        f'  "2": [{{"cam_R_m2c": {r}, "cam_t_m2c": [1.5, -2.0, 3.0], "obj_id": 1}}, '
        f'{{"cam_R_m2c": {r}, "cam_t_m2c": [0.0, 0.0, 1.0], "obj_id": 2}}],\n'
        f'  "10": [{{"cam_R_m2c": {r}, "cam_t_m2c": [0.0, 0.0, 500.0], "obj_id": 3}}]\n'
        "}"
    )
    assert path.read_text() == expected
    loaded = load_scene_gt(path)
    assert list(loaded) == [2, 10]
    assert loaded[2][0] == gts[2][0]
    assert loaded[2][0].t.shape == (3,)
    assert loaded[10][0].R.dtype == np.float64


def test_scene_camera_round_trip_keeps_extra(tmp_path: Path) -> None:
    path = tmp_path / "scene_camera.json"
    K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])
    cams = {
        0: CameraInfo(K=K, depth_scale=0.1, extra={"view_level": 2, "elev": 30, "mode": 1}),
        1: CameraInfo(K=K, depth_scale=1.0, R_w2c=np.eye(3), t_w2c=[1.0, 2.0, 3.0]),
    }
    save_scene_camera(path, cams)
    text = path.read_text()
    assert text.splitlines()[1] == (
        '  "0": {"cam_K": [572.4114, 0.0, 325.2611, 0.0, 573.57043, 242.04899, 0.0, 0.0, 1.0], '
        '"depth_scale": 0.1, "elev": 30, "mode": 1, "view_level": 2},'
    )
    loaded = load_scene_camera(path)
    assert loaded == cams
    assert loaded[1].t_w2c.shape == (3,)
    save_scene_camera(tmp_path / "again.json", loaded)
    assert (tmp_path / "again.json").read_text() == text


def test_scene_camera_bop24_cam_model(tmp_path: Path) -> None:
    path = tmp_path / "scene_camera.json"
    model = {
        "projection_model_type": "fisheye",
        "projection_params": [600.0, 601.0, 320.0, 240.0, 0.1, 0.2],
        "image_width": 640,
        "image_height": 480,
    }
    path.write_text(json.dumps({"3": {"cam_model": model, "depth_scale": 1}}))
    cam = load_scene_camera(path)[3]
    assert np.array_equal(cam.K, [[600, 0, 320], [0, 601, 240], [0, 0, 1]])
    assert cam.extra["cam_model"] == model
    save_scene_camera(tmp_path / "out.json", {3: cam})
    assert "cam_K" not in (tmp_path / "out.json").read_text()  # the reference rejects both


def test_scene_gt_info_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "scene_gt_info.json"
    infos = {
        0: [GtInfo((-3, 5, 40, 30), (0, 5, 37, 30), 1200, 1000, 900, 0.75)],
        1: [GtInfo([-1, -1, -1, -1], [-1, -1, -1, -1], 0, 0, 0, 0.0)],
    }
    save_scene_gt_info(path, infos)
    assert path.read_text().splitlines()[1] == (
        '  "0": [{"bbox_obj": [-3, 5, 40, 30], "bbox_visib": [0, 5, 37, 30], '
        '"px_count_all": 1200, "px_count_valid": 1000, "px_count_visib": 900, '
        '"visib_fract": 0.75}],'
    )
    assert load_scene_gt_info(path) == infos


def test_gt_accepts_slightly_non_orthonormal_rotation(tmp_path: Path) -> None:
    path = tmp_path / "scene_gt.json"
    path.write_text(
        '{"0": [{"obj_id": 1, "cam_R_m2c": [1.01, 0, 0, 0, 1, 0, 0, 0, 1], '
        '"cam_t_m2c": [0, 0, 1]}]}'
    )
    assert load_scene_gt(path)[0][0].R[0, 0] == 1.01


@pytest.mark.parametrize(
    ("text", "field", "reason"),
    [
        ('{"12": {"cam_K": [1, 2, 3]}}', "12/cam_K", "expected a list of 9 numbers"),
        ('{"12": {"cam_K": [1, 0, 0, 0, 1, 0, 0, 0, "x"]}}', "12/cam_K", "expected numbers"),
        ('{"12": {"depth_scale": 1}}', "12/cam_K", "missing"),
        (
            '{"12": {"cam_K": [1, 0, 0, 0, 1, 0, 0, 0, 1], "depth_scale": "a"}}',
            "12/depth_scale",
            "expected a number",
        ),
        (
            '{"x": {"cam_K": [1, 0, 0, 0, 1, 0, 0, 0, 1]}}',
            "x",
            "image id must be a non-negative integer",
        ),
        ("[1, 2]", None, "expected a mapping"),
    ],
)
def test_scene_camera_errors(tmp_path: Path, text: str, field: str | None, reason: str) -> None:
    path = tmp_path / "scene_camera.json"
    path.write_text(text)
    with pytest.raises(DatasetError, match=reason) as e:
        load_scene_camera(path)
    assert e.value.field == field
    assert e.value.path == str(path)


@pytest.mark.parametrize(
    ("entry", "field", "reason"),
    [
        (
            '{"obj_id": 1, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0], "cam_t_m2c": [0, 0, 1]}',
            "12/1/cam_R_m2c",
            "list of 9 numbers",
        ),
        (
            '{"obj_id": 1, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, NaN], "cam_t_m2c": [0, 0, 1]}',
            "12/1/cam_R_m2c",
            "NaN or inf",
        ),
        (
            '{"obj_id": 1, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 1]}',
            "12/1/cam_t_m2c",
            "list of 3 numbers",
        ),
        (
            '{"obj_id": 1.5, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 1]}',
            "12/1/obj_id",
            "expected an integer",
        ),
        (
            '{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 1]}',
            "12/1/obj_id",
            "missing",
        ),
    ],
)
def test_scene_gt_errors(tmp_path: Path, entry: str, field: str, reason: str) -> None:
    good = '{"obj_id": 1, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 1]}'
    path = tmp_path / "scene_gt.json"
    path.write_text(f'{{"12": [{good}, {entry}]}}')
    with pytest.raises(DatasetError, match=reason) as e:
        load_scene_gt(path)
    assert e.value.field == field
    assert str(e.value).startswith(f"{path}: {field}: ")


def test_scene_gt_info_errors(tmp_path: Path) -> None:
    path = tmp_path / "scene_gt_info.json"
    path.write_text(
        '{"3": [{"bbox_obj": [1, 2, 3], "bbox_visib": [1, 2, 3, 4], "px_count_all": 1, '
        '"px_count_valid": 1, "px_count_visib": 1, "visib_fract": 1.0}]}'
    )
    with pytest.raises(DatasetError, match="4 integers") as e:
        load_scene_gt_info(path)
    assert e.value.field == "3/0/bbox_obj"
    path.write_text('{"3": [{"bbox_obj": [1, 2, 3, 4]}]}')
    with pytest.raises(DatasetError, match="missing") as e:
        load_scene_gt_info(path)
    assert e.value.field == "3/0/bbox_visib"


def test_missing_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="file not found"):
        load_scene_gt(tmp_path / "scene_gt.json")
    bad = tmp_path / "scene_camera.json"
    bad.write_text('{"0": {"cam_K": [1, 2,]}}')
    with pytest.raises(DatasetError, match="malformed JSON") as e:
        load_scene_camera(bad)
    assert e.value.line == 1


def test_dataclass_validation() -> None:
    with pytest.raises(ShapeError):
        GtPose(obj_id=1, R=np.eye(2), t=[0, 0, 0])
    with pytest.raises(ShapeError):
        CameraInfo(K=np.full((3, 3), np.nan))
    assert GtPose(1, np.eye(3).ravel(), np.zeros((3, 1))).t.shape == (3,)
