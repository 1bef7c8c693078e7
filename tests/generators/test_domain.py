"""`generate --domain`: the paper profile is the old draw, the wide one reaches 20-120 mm,
is recorded and deterministic, paints suture targets on half its phantoms, shows the groove
pad on half, and its suture thread occludes the needle in its masks."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from bopsurg.errors import InputError
from bopsurg.generators import generate as gen
from bopsurg.generators.backend import (
    DEFAULT_ECM_JOINTS,
    DEFAULT_NEEDLE_POSE,
    CameraSpec,
    LightSpec,
    SceneSpec,
)
from bopsurg.generators.domain import (
    DOMAIN_REVISIONS,
    GROOVE_SHARE,
    MARK_COLOURS,
    MARKS_SHARE,
    ORBIT_ELEVATION_DEG,
    ORBIT_SHARE,
    WIDE_DISTANCE_MM,
    MarksDraw,
    OrbitDraw,
    SutureThread,
    dolly_offset,
    draw_domain,
    floor_height,
    needle_tail,
    orbit_offset,
)
from bopsurg.generators.kinematics import ecm_camera_pose, look_rotation, pose
from bopsurg.generators.pybullet_scene import (
    GROOVE_DEPTH,
    INCISION_HALF_LENGTH,
    INCISIONS_X,
    LIP_HEIGHT,
    LIP_OFFSET,
    MARK_SHAPES,
    PAD_SIZE,
    pad_height,
    pad_mesh,
    paint_marks,
)
from bopsurg.generators.replay import GenerateSettings
from bopsurg.generators.viewpoints import draw_replay
from bopsurg.needle import needle_mesh
from tests.generators.fake_backend import FakeBackend, FakeRecording


def test_paper_profile_is_the_draw_of_before():
    for seed in range(5):
        for replay in (0, 7):
            draw, domain = draw_domain(np.random.default_rng(seed), replay, "paper")
            assert domain is None
            assert draw == draw_replay(np.random.default_rng(seed), replay)
    assert "domain" not in GenerateSettings().to_json()  # the record of before, unchanged
    assert GenerateSettings(domain="wide").to_json()["domain"] == "wide"
    with pytest.raises(ValueError, match="unknown domain"):
        draw_domain(np.random.default_rng(0), 0, "nope")


def test_each_wide_revision_keeps_the_draws_of_the_one_before():
    """Revision 1's, 2's and 3's draws are recorded here (from their code), so what a later
    revision draws last changes nothing drawn before it."""
    _, domain = draw_domain(np.random.default_rng(4), 0, "wide")
    assert domain is not None
    assert domain.distance_mm == pytest.approx(67.71535238392063, abs=1e-12)
    assert domain.thread is not None
    assert domain.thread.lay_seed == 1070443482
    assert (domain.light_setup, domain.phantom_tint) == ("bright", "yellow")
    _, domain = draw_domain(np.random.default_rng(8), 8, "wide")  # revision 2: the targets
    assert domain is not None
    assert domain.appearance.phantom_marks == MarksDraw(
        "square", "blue", 3.356799586481439, 9.64398400542885, 3.2807099489468046
    )
    _, domain = draw_domain(np.random.default_rng(0), 0, "wide")  # revision 3: the orbit
    assert domain is not None
    assert domain.orbit == OrbitDraw(
        53.2893004116449, 189.1275560912613, -68.31292479877597, -0.42493923504632747,
        11.684635030470009,
    )  # fmt: skip
    assert GenerateSettings(domain="wide").to_json()["domain_revision"] == 4


def test_wide_draws_targets_orbits_and_grooves_on_their_shares_of_replays():
    marks, orbits, shapes = [], [], []
    for seed in range(400):
        _, d = draw_domain(np.random.default_rng(seed), seed % 20, "wide")
        assert d is not None
        marks.append(d.appearance.phantom_marks)
        orbits.append(d.orbit)
        shapes.append(d.appearance.phantom_shape)
    assert set(shapes) == {"incisions", "groove"}
    assert abs(shapes.count("groove") / len(shapes) - GROOVE_SHARE) < 0.08
    shown = [m for m in marks if m is not None]
    assert abs(len(shown) / len(marks) - MARKS_SHARE) < 0.08
    assert {m.shape for m in shown} == set(MARK_SHAPES)
    assert {m.colour for m in shown} == set(MARK_COLOURS)
    assert all(2.0 <= m.size_mm <= 5.0 and 2.5 <= m.offset_mm <= 6.0 for m in shown)
    orbiting = [o for o in orbits if o is not None]
    assert abs(len(orbiting) / len(orbits) - ORBIT_SHARE) < 0.08
    elevation = np.array([o.elevation_deg for o in orbiting])
    assert ORBIT_ELEVATION_DEG[0] <= elevation.min() < 15.0
    assert 65.0 < elevation.max() <= ORBIT_ELEVATION_DEG[1]
    roll = np.array([o.roll_deg for o in orbiting])
    assert np.histogram(roll, bins=4, range=(-180, 180))[0].min() > 0.15 * len(roll)


@pytest.mark.parametrize(
    "orbit",
    [
        OrbitDraw(
            elevation_deg=30.0, azimuth_deg=120.0, roll_deg=0.0, off_x_deg=0.0, off_y_deg=0.0
        ),
        OrbitDraw(
            elevation_deg=12.0, azimuth_deg=300.0, roll_deg=-150.0, off_x_deg=14.0, off_y_deg=-9.0
        ),
        OrbitDraw(
            elevation_deg=90.0, azimuth_deg=0.0, roll_deg=75.0, off_x_deg=-5.0, off_y_deg=15.0
        ),
    ],
)
def test_the_orbiting_endoscope_sees_the_needle_as_drawn(orbit):
    T0 = ecm_camera_pose(DEFAULT_ECM_JOINTS)
    needle = DEFAULT_NEEDLE_POSE[:3, 3] + np.array([0.004, -0.003, 0.002])
    T = T0 @ orbit_offset(T0, needle, 42.0, orbit)
    R, c = T[:3, :3], T[:3, 3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    p = R.T @ (needle - c)  # the needle in the new camera, m
    assert 1e3 * p[2] == pytest.approx(42.0, abs=1e-9)  # at the drawn depth
    # seen off the axis as drawn, then rolled about the axis with the image
    off = np.tan(np.deg2rad([orbit.off_x_deg, orbit.off_y_deg]))
    roll = np.deg2rad(orbit.roll_deg)
    turned = np.array([[np.cos(roll), np.sin(roll)], [-np.sin(roll), np.cos(roll)]]) @ off
    np.testing.assert_allclose(p[:2] / p[2], turned, atol=1e-12)
    # from the elevation and azimuth drawn, above the tissue
    d = (c - needle) / np.linalg.norm(c - needle)
    assert np.rad2deg(np.arcsin(d[2])) == pytest.approx(orbit.elevation_deg, abs=1e-9)
    if orbit.elevation_deg < 90.0:
        azimuth = np.rad2deg(np.arctan2(d[1], d[0])) % 360.0
        assert azimuth == pytest.approx(orbit.azimuth_deg, abs=1e-9)
    assert c[2] > 0.0
    if orbit.roll_deg == 0.0 and orbit.elevation_deg < 90.0:  # world +Z is image up
        up = R.T @ np.array([0.0, 0.0, 1.0])
        assert up[0] == pytest.approx(0.0, abs=1e-12)
        assert up[1] < 0.0


def test_a_turned_stereo_rig_keeps_its_right_eye_beside_the_left():
    from bopsurg.generators.replay import _View
    from bopsurg.generators.viewpoints import draw_replay as draw_view

    settings = GenerateSettings(stereo=True)
    draw = draw_view(np.random.default_rng(0), 3)
    still = _View.of(settings, draw)
    orbit = OrbitDraw(
        elevation_deg=25.0, azimuth_deg=200.0, roll_deg=40.0, off_x_deg=5.0, off_y_deg=2.0
    )
    moved = _View.of(
        settings, draw, orbit_offset(still.T_world_cam, DEFAULT_NEEDLE_POSE[:3, 3], 60.0, orbit)
    )
    assert still.right is not None
    assert moved.right is not None
    rig = np.linalg.solve(still.camera.T_world_cam, still.right.T_world_cam)
    np.testing.assert_allclose(
        np.linalg.solve(moved.camera.T_world_cam, moved.right.T_world_cam), rig, atol=1e-12
    )


def test_the_backdrop_room_faces_in_and_lies_inside_the_far_plane():
    pytest.importorskip("pybullet")
    from bopsurg.generators.pybullet_domain import backdrop_mesh

    m = backdrop_mesh()
    tri = m.pts[m.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    stored = m.normals[m.faces[:, 0]]
    np.testing.assert_allclose((n * stored).sum(1), 1.0, atol=1e-9)  # wound as its normals say
    inward = (np.array([0.0, 0.0, 100.0]) - tri.mean(1)) * stored
    assert (inward.sum(1) > 0).all()  # every face towards the pad
    # a camera anywhere the generator puts one (measured on its splits: within 0.19 m of the
    # pad's centre horizontally, up to 0.13 m above it) sees the whole room nearer than the
    # renderer's 1 m far plane
    corners = np.array([[sx, sy, 130.0] for sx in (-190.0, 190.0) for sy in (-190.0, 190.0)])
    far = np.linalg.norm(m.pts[None] - corners[:, None], axis=2).max()
    assert far < 1000.0 * CameraSpec.far


def _texel(image: np.ndarray, x_mm: float, y_mm: float) -> np.ndarray:
    h, w = image.shape[:2]
    col = int((x_mm / PAD_SIZE[0] + 0.5) * w)
    row = int((0.5 - y_mm / PAD_SIZE[1]) * h)
    return image[row, col].astype(int)


@pytest.mark.parametrize("shape", MARK_SHAPES)
def test_targets_are_painted_in_pairs_beside_every_incision(shape):
    grey = np.full((600, 800, 3), 200, np.uint8)  # 10 texels per mm
    out = paint_marks(grey, shape=shape, size_mm=3.0, spacing_mm=8.0, offset_mm=4.0, rgb=(1, 0, 0))
    assert grey[0, 0, 0] == 200  # the input is left as it was
    red = (out[..., 0] > 200) & (out[..., 1] < 60)
    n_along = 2 * int((INCISION_HALF_LENGTH + 8.0) // 8.0) + 1  # -16, -8, 0, 8, 16 mm
    n, _ = cv2.connectedComponents(red.astype(np.uint8))
    assert n - 1 == len(INCISIONS_X) * 2 * n_along
    for xc in INCISIONS_X:
        for side in (-4.0, 4.0):
            assert _texel(out, xc + side, 8.0).tolist() == [255, 0, 0]  # a target's centre
        assert _texel(out, xc, 8.0).tolist() == [200, 200, 200]  # the cut itself: bare
        assert _texel(out, xc + 4.0, 4.0).tolist() == [200, 200, 200]  # between two targets
    # a 3 mm target covers its area (dots: the disc's), to a texel's antialiasing
    area = {"square": 9.0, "diamond": 9.0, "dot": np.pi * 2.25}[shape]
    painted = (200.0 - out[..., 1]).sum() / 200.0 / 100.0  # coverage summed, mm^2
    assert painted / (n - 1) == pytest.approx(area, rel=0.03)


def test_the_groove_pad_has_one_crease_its_whole_length_between_two_lips():
    y = np.linspace(-0.5 * PAD_SIZE[1], 0.5 * PAD_SIZE[1], 61)
    groove = pad_height(0.0, y, "groove")  # the crease, end to end
    assert np.all(groove < -GROOVE_DEPTH + 0.26)  # (the undulation: at most 0.25 mm)
    lips = pad_height(np.array([[-LIP_OFFSET], [LIP_OFFSET]]), y[None, :], "groove")
    np.testing.assert_allclose(lips, LIP_HEIGHT, atol=0.26)
    # and nothing else: no incisions, no ridges
    for x, yy in [(INCISIONS_X[0], 0.0), (INCISIONS_X[2], 5.0), (10.0, 20.0), (-12.0, -20.0)]:
        assert abs(float(pad_height(x, yy, "groove"))) <= 0.25
        assert abs(float(pad_height(x, yy))) > 0.5  # where the incised pad has them
    # a closed height field like the incised pad's: every vertex used, unit normals
    model, uvs = pad_mesh("groove")
    assert np.array_equal(np.unique(model.faces), np.arange(len(model.pts)))
    np.testing.assert_allclose(np.linalg.norm(model.normals, axis=1), 1.0, atol=1e-9)
    assert uvs.shape == (len(model.pts), 2)
    for bad in (lambda: pad_height(0, 0, "moat"), lambda: pad_mesh("moat")):
        with pytest.raises(ValueError, match="unknown pad shape 'moat'"):
            bad()


def test_the_incised_pad_is_the_one_of_before():
    """The default pad's mesh, byte for byte (recorded from the code before pad shapes), so
    the ``paper`` profile's renders cannot change with the groove."""
    model, uvs = pad_mesh()
    data = model.pts.tobytes() + model.faces.tobytes() + model.normals.tobytes() + uvs.tobytes()
    assert hashlib.sha256(data).hexdigest() == (
        "b9e180fa2bf6f053c66a326bb07a7f3d0fb89241d13929077cef99106e11e24d"
    )


def test_targets_on_a_groove_pad_line_the_groove_end_to_end():
    grey = np.full((600, 800, 3), 200, np.uint8)  # 10 texels per mm
    out = paint_marks(
        grey, shape="square", size_mm=2.0, spacing_mm=8.0, offset_mm=4.0, rgb=(1, 0, 0),
        pad_shape="groove",
    )  # fmt: skip
    for side in (-4.0, 4.0):
        for y in (-24.0, 0.0, 24.0):
            assert _texel(out, side, y).tolist() == [255, 0, 0]
    for x in INCISIONS_X:
        if x != 0.0:
            assert _texel(out, x + 4.0, 8.0).tolist() == [200, 200, 200]  # none by the incisions
    assert _texel(out, 0.0, 8.0).tolist() == [200, 200, 200]  # the groove itself: bare


def test_bad_targets_are_refused():
    grey = np.full((60, 80, 3), 200, np.uint8)
    with pytest.raises(ValueError, match="unknown mark shape 'star'"):
        paint_marks(grey, shape="star", size_mm=3, spacing_mm=8, offset_mm=4, rgb=(1, 0, 0))
    with pytest.raises(ValueError, match="must be positive"):
        paint_marks(grey, shape="dot", size_mm=3, spacing_mm=0, offset_mm=4, rgb=(1, 0, 0))


@pytest.mark.parametrize("was", [1, 2])
def test_a_split_of_an_older_wide_revision_is_not_resumed(fake_bag, tmp_path, was):
    settings = GenerateSettings(replays=1, seed=3, min_visib=0.0, domain="wide")
    old = {**settings.to_json(), "domain_revision": was}
    if was == 1:
        del old["domain_revision"]  # revision 1 wrote none
    info = tmp_path / "ds/test/bopsurg_generate.json"
    info.parent.mkdir(parents=True)
    info.write_text(json.dumps({"split": "test", "settings": old, "bags": []}))
    before = info.read_bytes()
    now = DOMAIN_REVISIONS["wide"]
    recorded = "none" if was == 1 else was
    with pytest.raises(InputError, match=f"domain_revision: {recorded} recorded, {now} now"):
        gen._write_dataset_files(tmp_path / "ds", "test", [str(fake_bag)], settings)
    assert info.read_bytes() == before
    assert sorted(p.name for p in (tmp_path / "ds").rglob("*")) == ["bopsurg_generate.json", "test"]


def test_wide_distance_is_reached_at_the_needle():
    """The GT depth of the needle (its median position) is the drawn distance, 20-120 mm."""
    K = np.array([[350.8, 0.0, 320.0], [0.0, 350.8, 240.0], [0.0, 0.0, 1.0]])
    needle = DEFAULT_NEEDLE_POSE[:3, 3] + np.array([0.004, -0.003, 0.002])
    z = []
    for seed in range(60):
        draw, domain = draw_domain(np.random.default_rng([seed, 0, seed % 20]), seed % 20, "wide")
        assert domain is not None
        T0 = ecm_camera_pose(draw.ecm_joints)
        T = T0 @ dolly_offset(T0, needle, domain.distance_mm)
        p0 = np.linalg.solve(T0, np.append(needle, 1.0))[:3]
        p = np.linalg.solve(T, np.append(needle, 1.0))[:3]
        np.testing.assert_allclose(T[:3, :3], T0[:3, :3])  # only moved, not turned
        np.testing.assert_allclose((K @ p)[:2] / p[2], (K @ p0)[:2] / p0[2], atol=1e-6)  # same px
        z.append(1e3 * p[2])
        assert z[-1] == pytest.approx(domain.distance_mm, abs=1e-9)
    z = np.array(z)
    assert WIDE_DISTANCE_MM[0] <= z.min() < 35.0
    assert 105.0 < z.max() <= WIDE_DISTANCE_MM[1]


def test_dolly_brings_a_point_behind_the_camera_onto_the_axis():
    T0 = np.eye(4)
    T = T0 @ dolly_offset(T0, np.array([0.01, 0.0, -0.02]), 50.0)
    p = np.linalg.solve(T, np.array([0.01, 0.0, -0.02, 1.0]))[:3]
    np.testing.assert_allclose(p, [0.0, 0.0, 0.05], atol=1e-12)


def test_wide_shows_large_needle_driver_instruments():
    from bopsurg.generators.backend import SceneSpec
    from bopsurg.generators.domain import profile_scene
    from bopsurg.generators.pybullet_scene import build_scene

    assert profile_scene("paper", SceneSpec()) == SceneSpec()
    assert profile_scene("wide", SceneSpec()).instruments == "lnd"
    simple = build_scene(annotate_instruments=True)
    lnd = build_scene(annotate_instruments=True, instruments="lnd")
    assert simple.annotated == lnd.annotated  # same objects, same frames
    size = {k: np.ptp(v.model.pts, axis=0) for k, v in lnd.parts.items()}
    assert size["psm1_shaft"][0] == pytest.approx(8.4, abs=0.05)  # Ø 8.4 mm
    assert size["psm1_jaw1"][2] == pytest.approx(10.5, abs=0.05)  # 1 mm behind the pivot + 9.5
    assert size["psm1_wrist"][1] == pytest.approx(7.8, abs=0.05)  # the pitch drum: Ø 7.8 mm
    assert size["psm1_wrist"][2] == pytest.approx(7.6, abs=0.05)  # ... 7.6 mm long
    assert lnd.parts["psm1_jaw1"].double_sided
    assert not simple.parts["psm1_jaw1"].double_sided
    with pytest.raises(ValueError, match="unknown instruments"):
        build_scene(instruments="round")


def test_thread_is_deterministic_rests_on_the_tissue_and_keeps_its_length():
    _, domain = draw_domain(np.random.default_rng(4), 0, "wide")
    assert domain is not None
    assert domain.thread is not None
    tail, axis = needle_tail(needle_mesh())
    np.testing.assert_allclose(tail, [0.01018, 0.0, 0.0], atol=1e-5)  # the tail end, +X
    np.testing.assert_allclose(axis, [0.0, -1.0, 0.0], atol=1e-6)  # away from the tip

    def run() -> list[np.ndarray]:
        thread = SutureThread(domain.thread)
        out = []
        for k in range(4):
            T = pose(np.eye(3), [0.003 * k, 0.002 * k, 0.01])  # lifted 1 cm, moving
            out.append(thread.advance(0.5 * k, T, tail, axis))
        return out

    a, b = run(), run()
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    x = a[-1]
    np.testing.assert_allclose(x[0], [0.009 + 0.01018, 0.006, 0.01], atol=1e-9)  # on the tail
    seg = 1e-3 * domain.thread.length_mm / domain.thread.segments
    lengths = np.linalg.norm(np.diff(x, axis=0), axis=1) / seg
    assert lengths.min() > 0.8
    assert lengths.max() < 1.45  # stretched at most ~1.3 (the rendered overlap) plus slack
    # on or above the tissue (the floor is taken once per substep: 0.3 mm of slack)
    assert np.all(x[:, 2] >= floor_height(x[:, :2]) - 0.3e-3)
    assert x[-1, 2] < 0.005  # it fell onto the tissue


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture
def fake_bag(monkeypatch, tmp_path):
    bag = tmp_path / "a.bag"
    bag.write_bytes(b"fake bag")
    monkeypatch.setattr(gen, "_read_bag", lambda path, topic_map: FakeRecording(end=1.0))
    return bag


def test_paper_never_asks_the_backend_for_a_domain(fake_bag, monkeypatch, tmp_path):
    """FakeBackend has no set_appearance / set_thread: the default needs neither."""
    monkeypatch.setattr(gen, "make_backend", lambda settings: FakeBackend())
    settings = GenerateSettings(replays=1, seed=3, renderer=None, min_visib=0.0)
    gen.generate_dataset([fake_bag], tmp_path / "ds", settings=settings, progress=False)
    scene = json.loads((tmp_path / "ds/test/000001/bopsurg_scene.json").read_text())
    info = json.loads((tmp_path / "ds/test/bopsurg_generate.json").read_text())
    assert "domain" not in scene
    assert "domain" not in info["settings"]
    wide = GenerateSettings(**{**settings.to_json(), "domain": "wide"})
    with pytest.raises(InputError, match="does not support --domain wide"):
        gen.generate_dataset([fake_bag], tmp_path / "w", settings=wide, progress=False)


@pytest.mark.slow
def test_wide_is_recorded_and_gives_the_same_bytes_twice(fake_bag, tmp_path):
    pytest.importorskip("pybullet")
    settings = GenerateSettings(replays=1, seed=11, min_visib=0.0, domain="wide")
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        gen.generate_dataset([fake_bag], out, settings=settings, progress=False)
    assert _digest(a) == _digest(b)
    info = json.loads((a / "test/bopsurg_generate.json").read_text())
    assert info["settings"]["domain"] == "wide"
    assert info["settings"]["seed"] == 11
    scene = json.loads((a / "test/000001/bopsurg_scene.json").read_text())
    rng = np.random.default_rng(np.random.SeedSequence([11, 0, 0]))
    draw, domain = draw_domain(rng, 0, "wide")
    assert domain is not None
    assert scene["draw"]["ecm_joints"] == list(draw.ecm_joints)
    assert scene["domain"]["distance_mm"] == domain.distance_mm
    assert scene["domain"]["thread"]["lay_seed"] == domain.thread.lay_seed  # type: ignore[union-attr]
    assert len(scene["domain"]["camera_offset_m"]) == 3
    # the GT depth of the needle is the drawn distance at the replay's median frame
    gt = json.loads((a / "test/000001/scene_gt.json").read_text())
    z = sorted(v[0]["cam_t_m2c"][2] for v in gt.values())
    assert z[len(z) // 2] == pytest.approx(domain.distance_mm, abs=1e-6)


@pytest.mark.slow
def test_killed_wide_replay_resumes_to_the_same_bytes(fake_bag, tmp_path):
    """The thread is simulated: a resumed replay re-runs it from the first frame."""
    pytest.importorskip("pybullet")
    from bopsurg.generators.replay import ReplayUnit, run_replay

    settings = GenerateSettings(replays=1, seed=5, min_visib=0.0, domain="wide")
    clean, killed = tmp_path / "clean", tmp_path / "killed"
    gen.generate_dataset([fake_bag], clean, settings=settings, progress=False)
    gen._write_dataset_files(killed, "test", [str(fake_bag)], settings)
    unit = ReplayUnit(str(fake_bag), 0, 0, str(killed), "test", settings)

    def die_after_two(n: int, calls: list[int] = []) -> None:  # noqa: B006
        calls.append(n)
        if len(calls) == 2:
            raise KeyboardInterrupt

    backend = gen.make_backend(settings)
    with pytest.raises(KeyboardInterrupt):
        run_replay(
            unit,
            backend,
            gen._read_bag,
            amodal=gen.make_amodal(settings, killed),
            on_frame=die_after_two,
        )
    backend.close()
    rep = gen.generate_dataset([fake_bag], killed, settings=settings, progress=False)
    assert rep.frames_rendered == 1  # resumed at the third frame
    assert _digest(clean) == _digest(killed)


def test_thread_occludes_the_needle_and_is_not_in_its_visible_mask():
    pytest.importorskip("pybullet")
    from bopsurg.generators.pybullet_backend import PyBulletBackend
    from bopsurg.visibility import instance_visibility, large_canvas

    K = np.array([[350.8, 0.0, 320.0], [0.0, 350.8, 240.0], [0.0, 0.0, 1.0]])
    # 60 mm above the needle lying flat at the origin, looking straight down
    T_world_cam = pose(look_rotation([0.0, 0.0, -1.0], up_hint=(0.0, 1.0, 0.0)), [0, 0, 0.06])
    camera = CameraSpec(K=K, width=640, height=480, T_world_cam=T_world_cam)
    # a straight thread 3 mm above the tissue across the needle's arc (x from -15 to 15 mm)
    pts = np.stack([np.linspace(-0.015, 0.015, 13), np.full(13, 0.007), np.full(13, 0.003)], 1)
    with PyBulletBackend() as backend:
        backend.load_scene(SceneSpec())
        before = backend.render(camera, LightSpec())
        backend.set_thread(pts, 0.25, (0.03, 0.03, 0.035, 1.0))
        after = backend.render(camera, LightSpec())
        Kl, wl, hl = large_canvas(K, 640, 480)
        canvas = CameraSpec(K=Kl, width=wl, height=hl, T_world_cam=T_world_cam)
        alone = backend.render_object_depth("needle", canvas)
    thread = np.abs(after.depth - before.depth) > 1e-6
    assert thread.sum() > 50
    assert np.all(after.instance[thread] == 0)  # the thread is no annotated object
    assert after.rgb[thread].mean() < 60  # and dark
    v0 = instance_visibility(before.depth, alone, K, delta=1.0)
    v1 = instance_visibility(after.depth, alone, K, delta=1.0)
    crossing = thread & v0.mask
    assert crossing.sum() > 10  # it crosses the needle
    assert not v1.mask_visib[crossing].any()  # ... which is hidden there
    assert v1.info.visib_fract < v0.info.visib_fract < 1.0 + 1e-9
    assert v1.info.px_count_visib == v0.info.px_count_visib - crossing.sum()


def test_a_groove_appearance_shows_the_groove_pad_in_depth():
    pytest.importorskip("pybullet")
    from bopsurg.generators.domain import Appearance
    from bopsurg.generators.pybullet_backend import PyBulletBackend

    K = np.array([[350.8, 0.0, 320.0], [0.0, 350.8, 240.0], [0.0, 0.0, 1.0]])
    # 60 mm above the pad's centre, looking straight down; the row 11 mm off the centre (the
    # needle lies within 10 mm of it, the incisions reach 12)
    T_world_cam = pose(look_rotation([0.0, 0.0, -1.0], up_hint=(0.0, 1.0, 0.0)), [0, 0, 0.06])
    camera = CameraSpec(K=K, width=640, height=480, T_world_cam=T_world_cam)
    xs = np.linspace(-0.03, 0.03, 601)
    world = np.stack([xs, np.full_like(xs, -0.011), np.zeros_like(xs), np.ones_like(xs)])
    cam = np.linalg.solve(T_world_cam, world)[:3]
    uv = K @ cam
    cols, row = np.round(uv[0] / uv[2]).astype(int), round(float(uv[1, 0] / uv[2, 0]))

    def profile(shape: str | None) -> np.ndarray:
        with PyBulletBackend() as backend:
            backend.load_scene(SceneSpec())
            if shape is not None:
                backend.set_appearance(Appearance(phantom_shape=shape))
            return backend.render(camera, LightSpec()).depth[row, cols]

    def near(x_mm: float) -> np.ndarray:
        return np.abs(1e3 * xs - x_mm) < 0.3

    default, appearance, groove = profile(None), profile("incisions"), profile("groove")
    np.testing.assert_array_equal(appearance, default)  # only the groove swaps the pad
    # (depth in mm from the camera 60 mm above z = 0: 60 - height)
    assert groove[near(0.0)].max() > 60.0 + GROOVE_DEPTH - 0.5
    assert groove[near(LIP_OFFSET)].min() < 60.0 - LIP_HEIGHT + 0.5
    assert default[near(0.0)].max() > 60.0 + 2.5  # the incised pad's middle incision
    for x in (INCISIONS_X[0], INCISIONS_X[2]):  # its side incisions, gone on the groove pad
        assert default[near(x)].max() > 62.0
        assert groove[near(x)].max() < 60.5


def test_a_thread_on_the_groove_pad_spans_the_groove():
    xy = np.array([[0.0, y] for y in np.linspace(-0.025, 0.025, 11)])
    bridged = 1e3 * floor_height(xy, "groove")
    assert np.all(bridged > 0.0)  # on the lips' flanks, not down in the crease
    assert np.all(1e3 * floor_height(xy + np.array([0.02, 0.0]), "groove") < 0.26)  # flat elsewhere
