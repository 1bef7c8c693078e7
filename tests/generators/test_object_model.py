"""`bopsurg generate --object-model`: the user's needle mesh, in its own frame, on the recorded
needle's motion.

The user's mesh here is bopsurg's needle moved by a known rigid transform M (and its vertices
shuffled, so nothing can rely on vertex order): every GT pose must be the default generation's
composed with M⁻¹, and the written masks must be that mesh projected at the GT pose. The
pure-numpy backend renders (registered as a third-party plugin; no pybullet).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")  # bopsurg[sim]: the bag writer these tests record with

from bopsurg.bop.check import check_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_mask
from bopsurg.bop.meshes import ObjectModel, save_ply
from bopsurg.cli.main import main
from bopsurg.errors import BopsurgError, ModelError
from bopsurg.generators.backend import (
    ARMS,
    PARKED_PSM_JOINTS,
    CameraSpec,
    SceneSpec,
    default_state,
)
from bopsurg.generators.bags import Recording, write_bag
from bopsurg.generators.kinematics import DEFAULT_LAYOUT, ecm_camera_pose, pose, rot_z
from bopsurg.generators.object_model import load_needle_model
from bopsurg.needle import NeedleSpec, needle_mesh
from bopsurg.silhouette import project_silhouette
from tests.generators.fake_backend import FakeBackend
from tests.generators.numpy_backend import rasterize_depth
from tests.generators.test_backend_plugin import _register

# The user's model frame: x_user = RM x_bopsurg + TM (mm).
RM = pose(rot_z(2.1), [0, 0, 0])[:3, :3] @ np.array(
    [[1.0, 0.0, 0.0], [0.0, np.cos(0.7), -np.sin(0.7)], [0.0, np.sin(0.7), np.cos(0.7)]]
)
TM = np.array([3.0, -7.5, 2.0])


def _moved(model: ObjectModel, seed: int = 0) -> ObjectModel:
    """``model`` in the user's frame, vertices shuffled (faces renumbered)."""
    perm = np.random.default_rng(seed).permutation(len(model.pts))
    inverse = np.argsort(perm)
    normals = None if model.normals is None else model.normals[perm] @ RM.T
    return ObjectModel(model.pts[perm] @ RM.T + TM, inverse[model.faces], normals)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A bag of the needle turning and sliding on the tissue, and the meshes to bring."""
    root = tmp_path_factory.mktemp("objmodel")
    times = np.linspace(0.0, 1.0, 11)
    poses = np.stack([pose(rot_z(0.8 * t), [0.004 * t - 0.002, 0.001, 0.36e-3]) for t in times])
    parked = np.tile(PARKED_PSM_JOINTS, (len(times), 1))
    rec = Recording(
        psm_joints=dict.fromkeys(ARMS, (times, parked)),
        jaws={arm: (times, np.zeros(len(times))) for arm in ARMS},
        needle_pose=(times, poses),
    )
    write_bag(root / "needle.bag", rec)
    save_ply(root / "user.ply", _moved(needle_mesh()))
    box = ObjectModel(
        np.array([[x, y, z] for x in (-10, 10) for y in (-5, 5) for z in (-2, 2)], float),
        np.array([[0, 1, 2], [1, 3, 2], [4, 6, 5], [5, 6, 7], [0, 4, 1], [1, 4, 5]]),
    )
    save_ply(root / "box.ply", box)
    return root


@pytest.fixture
def registered(tmp_path, monkeypatch):
    _register(tmp_path / "site", "bopsurg.render_backends", monkeypatch)


# Zoomed in (f = 900 px at 240 x 180) so the wire is several px wide and edges matter little.
OPTS = ["--backend", "numpy_needle", "--amodal-renderer", "backend", "--replays", "1"]
OPTS += ["--period", "0.5", "--width", "240", "--height", "180", "--K", "900,900,120,90"]
OPTS += ["--min-visib", "0", "--seed", "3", "--no-progress"]


def _generate(bag: Path, out: Path, *extra: str) -> int:
    return main(["generate", str(bag), "--out", str(out), *OPTS, *extra])


@pytest.fixture
def generated(registered, files, tmp_path):
    """The same bag and viewpoint with bopsurg's needle and with the user's mesh."""
    base, user = tmp_path / "base", tmp_path / "user"
    assert _generate(files / "needle.bag", base) == 0
    assert _generate(files / "needle.bag", user, "--object-model", str(files / "user.ply")) == 0
    return BopDataset(base, "test"), BopDataset(user, "test")


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_gt_poses_are_the_users_frame_on_the_same_motion(generated, files):
    base, user = generated
    assert check_dataset(user.root, "test") == []
    user_mesh = _moved(needle_mesh())
    np.testing.assert_allclose(user.model(1).pts, user_mesh.pts, atol=1e-5)  # PLY float32
    scene_b, scene_u = base.scene(1), user.scene(1)
    assert scene_u.im_ids == scene_b.im_ids == [0, 1, 2]
    visible = 0
    for im_id in scene_u.im_ids:
        gb, gu = scene_b.gt[im_id][0], scene_u.gt[im_id][0]
        # x_cam = Rb x_b + tb, x_b = RMᵀ (x_user − TM)  →  Ru = Rb RMᵀ, tu = tb − Ru TM
        np.testing.assert_allclose(gu.R, gb.R @ RM.T, atol=1e-6)
        np.testing.assert_allclose(gu.t, gb.t - gu.R @ TM, atol=1e-4)
        mask = load_mask(scene_u.mask_path(im_id, 0))
        if mask.sum() < 200:
            continue
        visible += 1
        K = scene_u.camera[im_id].K
        sil = project_silhouette(user_mesh.pts, user_mesh.faces, K, gu.R, gu.t, mask.shape)
        assert _iou(mask, sil) > 0.9  # the user's mesh at its GT pose is the rendered needle
        assert _iou(mask, load_mask(scene_b.mask_path(im_id, 0))) > 0.98  # the same needle
        # gt_info comes from the user's mesh: amodal counts (3x canvas) as the same needle's
        ib, iu = scene_b.gt_info[im_id][0], scene_u.gt_info[im_id][0]
        assert iu.px_count_all == pytest.approx(ib.px_count_all, rel=0.02)
        assert iu.px_count_visib == int(load_mask(scene_u.mask_visib_path(im_id, 0)).sum())
    assert visible >= 2
    # models_info: the fitted tip, tail and plane normal, in the user's frame
    info = user.models_info[1]
    np.testing.assert_allclose(info["keypoints"]["tip"], RM @ needle_mesh().pts[-1] + TM, atol=0.05)
    np.testing.assert_allclose(info["plane_normal"], RM[:, 2], atol=1e-6)
    assert info["diameter"] == pytest.approx(base.models_info[1]["diameter"], abs=1e-4)
    # the generation record names the mesh by path and checksum
    record = json.loads((user.root / "test" / "bopsurg_generate.json").read_text())
    model = record["settings"]["backend_config"]["object_model"]
    assert model["path"] == str((files / "user.ply").resolve())
    assert len(model["sha256"]) == 64
    # without --object-model nothing about it is recorded (byte-identical to before)
    base_record = json.loads((base.root / "test" / "bopsurg_generate.json").read_text())
    assert "object_model" not in base_record["settings"]["backend_config"]


def test_resume_refuses_another_mesh_but_not_a_moved_copy(generated, files, tmp_path, capsys):
    _, user = generated
    other = tmp_path / "other.ply"
    save_ply(other, _moved(needle_mesh(), seed=1))  # same geometry, other bytes
    assert _generate(files / "needle.bag", user.root, "--object-model", str(other)) == 2
    err = capsys.readouterr().err.strip()
    assert "generated with the object model" in err
    assert "\n" not in err
    assert _generate(files / "needle.bag", user.root) == 2  # and not without it either
    copy = tmp_path / "copy.ply"
    shutil.copy(files / "user.ply", copy)
    assert _generate(files / "needle.bag", user.root, "--object-model", str(copy)) == 0
    assert "1 already done" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("name", "expected"),
    [("box.ply", "not a needle"), ("missing.ply", "not found"), ("garbage.ply", "PLY")],
)
def test_a_mesh_that_is_not_a_needle_is_a_one_line_error(
    registered, files, tmp_path, capsys, name, expected
):
    (files / "garbage.ply").write_text("not a ply\n")
    out = tmp_path / "ds"
    assert _generate(files / "needle.bag", out, "--object-model", str(files / name)) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bopsurg: error: --object-model:")
    assert name in err
    assert expected in err
    assert "\n" not in err
    assert not out.exists()  # nothing half-written


def test_the_users_radius_defines_the_geometry(registered, files, tmp_path, capsys):
    big = tmp_path / "big.ply"
    save_ply(big, needle_mesh(NeedleSpec(arc_radius=12.0)))
    out = tmp_path / "ds"
    assert _generate(files / "needle.bag", out, "--object-model", str(big)) == 0
    (line,) = capsys.readouterr().err.strip().splitlines()  # one line says what was done
    assert line.startswith(f"WARNING: {big.resolve()}: fitted arc radius 12.00 mm")
    assert "+18 %" in line
    assert "1.82 mm off" in line
    ds = BopDataset(out, "test")
    np.testing.assert_allclose(
        ds.model(1).pts, needle_mesh(NeedleSpec(arc_radius=12.0)).pts, atol=1e-5
    )
    assert check_dataset(out, "test") == []
    # centred on the recorded arc: the model's arc centre sits at the needle frame's origin
    model = load_needle_model(big)
    T = model.T_needle_model
    np.testing.assert_allclose(T[:3, :3] @ model.arc.center * 1e-3 + T[:3, 3], 0, atol=1e-9)
    metres = tmp_path / "metres.ply"
    m = needle_mesh()
    save_ply(metres, ObjectModel(m.pts * 1e-3, m.faces, m.normals))
    with pytest.raises(ModelError, match="BOP models are in mm"):
        load_needle_model(metres)


def test_needle_model_maps_bopsurg_frame_to_the_users(files):
    model = load_needle_model(files / "user.ply")
    # T_needle_model = M⁻¹ (m): x_needle = RMᵀ (x_user − TM)
    np.testing.assert_allclose(model.T_needle_model[:3, :3], RM.T, atol=1e-6)  # float32 PLY
    np.testing.assert_allclose(model.T_needle_model[:3, 3], -RM.T @ TM * 1e-3, atol=1e-8)
    scene = SceneSpec(needle_model=model)
    T = default_state().needle_pose
    np.testing.assert_allclose(scene.needle_model_pose(T), T @ model.T_needle_model)
    np.testing.assert_array_equal(SceneSpec().needle_model_pose(T), T)


def test_a_backend_that_ignores_the_object_model_is_refused(files, tmp_path, monkeypatch):
    from bopsurg.generators import generate as gen
    from bopsurg.generators.replay import GenerateSettings

    monkeypatch.setattr(gen, "make_backend", lambda settings: FakeBackend())
    settings = GenerateSettings(backend_config={"object_model": str(files / "user.ply")})
    with pytest.raises(BopsurgError, match="does not support --object-model"):
        gen.generate_dataset([files / "needle.bag"], tmp_path / "ds", settings=settings)
    assert not (tmp_path / "ds" / "models").exists()


def test_pybullet_renders_the_users_mesh_at_its_pose(files):
    pytest.importorskip("pybullet")
    from bopsurg.generators.pybullet_backend import PyBulletBackend

    model = load_needle_model(files / "user.ply")
    T_world_cam = ecm_camera_pose(np.zeros(4), DEFAULT_LAYOUT)
    K = np.array([[1500.0, 0.0, 200.0], [0.0, 1500.0, 150.0], [0.0, 0.0, 1.0]])
    camera = CameraSpec(K=K, width=400, height=300, T_world_cam=T_world_cam)
    with PyBulletBackend({"renderer": "tiny"}) as backend:
        backend.load_scene(SceneSpec(needle_model=model))
        assert backend.object_model("needle") is model.model
        T_world_obj = backend.object_pose("needle")
        np.testing.assert_allclose(
            T_world_obj, default_state().needle_pose @ model.T_needle_model, atol=1e-12
        )
        depth = backend.render_object_depth("needle", camera)
    T_cam_obj = np.linalg.solve(T_world_cam, T_world_obj)
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3] * 1000.0
    sil = project_silhouette(model.model.pts, model.model.faces, K, R, t, (300, 400))
    assert sil.sum() > 1000
    assert _iou(depth > 0, sil) > 0.9
    ref = rasterize_depth(model.model, T_cam_obj, camera) > 0
    assert _iou(depth > 0, ref) > 0.9


def test_a_training_split_keeps_the_test_splits_targets(registered, files, tmp_path):
    # generating test and then train into one dataset: evaluating the test split needs the
    # targets of its own images (a train split once overwrote them: "no scene 33")
    out = tmp_path / "ds"
    assert _generate(files / "needle.bag", out) == 0
    before = {
        n: (out / n).read_bytes() for n in ("test_targets_bop19.json", "test_targets_bop24.json")
    }
    assert _generate(files / "needle.bag", out, "--split", "train", "--replays", "2") == 0
    assert (out / "train" / "000002").is_dir()  # a scene the test split does not have
    for name, content in before.items():
        assert (out / name).read_bytes() == content


def _grip_radius(bag: Path) -> float:
    """Median in-plane distance (mm) of PSM1's tool tip from the needle's arc centre while
    PSM1 holds the needle: the wire's radius less the tilted jaws' reach (same for one seed)."""
    from bopsurg.generators.bag_reader import read_bag
    from bopsurg.generators.kinematics import psm_tip_pose

    rec = read_bag(bag)
    hold = next(g for g in rec.meta["grasps"] if g["arm"] == "psm1")
    times, joints = rec.psm_joints["psm1"]
    n_times, needle = rec.needle_pose
    keep = (times > hold["t_from"] + 0.05) & (times < hold["t_to"] - 0.05)
    base = DEFAULT_LAYOUT.psm_base(0)
    radii = []
    for t, q in zip(times[keep], joints[keep], strict=True):
        T = needle[int(np.argmin(np.abs(n_times - t)))]
        tip = np.linalg.inv(T) @ base @ psm_tip_pose(q)  # tool tip in the needle frame, m
        radii.append(1e3 * np.hypot(tip[0, 3], tip[1, 3]))
    return float(np.median(radii))


def test_record_plans_for_the_users_needle_and_generate_replays_it(registered, tmp_path, capsys):
    big = tmp_path / "big.ply"
    save_ply(big, _moved(needle_mesh(NeedleSpec(arc_radius=12.0))))
    mine, default = tmp_path / "mine.bag", tmp_path / "default.bag"
    assert main(["record", "--out", str(mine), "--seed", "1", "--duration", "6",
                 "--object-model", str(big)]) == 0  # fmt: skip
    assert "radius 12.00 mm, arc 128.5 deg" in capsys.readouterr().out
    assert main(["record", "--out", str(default), "--seed", "1", "--duration", "6"]) == 0
    # same seed, same draws: the grasps hold the user's wire, 12 - 10.18 mm further out
    assert _grip_radius(mine) - _grip_radius(default) == pytest.approx(1.82, abs=0.01)
    capsys.readouterr()
    out = tmp_path / "ds"
    assert _generate(mine, out, "--period", "2", "--object-model", str(big)) == 0
    assert "WARNING" not in capsys.readouterr().err  # the recorded needle is the user's
    record = json.loads((out / "test" / "bopsurg_generate.json").read_text())
    assert record["settings"]["backend_config"]["needle"]["arc_radius"] == pytest.approx(12.0)
    assert check_dataset(out, "test") == []
    # bags of two needles do not mix; the message names the odd one
    mix = ["generate", str(default), str(mine), "--out", str(tmp_path / "mix"), *OPTS]
    assert main(mix) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bopsurg: error: ")
    assert str(mine) in err
    assert "recorded for another needle" in err
    assert not (tmp_path / "mix").exists()  # refused before anything was written
