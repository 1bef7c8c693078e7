"""A render backend from outside: `bopsurg generate` through the protocol and entry points only.

The pure-numpy needle backend (:mod:`tests.generators.numpy_backend`) is registered from a
temporary ``.dist-info`` folder, exactly as ``pip install`` of a third-party package would,
so discovery, options, scene, object models, rendering and writing all go through the public
contract. No pybullet.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")  # bopsurg[sim]: the bag writer these tests record with

from bopsurg.bop.check import check_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_rgb
from bopsurg.cli.main import main
from bopsurg.generators.backend import (
    ARMS,
    PARKED_PSM_JOINTS,
    CameraSpec,
    RenderBackend,
    SceneSpec,
    default_state,
    split_backend_config,
)
from bopsurg.generators.bags import Recording, write_bag
from bopsurg.generators.kinematics import DEFAULT_LAYOUT, ecm_camera_pose, pose, rot_z
from bopsurg.needle import NeedleSpec, needle_mesh
from bopsurg.plugins import load_plugin
from bopsurg.silhouette import project_silhouette
from tests.generators.numpy_backend import NumpyNeedleBackend, rasterize_depth

ENTRY = "numpy_needle = tests.generators.numpy_backend:NumpyNeedleBackend\n"


def _register(site: Path, group: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Install the numpy backend's entry point under ``group`` (metadata only)."""
    info = site / "numpy_needle_backend-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: numpy-needle-backend\nVersion: 1.0\n", encoding="utf-8"
    )
    (info / "entry_points.txt").write_text(f"[{group}]\n{ENTRY}", encoding="utf-8")
    monkeypatch.syspath_prepend(str(site))


@pytest.fixture
def registered(tmp_path, monkeypatch):
    _register(tmp_path / "site", "bopsurg.render_backends", monkeypatch)


@pytest.fixture
def bag(tmp_path) -> Path:
    """Two seconds of the needle turning and sliding on the tissue, arms parked (ROS1 bag)."""
    times = np.linspace(0.0, 2.0, 21)
    poses = np.stack([pose(rot_z(0.5 * t), [0.004 * t - 0.004, 0.0, 0.36e-3]) for t in times])
    parked = np.tile(PARKED_PSM_JOINTS, (len(times), 1))
    rec = Recording(
        psm_joints=dict.fromkeys(ARMS, (times, parked)),
        jaws={arm: (times, np.zeros(len(times))) for arm in ARMS},
        needle_pose=(times, poses),
    )
    path = tmp_path / "needle.bag"
    write_bag(path, rec)
    return path


def test_generate_end_to_end_with_a_numpy_backend(registered, bag, tmp_path):
    out = tmp_path / "ds"
    args = ["generate", str(bag), "--out", str(out), "--backend", "numpy_needle"]
    args += ["--backend-option", "grey=60", "--replays", "2", "--period", "0.5"]
    args += ["--width", "160", "--height", "120", "--min-visib", "0", "--no-progress"]
    args += ["--amodal-renderer", "backend"]  # no pybullet anywhere
    assert main(args) == 0
    assert check_dataset(out, "test") == []
    ds = BopDataset(out, "test")
    assert ds.scene_ids == [1, 2]
    np.testing.assert_allclose(ds.model(1).pts, needle_mesh().pts, atol=1e-5)  # PLY precision
    record = json.loads((out / "test" / "bopsurg_generate.json").read_text())
    # The backend's options are recorded as given; no PyBullet key slips in.
    assert record["settings"]["backend_config"] == {"annotate_instruments": False, "grey": "60"}
    scene = ds.scene(1)
    assert scene.im_ids == [0, 1, 2, 3, 4]
    for im_id in scene.im_ids:
        info = scene.gt_info[im_id][0]
        assert info.px_count_all > 10  # a thin arc at 160 x 120 px
        assert info.visib_fract == 1.0  # nothing occludes the needle alone
    rgb = load_rgb(scene.rgb_path(0))
    assert (rgb[0, 0] == 60).all()


def test_unknown_backend_option_is_a_one_line_error(registered, bag, tmp_path, capsys):
    args = ["generate", str(bag), "--out", str(tmp_path / "ds"), "--backend", "numpy_needle"]
    assert main([*args, "--backend-option", "colour=red", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "--backend-option" in err
    assert "'colour'" in err
    args[-1] = "pybullet"
    assert main([*args, "--backend-option", "annotate_instruments=1", "--no-progress"]) == 2
    assert "describes the scene" in capsys.readouterr().err


def test_the_former_group_name_still_works_with_a_warning(tmp_path, monkeypatch, caplog):
    _register(tmp_path / "old_site", "bopsurg.generators", monkeypatch)
    with caplog.at_level(logging.WARNING, logger="bopsurg.plugins"):
        assert load_plugin("backend", "numpy_needle") is NumpyNeedleBackend
    assert "deprecated entry-point group 'bopsurg.generators'" in caplog.text
    assert "'bopsurg.render_backends'" in caplog.text


def test_numpy_backend_meets_the_protocol_and_the_scene_spec():
    backend = NumpyNeedleBackend({"grey": 10})
    assert isinstance(backend, RenderBackend)
    scene, options = split_backend_config({"needle": {"arc_radius": 12.0}, "grey": "10"})
    assert options == {"grey": "10"}
    assert scene == SceneSpec(needle=NeedleSpec(arc_radius=12.0))
    backend.load_scene(scene)
    np.testing.assert_array_equal(backend.object_pose("needle"), default_state().needle_pose)
    with pytest.raises(KeyError):
        backend.object_model("scalpel")
    with pytest.raises(ValueError, match="'colour'"):
        NumpyNeedleBackend({"colour": "red"})
    with pytest.raises(TypeError, match="layout"):
        split_backend_config({"layout": "left"})


def test_rasterizer_matches_the_silhouette_of_the_needle():
    """The test backend is a real renderer: its mask is the model's projected silhouette."""
    model = needle_mesh()
    T_world_cam = ecm_camera_pose(np.zeros(4), DEFAULT_LAYOUT)
    K = np.array([[1500.0, 0.0, 200.0], [0.0, 1500.0, 150.0], [0.0, 0.0, 1.0]])  # wire ~10 px
    camera = CameraSpec(K=K, width=400, height=300, T_world_cam=T_world_cam)
    T_cam_obj = np.linalg.solve(T_world_cam, default_state().needle_pose)
    depth = rasterize_depth(model, T_cam_obj, camera)
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3] * 1000.0
    sil = project_silhouette(model.pts, model.faces, K, R, t, (300, 400))
    mask = depth > 0
    iou = (mask & sil).sum() / (mask | sil).sum()
    assert mask.sum() > 1000
    assert iou > 0.9, iou  # the two differ on edge pixels only (centre vs area rule)
    z = (model.pts @ R.T + t)[:, 2]
    assert depth[mask].min() >= z.min() - 0.01
    assert depth[mask].max() <= z.max() + 0.01
