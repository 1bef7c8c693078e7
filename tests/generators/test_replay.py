"""Replay and generation pipeline, with a fake backend: writing, visibility, determinism,
resuming and bad input (the PyBullet backend has its own tests)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from bopsurg.bop.check import check_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_mask
from bopsurg.errors import InputError
from bopsurg.generators import generate as gen
from bopsurg.generators.replay import GenerateSettings, ReplayUnit, frame_times, run_replay
from tests.generators.fake_backend import FakeBackend, FakeRecording


@pytest.fixture
def fake(monkeypatch, tmp_path):
    bag = tmp_path / "a.bag"
    bag.write_bytes(b"fake bag")
    monkeypatch.setattr(gen, "make_backend", lambda settings: FakeBackend())
    monkeypatch.setattr(gen, "_read_bag", lambda path, topic_map: FakeRecording())
    return bag


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


SETTINGS = GenerateSettings(replays=2, period=0.5, seed=7, min_visib=0.2, renderer=None)


def test_frame_times_are_exact_multiples():
    assert frame_times(0.0, 2.0, 0.5).tolist() == [0.0, 0.5, 1.0, 1.5, 2.0]
    assert frame_times(1.0, 1.2, 0.5).tolist() == [1.0]
    with pytest.raises(InputError, match="period"):
        frame_times(0.0, 1.0, 0.0)


def test_generate_writes_a_valid_bop_dataset(fake, tmp_path):
    out = tmp_path / "ds"
    rep = gen.generate_dataset([fake], out, settings=SETTINGS, progress=False)
    assert rep.scenes == 2
    assert rep.frames_rendered == 2 * 9
    assert 0 < rep.frames_written < rep.frames_rendered  # the occluding bar drops frames
    assert check_dataset(out, "test") == []
    ds = BopDataset(out, "test")
    assert ds.scene_ids == [1, 2]
    for scene in ds.iter_scenes():
        for im_id, infos in scene.gt_info.items():
            info = infos[0]
            assert info.visib_fract >= SETTINGS.min_visib
            visib = load_mask(scene.mask_visib_path(im_id, 0))
            assert int(visib.sum()) == info.px_count_visib
            cam = scene.camera[im_id]
            assert cam.depth_scale == SETTINGS.depth_scale
            assert cam.R_w2c is not None
    assert (out / "test_targets_bop19.json").exists()
    assert (out / "test" / gen.INFO_NAME).exists()


def test_same_seed_same_bytes_other_seed_other_viewpoints(fake, tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    gen.generate_dataset([fake], a, settings=SETTINGS, progress=False)
    gen.generate_dataset([fake], b, settings=SETTINGS, progress=False)
    da, db = _tree_digest(a), _tree_digest(b)
    # the generation record holds absolute bag paths, identical here
    assert da == db
    other = GenerateSettings(**{**SETTINGS.to_json(), "seed": 8})
    gen.generate_dataset([fake], c, settings=other, progress=False)
    assert (a / "test/000001/scene_camera.json").read_bytes() != (
        c / "test/000001/scene_camera.json"
    ).read_bytes()


def test_killed_replay_resumes_to_identical_bytes(fake, tmp_path):
    clean, killed = tmp_path / "clean", tmp_path / "killed"
    gen.generate_dataset([fake], clean, settings=SETTINGS, progress=False)

    gen._write_dataset_files(killed, "test", [str(fake)], SETTINGS)
    unit = ReplayUnit(str(fake), 0, 0, str(killed), "test", SETTINGS)
    calls = {"n": 0}

    def die_after_five(_n: int) -> None:
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_replay(unit, FakeBackend(), lambda p, m: FakeRecording(), on_frame=die_after_five)
    partial = killed / "test" / "000001"
    assert (partial / "bopsurg_scene.json").exists()
    # what a SIGKILL in the middle of an atomic write leaves behind
    (partial / "rgb" / ".000007.tmp-99999.png").write_bytes(b"")
    rep = gen.generate_dataset([fake], killed, settings=SETTINGS, progress=False)
    assert rep.frames_rendered < 2 * 9  # it resumed instead of starting over
    assert _tree_digest(clean) == _tree_digest(killed)


def test_rerun_skips_finished_scenes(fake, tmp_path):
    out = tmp_path / "ds"
    gen.generate_dataset([fake], out, settings=SETTINGS, progress=False)
    rep = gen.generate_dataset([fake], out, settings=SETTINGS, progress=False)
    assert rep.scenes_skipped == 2
    assert rep.frames_rendered == 0


def test_other_settings_into_the_same_split_are_refused(fake, tmp_path):
    out = tmp_path / "ds"
    gen.generate_dataset([fake], out, settings=SETTINGS, progress=False)
    other = GenerateSettings(**{**SETTINGS.to_json(), "period": 0.25})
    before = _tree_digest(out)
    with pytest.raises(InputError, match=r"other bags or settings \(period: 0.5 recorded, 0.25"):
        gen.generate_dataset([fake], out, settings=other, progress=False)
    assert _tree_digest(out) == before


def test_a_refused_resume_names_what_changed():
    old = {"seed": 1, "camera": {"fov": 40, "far": 1.0}, "domain": None}
    new = {"seed": 2, "camera": {"fov": 40, "far": 2.0}, "domain": "wide", "domain_revision": 4}
    assert gen._settings_changes(old, new) == [
        "camera.far: 1.0 recorded, 2.0 now",
        'domain: none recorded, "wide" now',
        "domain_revision: none recorded, 4 now",
        "seed: 1 recorded, 2 now",
    ]
    assert gen._settings_changes(new, new) == []
    long = gen._settings_changes({"k": "x" * 80}, {"k": "y"})[0]
    assert long.endswith('"y" now')
    assert "…" in long
    assert len(long) < 70


def test_missing_bag_is_a_one_line_error(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        gen.generate_dataset([tmp_path / "nope.bag"], tmp_path / "ds", progress=False)


def test_gt_pose_matches_the_recording(fake, tmp_path):
    out = tmp_path / "ds"
    gen.generate_dataset([fake], out, settings=SETTINGS, progress=False)
    ds = BopDataset(out, "test")
    scene = ds.scene(1)
    for im_id, gts in scene.gt.items():
        cam = scene.camera[im_id]
        T_c2w = np.eye(4)
        T_c2w[:3, :3], T_c2w[:3, 3] = cam.R_w2c, cam.t_w2c  # world -> camera, mm
        needle_world = FakeRecording().state_at(im_id * 0.5).needle_pose[:3, 3] * 1000.0
        expected = cam.R_w2c @ needle_world + cam.t_w2c
        np.testing.assert_allclose(gts[0].t, expected, atol=1e-6)
