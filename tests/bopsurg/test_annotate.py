"""`bopsurg annotate` with a stand-in depth renderer: hand-built truncation, occlusion,
depth-less and bad-input cases (the PyBullet renderer is tested against the generator in
tests/generators)."""

from __future__ import annotations

import numpy as np
import pytest

from bopsurg.annotate import annotate_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_mask, save_depth, save_rgb
from bopsurg.bop.meshes import ObjectModel, compute_model_info, save_models_info, save_ply
from bopsurg.bop.scene import CameraInfo, GtPose, save_scene_camera, save_scene_gt
from bopsurg.errors import DatasetError

W, H = 64, 48
K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
HALF = 5  # the stand-in object is an 10x10 px square at the projection of t


class SquareRenderer:
    """Renders every model as a (2*HALF)^2 px square at constant depth t_z."""

    def render_depth(self, model, R, t, K, width, height):
        u = K[0, 0] * t[0] / t[2] + K[0, 2]
        v = K[1, 1] * t[1] / t[2] + K[1, 2]
        d = np.zeros((height, width))
        r0, c0 = int(np.rint(v)) - HALF, int(np.rint(u)) - HALF
        d[max(r0, 0) : max(r0 + 2 * HALF, 0), max(c0, 0) : max(c0 + 2 * HALF, 0)] = t[2]
        return d


def _px(u: float, v: float, z: float) -> np.ndarray:
    """Translation (mm) whose projection is pixel (u, v) at depth z."""
    return np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])


def _dataset(root, gts, depth=None, obj_ids=(1,)):
    model = ObjectModel(
        pts=np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), faces=np.array([[0, 1, 2]])
    )
    for o in obj_ids:
        save_ply(root / "models" / f"obj_{o:06d}.ply", model)
    save_models_info(
        root / "models" / "models_info.json", {o: compute_model_info(model.pts) for o in obj_ids}
    )
    sdir = root / "test" / "000001"
    save_scene_camera(sdir / "scene_camera.json", {0: CameraInfo(K=K, depth_scale=1.0)})
    save_scene_gt(sdir / "scene_gt.json", {0: gts})
    save_rgb(sdir / "rgb" / "000000.png", np.zeros((H, W, 3), np.uint8))
    if depth is not None:
        save_depth(sdir / "depth" / "000000.png", depth)
    return sdir


def _annotate(root, **kw):
    return annotate_dataset(root, "test", renderer=SquareRenderer(), progress=False, **kw)


def test_truncated_instance_counts_the_part_outside(tmp_path):
    sdir = _dataset(
        tmp_path, [GtPose(1, np.eye(3), _px(2, 24, 100.0))], depth=np.full((H, W), 200.0)
    )
    _annotate(tmp_path)
    info = BopDataset(tmp_path, "test").scene(1).gt_info[0][0]
    # square columns -3..6: 3 of 10 columns outside the image
    assert info.px_count_all == 100
    assert info.px_count_visib == 70
    assert info.visib_fract == pytest.approx(0.7)
    assert info.bbox_obj == (-3, 19, 9, 9)
    assert info.bbox_visib == (0, 19, 6, 9)
    assert load_mask(sdir / "mask_visib" / "000000_000000.png").sum() == 70
    assert (tmp_path / "test_targets_bop19.json").exists()


def test_fully_occluded_instance(tmp_path):
    _dataset(tmp_path, [GtPose(1, np.eye(3), _px(32, 24, 100.0))], depth=np.full((H, W), 50.0))
    _annotate(tmp_path, delta=15.0)
    info = BopDataset(tmp_path, "test").scene(1).gt_info[0][0]
    assert info.px_count_visib == 0
    assert info.visib_fract == 0.0
    assert info.bbox_visib == (-1, -1, -1, -1)
    assert info.px_count_valid == 100


def test_without_depth_instances_occlude_each_other(tmp_path):
    near = GtPose(1, np.eye(3), _px(30, 24, 80.0))
    far = GtPose(1, np.eye(3), _px(35, 24, 120.0))  # shifted 5 px right, behind
    _dataset(tmp_path, [near, far])
    report = _annotate(tmp_path, delta=1.0)
    assert not report.with_depth
    infos = BopDataset(tmp_path, "test").scene(1).gt_info[0]
    assert infos[0].visib_fract == 1.0
    assert infos[1].px_count_visib == 50  # half of the far square is hidden
    assert infos[1].px_count_valid == 100  # no depth sensor: every pixel counts as valid


def test_existing_annotations_are_kept_unless_overwrite(tmp_path):
    sdir = _dataset(
        tmp_path, [GtPose(1, np.eye(3), _px(32, 24, 100.0))], depth=np.full((H, W), 200.0)
    )
    _annotate(tmp_path)
    info_file = sdir / "scene_gt_info.json"
    info_file.write_text(info_file.read_text().replace('"px_count_all": 100', '"px_count_all": 7'))
    again = _annotate(tmp_path)
    assert again.scenes_skipped == 1
    assert '"px_count_all": 7' in info_file.read_text()
    _annotate(tmp_path, overwrite=True)
    assert '"px_count_all": 100' in info_file.read_text()


@pytest.mark.parametrize(
    ("case", "match"),
    [
        ("obj0", "obj_id must be >= 1"),
        ("unknown_obj", "obj_id 5 has no model"),
        ("depth_size", "depth image is 32x24"),
        ("no_K", "no cam_K"),
    ],
)
def test_bad_input_is_one_error_and_nothing_written(tmp_path, case, match):
    pose = GtPose(1 if case != "obj0" else 0, np.eye(3), _px(32, 24, 100.0))
    if case == "unknown_obj":
        pose = GtPose(5, np.eye(3), pose.t)
    depth = np.full((24, 32) if case == "depth_size" else (H, W), 200.0)
    sdir = _dataset(tmp_path, [pose], depth=depth)
    if case == "no_K":
        save_scene_camera(sdir / "scene_camera.json", {1: CameraInfo(K=K, depth_scale=1.0)})
        save_rgb(sdir / "rgb" / "000001.png", np.zeros((H, W, 3), np.uint8))
    with pytest.raises(DatasetError, match=match) as err:
        _annotate(tmp_path)
    assert "\n" not in str(err.value)
    assert not (sdir / "scene_gt_info.json").exists()
    assert not (sdir / "mask").exists()
