"""BopDataset: lazy access to scenes, images, models and targets."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from bopsurg.bop import (
    BopDataset,
    ObjectModel,
    Target,
    load_ply,
    save_json,
    save_ply,
    save_targets,
)
from bopsurg.errors import DatasetError

from .conftest import CUBE_PTS, H, K, W


def test_scenes_and_annotations(dataset: Path) -> None:
    ds = BopDataset(dataset)
    assert ds.split_dir == dataset / "test"
    assert ds.scene_ids == [1]
    scene = ds.scene(1)
    assert ds.scene(1) is scene  # cached
    assert "camera" not in scene.__dict__  # nothing read yet
    assert scene.im_ids == [0, 1]
    np.testing.assert_array_equal(scene.camera[0].K, K)
    assert scene.camera[0].depth_scale == 0.1
    assert scene.camera[0].extra == {"view_level": 0}
    assert [g.obj_id for g in scene.gt[0]] == [1, 1]
    assert scene.gt_info is not None
    assert scene.gt_info[1][0].visib_fract == 1.0
    assert scene.rgb_path(0) == scene.scene_dir / "rgb" / "000000.png"
    assert scene.depth_path(1) == scene.scene_dir / "depth" / "000001.png"
    assert scene.mask_path(0, 1).name == "000000_000001.png"
    assert scene.mask_visib_path(0, 1).parent.name == "mask_visib"
    assert [s.scene_id for s in ds.iter_scenes()] == [1]


def test_models(dataset: Path) -> None:
    ds = BopDataset(dataset)
    assert ds.models_dir == dataset / "models"
    assert ds.obj_ids == [1]
    assert ds.models_info[1]["diameter"] == pytest.approx(np.sqrt(3))
    assert ds.model_path(1).name == "obj_000001.ply"
    np.testing.assert_array_equal(ds.model(1).pts, CUBE_PTS)
    assert ds.model(1) is ds.model(1)
    with pytest.raises(DatasetError, match="unknown obj_id 9") as e:
        ds.model(9)
    assert str(dataset / "models") in str(e.value)


def test_models_eval_is_preferred_and_model_type(dataset: Path) -> None:
    shutil.copytree(dataset / "models", dataset / "models_eval")
    save_ply(dataset / "models_eval" / "obj_000001.ply", ObjectModel(CUBE_PTS * 2, []))
    assert BopDataset(dataset).models_dir == dataset / "models_eval"
    assert BopDataset(dataset).model(1).pts.max() == 1.0
    assert BopDataset(dataset, model_type="cad").split == "test"
    with pytest.raises(DatasetError, match="models folder not found"):
        _ = BopDataset(dataset, model_type="cad").models_dir
    assert len(load_ply(dataset / "models" / "obj_000001.ply").faces) == 12


def test_split_type_and_missing_folders(dataset: Path, tmp_path: Path) -> None:
    shutil.copytree(dataset / "test", dataset / "train_pbr")
    assert BopDataset(dataset, "train", split_type="pbr").split_dir == dataset / "train_pbr"
    with pytest.raises(DatasetError, match="split folder not found") as e:
        BopDataset(dataset, "val")
    assert e.value.path == str(dataset / "val")
    with pytest.raises(DatasetError, match="dataset folder not found"):
        BopDataset(tmp_path / "nowhere")
    with pytest.raises(DatasetError, match="no scene 5"):
        BopDataset(dataset).scene(5)


def test_rgb_path_prefers_existing_suffix_and_gray(dataset: Path) -> None:
    scene = BopDataset(dataset).scene(1)
    rgb = scene.scene_dir / "rgb"
    (rgb / "000000.png").rename(rgb / "000000.jpg")
    assert scene.rgb_path(0).suffix == ".jpg"
    rgb.rename(scene.scene_dir / "gray")
    assert scene.rgb_path(1) == scene.scene_dir / "gray" / "000001.png"
    assert scene.rgb_path(7) == scene.scene_dir / "rgb" / "000007.png"  # expected path


def test_gt_info_absent_is_none(dataset: Path) -> None:
    (dataset / "test" / "000001" / "scene_gt_info.json").unlink()
    assert BopDataset(dataset).scene(1).gt_info is None


def test_image_size(dataset: Path) -> None:
    ds = BopDataset(dataset)
    assert ds.camera_json is not None
    assert ds.image_size() == (W, H)
    (dataset / "camera.json").unlink()
    ds = BopDataset(dataset)
    assert ds.camera_json is None
    assert ds.image_size(1) == (W, H)  # from the first rgb image


def test_targets_from_file_or_enumerated(dataset: Path, caplog: pytest.LogCaptureFixture) -> None:
    ds = BopDataset(dataset)
    with caplog.at_level(logging.WARNING):
        targets = ds.targets()
    assert "enumerating targets" in caplog.text
    assert targets == [Target(1, 0, 1, 2), Target(1, 1, 1, 1)]
    save_targets(dataset / "test_targets_bop19.json", [Target(1, 1, 1, 1)])
    assert ds.targets() == [Target(1, 1, 1, 1)]


def test_malformed_camera_json(dataset: Path) -> None:
    save_json(dataset / "camera.json", [1, 2])
    with pytest.raises(DatasetError, match="JSON object"):
        _ = BopDataset(dataset).camera_json
