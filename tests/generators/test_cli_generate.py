"""`bopsurg generate` options: intrinsics, resolution, needle geometry, bad values."""

from __future__ import annotations

import json

import pytest

from bopsurg.bop.check import check_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import image_size
from bopsurg.bop.targets import load_image_targets
from bopsurg.cli.main import main

pytest.importorskip("pybullet")
pytest.importorskip("rosbags")  # the bags it generates from are recorded first


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bag") / "a.bag"
    assert main(["record", "--out", str(path), "--seed", "2", "--duration", "2"]) == 0
    return path


def test_half_circle_needle_at_320x240_with_explicit_K(bag, tmp_path):
    out = tmp_path / "ds"
    args = ["generate", str(bag), "--out", str(out), "--replays", "1", "--period", "1"]
    opts = ["--width", "320", "--height", "240", "--K", "180,180,160,120", "--needle-arc", "180"]
    assert main([*args, *opts, "--min-visib", "0", "--no-progress"]) == 0
    ds = BopDataset(out, "test")
    diameter = ds.models_info[1]["diameter"]
    assert 20.36 < diameter < 21.2  # half circle of radius 10.18 mm plus the wire
    scene = ds.scene(1)
    im_id = scene.im_ids[0]
    assert image_size(scene.rgb_path(im_id)) == (320, 240)
    assert scene.camera[im_id].K[0, 0] == 180.0
    camera = json.loads((out / "camera.json").read_text())
    assert (camera["width"], camera["height"], camera["cx"]) == (320, 240, 160.0)
    # The detection tasks' files: BOP24 targets and 2D annotations, valid for the checker.
    coco = json.loads((scene.scene_dir / "scene_gt_coco.json").read_text())
    assert len(coco["images"]) == len(scene.im_ids)
    assert len(load_image_targets(out / "test_targets_bop24.json")) == len(scene.im_ids)
    assert check_dataset(out) == []


@pytest.mark.parametrize(
    ("opts", "field"),
    [
        (["--K", "1,2,3"], "--K"),
        (["--fov", "4"], "--fov"),
        (["--needle-arc", "5"], "--needle-arc"),
        (["--needle-wire", "-1"], "--needle-wire"),
        (["--period", "0"], "--period"),
    ],
)
def test_bad_options_are_one_line_errors(bag, tmp_path, capsys, opts, field):
    code = main(["generate", str(bag), "--out", str(tmp_path / "ds"), *opts, "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bopsurg: error:")
    assert field in err
    assert "\n" not in err
    assert not (tmp_path / "ds").exists()
