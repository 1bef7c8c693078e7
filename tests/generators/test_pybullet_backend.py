"""PyBulletBackend and its procedural scene: geometry accuracy, masks, FK placement, API.

Accuracy is measured against exact references: the needle (and instrument parts) ray-cast
with trimesh through every pixel centre, at the object's GT pose from ``object_pose`` and the
camera pose (``T_cam_obj = inv(T_world_cam) @ T_world_obj``, converted to mm). Depth errors
leave out grazing pixels (surface seen within ~6° of edge-on), where any rasteriser's float32
vertex rounding moves z by a lot; see ``test_depth_renderer.MIN_COS_INCIDENCE``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("pybullet")
pytest.importorskip("trimesh")
pytest.importorskip("rtree")

from bopsurg.bop.meshes import ObjectModel
from bopsurg.generators import pybullet_scene as ps
from bopsurg.generators.backend import (
    DEFAULT_ECM_JOINTS,
    CameraSpec,
    LightSpec,
    RenderBackend,
    SceneSpec,
    SceneState,
    default_state,
)
from bopsurg.generators.kinematics import (
    DEFAULT_LAYOUT,
    ecm_camera_pose,
    look_rotation,
    pose,
    psm_link_frames,
    psm_tip_pose,
    rot_z,
)
from bopsurg.generators.pybullet_backend import (
    OPTION_KEYS,
    PyBulletBackend,
    PyBulletOptions,
    depth_buffer_to_mm,
    render_window,
)
from bopsurg.needle import NeedleSpec
from bopsurg.plugins import load_plugin

from .test_depth_renderer import K_ODD, K_SIM, H, W, compare, raycast

#: Instruments retracted out of the way (tips ~2 cm behind their RCMs).
RETRACTED = {"psm1": np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0]), "psm2": np.zeros(6)}
#: Both tool tips in the default ECM view, wrists bent, psm1 closed, psm2 open.
IN_VIEW = {
    "psm1": np.array([0.10, -0.05, 0.120, 0.3, 0.2, -0.2]),
    "psm2": np.array([-0.10, 0.05, 0.125, -0.2, -0.3, 0.25]),
}
JAWS = {"psm1": 0.0, "psm2": 0.6}
#: Both tools straight above the pad's centre, 12 cm inserted.
ABOVE_PAD = {arm: np.array([0.0, 0.0, 0.12, 0.0, 0.0, 0.0]) for arm in ("psm1", "psm2")}


def state(needle: np.ndarray, joints: dict[str, np.ndarray] | None = None, jaws=None) -> SceneState:
    return SceneState(
        psm_joints=RETRACTED if joints is None else joints,
        jaws={"psm1": 0.0, "psm2": 0.0} if jaws is None else jaws,
        ecm_joints=np.zeros(4),
        needle_pose=needle,
    )


def look_at(eye, target, roll: float = 0.0) -> np.ndarray:
    """T_world_cam (OpenCV axes) at ``eye`` looking at ``target``, rolled by ``roll`` rad."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    return pose(look_rotation(target - eye) @ rot_z(roll), eye)


def camera(T_world_cam, K=K_SIM, width=W, height=H) -> CameraSpec:
    return CameraSpec(K=K, width=width, height=height, T_world_cam=T_world_cam)


def reference(backend: PyBulletBackend, cam: CameraSpec, name: str = "needle"):
    """Ray-cast depth (mm) of an object's BOP model at its GT pose (object_pose, camera)."""
    T = np.linalg.inv(cam.T_world_cam) @ backend.object_pose(name)
    return raycast(
        backend.object_model(name), T[:3, :3], 1e3 * T[:3, 3], cam.K, cam.width, cam.height
    )


@pytest.fixture(scope="module")
def scene():
    with PyBulletBackend() as backend:
        backend.load_scene(SceneSpec(annotate_instruments=True))
        yield backend


# ------------------------------------------------------------------------- API


def test_protocol_entry_point_and_objects(scene):
    assert isinstance(scene, RenderBackend)
    assert load_plugin("backend", "pybullet") is PyBulletBackend
    names = [n for n, _ in scene.annotated_objects()]
    assert names == [
        "needle",
        "psm1_wrist",
        "psm1_jaw1",
        "psm1_jaw2",
        "psm2_wrist",
        "psm2_jaw1",
        "psm2_jaw2",
    ]
    assert [i for _, i in scene.annotated_objects()] == list(range(1, 8))
    needle = scene.object_model("needle")
    assert isinstance(needle, ObjectModel)
    # mm: the default needle's centre-line radius is 10.18 mm.
    assert np.linalg.norm(needle.pts[:, :2], axis=1).max() == pytest.approx(
        10.18 + 0.36 * 1.15, abs=0.05
    )
    assert np.ptp(scene.object_model("psm1_wrist").pts, axis=0) == pytest.approx(ps.WRIST_SIZE)
    with pytest.raises(KeyError):
        scene.object_model("scalpel")
    with pytest.raises(KeyError):
        scene.render_object_depth("phantom", camera(ecm_camera_pose(np.zeros(4))))


def test_config_and_lifecycle():
    with pytest.raises(ValueError, match="'colour'"):
        PyBulletBackend({"colour": "red"})
    with pytest.raises(ValueError, match="renderer"):
        PyBulletBackend({"renderer": "cycles"})
    with pytest.raises(ValueError, match="texture_seed"):
        PyBulletBackend({"texture_seed": "three"})
    with pytest.raises(ValueError, match="light_distance"):
        PyBulletBackend({"light_distance": "-1"})
    assert PyBulletBackend({"texture_seed": "3", "light_distance": "0.25"}).options == (
        PyBulletOptions(renderer="tiny", texture_seed=3, light_distance=0.25)
    )
    with PyBulletBackend({"texture_seed": 3}) as backend:
        with pytest.raises(RuntimeError, match="load_scene"):
            backend.annotated_objects()
        backend.load_scene(SceneSpec(needle=NeedleSpec(arc_radius=12.0)))
        assert backend.annotated_objects() == [("needle", 1)]
        radius = np.linalg.norm(backend.object_model("needle").pts[:, :2], axis=1)
        assert radius.max() == pytest.approx(12.0 + 0.36 * 1.15, abs=0.05)
        with pytest.raises(ValueError, match="arm"):
            backend.set_state(state(np.eye(4), {"psm3": np.zeros(6)}))
    backend.close()  # idempotent
    with pytest.raises(RuntimeError):
        backend.render(camera(np.eye(4)), LightSpec())
    assert set(OPTION_KEYS) == {"renderer", "texture_seed", "light_distance"}


def test_default_scene_is_the_default_state(scene):
    """Before any set_state, the scene shows default_state(): the same pixels as after it."""
    with PyBulletBackend() as fresh:
        fresh.load_scene(SceneSpec(annotate_instruments=True))
        cam = camera(ecm_camera_pose(DEFAULT_ECM_JOINTS))
        before = fresh.render(cam, LightSpec())
        fresh.set_state(default_state())
        after = fresh.render(cam, LightSpec())
    np.testing.assert_array_equal(before.instance, after.instance)
    np.testing.assert_array_equal(before.depth, after.depth)
    assert (before.instance == 1).sum() > 50  # the needle lies in view


def test_default_ecm_view_shows_everything(scene):
    """The default ECM view of tools in reach shows tissue, needle and both tools."""
    with PyBulletBackend() as fresh:
        fresh.load_scene(SceneSpec(annotate_instruments=True))
        jaws = {"psm1": 0.3, "psm2": 0.3}
        fresh.set_state(state(pose(np.eye(3), [0.0, 0.0, 0.004]), ABOVE_PAD, jaws))
        frame = fresh.render(camera(ecm_camera_pose(np.zeros(4))), LightSpec())
    assert frame.rgb.shape == (H, W, 3)
    assert frame.rgb.dtype == np.uint8
    assert frame.depth.dtype == np.float64
    assert frame.instance.dtype == np.int32
    counts = np.bincount(frame.instance.ravel(), minlength=8)
    assert (counts[1:] > 50).all(), counts
    # Depth everywhere (tissue and drape fill the view), tissue 40-170 mm away.
    assert (frame.depth > 0).all()
    assert 20.0 < np.median(frame.depth) < 170.0


# -------------------------------------------------------------------- accuracy

CAMERAS = [
    # K, distance (mm), elevation of the view (deg from vertical), azimuth, roll (deg)
    pytest.param(K_SIM, 40.0, 20.0, 30.0, 0.0, id="sim-40mm"),
    pytest.param(K_SIM, 60.0, 40.0, -70.0, 35.0, id="sim-60mm-tilted-rolled"),
    pytest.param(K_SIM, 100.0, 15.0, 160.0, -60.0, id="sim-100mm-rolled"),
    pytest.param(K_ODD, 55.0, 30.0, 100.0, 20.0, id="odd-K-55mm"),
]


@pytest.mark.parametrize(("K", "dist", "tilt", "azim", "roll"), CAMERAS)
def test_needle_mask_and_depth_match_raycast(scene, K, dist, tilt, azim, roll):
    """(a) IoU ≥ 0.98 with the exact silhouette, (b) depth ≤ 0.1 mm (surfaces not seen
    edge-on, see ``MIN_COS_INCIDENCE``), (c) the instance mask equals the object-alone mask."""
    rng = np.random.default_rng(int(dist))
    centre = np.array([0.004, -0.003, 0.020])  # 20 mm above the pad: nothing occludes it
    needle = pose(Rotation.random(random_state=rng).as_matrix(), centre)
    scene.set_state(state(needle))
    t, a = np.deg2rad(tilt), np.deg2rad(azim)
    eye = centre + 1e-3 * dist * np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
    cam = camera(look_at(eye, centre, np.deg2rad(roll)), K)
    frame = scene.render(cam, LightSpec())
    ref = reference(scene, cam)
    visible = np.where(frame.instance == 1, frame.depth, 0.0)
    iou, err = compare(visible, ref)
    assert iou >= 0.98, iou
    assert err <= 0.1, err
    solo = scene.render_object_depth("needle", cam)
    iou_solo, err_solo = compare(solo, ref)
    assert iou_solo >= 0.98
    assert err_solo <= 0.1
    np.testing.assert_array_equal(frame.instance == 1, solo > 0)
    # Same geometry, different render windows: float32 rounding differs by < 1 µm.
    np.testing.assert_allclose(visible, solo, atol=1e-3)


def test_occlusion_by_tissue_is_consistent(scene):
    """A needle half sunk into the pad: visible ⊂ alone; hidden pixels are behind tissue."""
    # The arc tilts down into the pad: its tail sticks out 2 mm, its middle dives 1.5 mm deep.
    needle = pose(Rotation.from_euler("x", -20.0, degrees=True).as_matrix(), [0.01, 0.0, 0.002])
    scene.set_state(state(needle))
    cam = camera(look_at([0.01, -0.03, 0.03], [0.01, 0.0, 0.0], 0.2))
    frame = scene.render(cam, LightSpec())
    alone = scene.render_object_depth("needle", cam)
    visible = frame.instance == 1
    hidden = (alone > 0) & ~visible
    assert visible.sum() > 100
    assert hidden.sum() > 100
    assert not (visible & ~(alone > 0)).any()
    assert np.abs(frame.depth - alone)[visible].max() < 1e-3
    assert (frame.depth[hidden] < alone[hidden]).all()
    # The object-alone render still has the exact (unoccluded) silhouette.
    ref = reference(scene, cam)
    assert compare(alone, ref)[0] >= 0.98


def test_three_times_canvas_counts_truncation(scene):
    needle = pose(np.eye(3), [0.0, 0.0, 0.02])
    scene.set_state(state(needle))
    cam = camera(look_at([0.045, -0.01, 0.07], [0.045, 0.0, 0.0]))  # needle cut at the left
    K3 = K_SIM.copy()
    K3[:2, 2] += (W, H)
    big_cam = camera(cam.T_world_cam, K3, 3 * W, 3 * H)
    small = scene.render_object_depth("needle", cam)
    big = scene.render_object_depth("needle", big_cam)
    centre = big[H : 2 * H, W : 2 * W]
    assert ((centre > 0) ^ (small > 0)).sum() <= 2
    assert (big > 0).sum() > (small > 0).sum() + 100
    assert compare(big, reference(scene, big_cam))[0] >= 0.98
    frame = scene.render(cam, LightSpec())
    assert ((frame.instance == 1) ^ (small > 0)).sum() <= 2


def test_set_state_moves_the_needle(scene):
    T_wc = look_at([0.0, -0.04, 0.07], [0.0, 0.0, 0.01])
    cam = camera(T_wc)
    before = pose(Rotation.from_euler("y", 30.0, degrees=True).as_matrix(), [0.0, 0.0, 0.012])
    scene.set_state(state(before))
    m0 = scene.render(cam, LightSpec()).instance == 1
    shift = 0.004 * T_wc[:3, 0]  # 4 mm along the camera's x axis
    after = before.copy()
    after[:3, 3] += shift
    scene.set_state(state(after))
    np.testing.assert_allclose(scene.object_pose("needle"), after)
    frame = scene.render(cam, LightSpec())
    m1 = frame.instance == 1
    assert compare(np.where(m1, frame.depth, 0), reference(scene, cam))[0] >= 0.98
    depth = (np.linalg.inv(T_wc) @ after)[2, 3]
    du = np.nonzero(m1)[1].mean() - np.nonzero(m0)[1].mean()
    assert du == pytest.approx(K_SIM[0, 0] * 0.004 / depth, abs=1.0)


# ----------------------------------------------------------------- instruments


def test_instruments_appear_where_fk_says(scene):
    scene.set_state(state(pose(np.eye(3), [0.0, 0.02, 0.002]), IN_VIEW, JAWS))
    cam = camera(ecm_camera_pose(np.zeros(4)))
    frame = scene.render(cam, LightSpec())
    T_cw = np.linalg.inv(cam.T_world_cam)

    def project(p_world):
        p = T_cw[:3, :3] @ p_world + T_cw[:3, 3]
        return np.array(
            [K_SIM[0, 0] * p[0] / p[2] + K_SIM[0, 2], K_SIM[1, 1] * p[1] / p[2] + K_SIM[1, 2]]
        )

    def near_mask(uv, mask, radius=1.5):
        rows, cols = np.nonzero(mask)
        return np.hypot(cols - uv[0], rows - uv[1]).min() <= radius

    for i, arm in enumerate(("psm1", "psm2")):
        # Independent FK: layout base × tip frame from the kinematics module.
        tip = DEFAULT_LAYOUT.psm_base(i) @ psm_tip_pose(IN_VIEW[arm])
        parts = {
            p: scene.render_object_depth(f"{arm}_{p}", cam) > 0 for p in ("wrist", "jaw1", "jaw2")
        }
        assert all(m.sum() > 50 for m in parts.values()), arm
        wrist_or_jaws = parts["wrist"] | parts["jaw1"] | parts["jaw2"]
        assert near_mask(project(tip[:3, 3]), wrist_or_jaws), arm
        # Mid-jaw point, 5 mm along the tip z axis.
        mid = project((tip @ np.array([0.0, 0.0, 0.005, 1.0]))[:3])
        if JAWS[arm] == 0.0:
            assert near_mask(mid, parts["jaw1"] | parts["jaw2"]), arm
        # The jaws open symmetrically about tip z, by the jaw angle, about the tip x axis.
        z1 = scene.object_pose(f"{arm}_jaw1")[:3, 2]
        z2 = scene.object_pose(f"{arm}_jaw2")[:3, 2]
        assert np.arctan2(np.linalg.norm(np.cross(z1, z2)), z1 @ z2) == pytest.approx(
            JAWS[arm], abs=1e-9
        )
        bisector = (z1 + z2) / np.linalg.norm(z1 + z2)
        np.testing.assert_allclose(bisector, tip[:3, 2], atol=1e-9)
        np.testing.assert_allclose(np.cross(z1, z2) @ tip[:3, 0], np.sin(JAWS[arm]), atol=1e-9)
        # Visible instrument pixels are a subset of each part's own silhouette.
        for name, obj_id in scene.annotated_objects():
            if name.startswith(arm):
                assert not ((frame.instance == obj_id) & ~parts[name.split("_")[1]]).any()
    # psm1 works on the +x side of the image, psm2 on the -x side (the camera looks along +y).
    assert (
        np.nonzero(frame.instance == 2)[1].mean()
        > W / 2
        > np.nonzero(frame.instance == 5)[1].mean()
    )


def test_jaw_model_matches_raycast(scene):
    """Instrument parts: the BOP model at object_pose lands on the rendered silhouette."""
    scene.set_state(state(pose(np.eye(3), [0.0, 0.02, 0.002]), IN_VIEW, JAWS))
    tip = scene.object_pose("psm2_jaw1")[:3, 3]
    cam = camera(look_at(tip + np.array([0.01, -0.03, 0.02]), tip, 0.3))
    for name in ("psm2_jaw1", "psm2_wrist"):
        alone = scene.render_object_depth(name, cam)
        iou, err = compare(alone, reference(scene, cam, name))
        assert iou >= 0.98, (name, iou)
        assert err <= 0.1, (name, err)


def test_shaft_axis_passes_through_the_rcm(scene):
    for i, arm in enumerate(ps.ARMS):
        q = IN_VIEW[arm]
        shaft = ps.instrument_part_poses(q, 0.0, DEFAULT_LAYOUT.psm_base(i))["shaft"]
        rcm = np.asarray(DEFAULT_LAYOUT.psm_rcm[i])
        d = rcm - shaft[:3, 3]
        off_axis = d - (d @ shaft[:3, 2]) * shaft[:3, 2]
        assert np.linalg.norm(off_axis) < 1e-9
        assert d @ shaft[:3, 2] < 0  # the RCM is behind the shaft's distal end
        np.testing.assert_allclose(shaft, DEFAULT_LAYOUT.psm_base(i) @ psm_link_frames(q)[3])


# ------------------------------------------------------------------- rendering


def test_lighting_changes_colour_only(scene):
    scene.set_state(state(pose(np.eye(3), [0.0, 0.0, 0.004]), IN_VIEW, JAWS))
    cam = camera(ecm_camera_pose(np.array([0.1, -0.05, 0.0, 0.2])))
    a = scene.render(cam, LightSpec())
    b = scene.render(
        cam,
        LightSpec(
            direction=np.array([1.0, 0.3, 0.5]),
            color=np.array([1.0, 0.8, 0.7]),
            ambient=0.3,
            diffuse=0.8,
            specular=0.6,
            shadows=True,
        ),
    )
    assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).mean() > 5
    np.testing.assert_array_equal(a.instance, b.instance)
    np.testing.assert_array_equal(a.depth, b.depth)
    # The tissue is pink-red: red dominates on the pad's pixels.
    pad = (a.instance == 0) & (a.depth < 100.0)
    red_minus_green = a.rgb[pad][:, 0].astype(int) - a.rgb[pad][:, 1]
    assert np.median(red_minus_green) > 30
    # LightSpec.direction points towards the light: the pad's top is lit from above.
    above = scene.render(cam, LightSpec(direction=np.array([0.0, 0.0, 1.0]), ambient=0.3))
    below = scene.render(cam, LightSpec(direction=np.array([0.0, 0.0, -1.0]), ambient=0.3))
    assert above.rgb[pad].mean() > below.rgb[pad].mean() + 20


def test_two_backends_are_independent(scene):
    cam = camera(look_at([0.0, -0.03, 0.08], [0.0, 0.0, 0.0]))
    scene.set_state(state(pose(np.eye(3), [0.01, 0.0, 0.01])))
    with PyBulletBackend() as other:
        other.load_scene(SceneSpec())
        other.set_state(state(pose(np.eye(3), [-0.01, 0.0, 0.01])))
        mine = scene.render(cam, LightSpec()).instance == 1
        theirs = other.render(cam, LightSpec()).instance == 1
        assert mine.sum() > 100
        assert theirs.sum() > 100
        assert not (mine & theirs).any()
    assert (scene.render(cam, LightSpec()).instance == 1).sum() == mine.sum()


def test_egl_renderer(capfd):
    """The EGL plugin (if it loads): same geometry within µm, and stdout stays clean."""
    backend = PyBulletBackend({"renderer": "egl"})
    try:
        backend.load_scene(SceneSpec())
    except RuntimeError as err:
        pytest.skip(f"EGL not available: {err}")
    try:
        needle = pose(
            Rotation.from_euler("xz", [40.0, 20.0], degrees=True).as_matrix(), [0.0, 0.0, 0.02]
        )
        backend.set_state(state(needle))
        cam = camera(look_at([0.01, -0.04, 0.07], [0.0, 0.0, 0.02], 0.4), K_ODD)
        frame = backend.render(cam, LightSpec())
        ref = reference(backend, cam)
        iou, err = compare(np.where(frame.instance == 1, frame.depth, 0.0), ref)
        assert iou >= 0.98, iou
        assert err <= 0.1, err
        alone = backend.render_object_depth("needle", cam)  # TinyRenderer solo client
        assert ((alone > 0) ^ (frame.instance == 1)).sum() <= 0.02 * ref.mask.sum() + 2
        # pybullet's EGL plugin holds one scene per process: a second user is refused.
        with (
            PyBulletBackend({"renderer": "egl"}) as other,
            pytest.raises(RuntimeError, match="EGL"),
        ):
            other.load_scene(SceneSpec())
        backend.load_scene(SceneSpec())  # reloading its own scene is fine
        assert (backend.render(cam, LightSpec()).instance == 1).sum() > 0
    finally:
        backend.close()
    with PyBulletBackend({"renderer": "egl"}) as after:  # free again once closed
        after.load_scene(SceneSpec())
    assert capfd.readouterr().out == ""


# --------------------------------------------------------------------- helpers


def test_depth_buffer_and_window_helpers():
    d = np.array([[0.0, 0.5, 1.0 - 6e-8]], dtype=np.float32)
    z = depth_buffer_to_mm(d, 0.01, 1.0)
    assert z[0, 0] == pytest.approx(10.0)
    assert z[0, 1] == pytest.approx(1000.0 * 0.01 / (1.0 - 0.99 * 0.5))
    assert z[0, 2] == 0.0  # TinyRenderer's cleared buffer reads 1 - 6e-8
    seg = np.array([[3, -1, 3]])
    assert depth_buffer_to_mm(d, 0.01, 1.0, seg)[0, 1] == 0.0
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.01, 0.0]])
    T = pose(np.eye(3), [0.0, 0.0, 0.1])
    # Projections: (320, 240) and (355.08, 275.08); one pixel of margin, end exclusive.
    assert render_window(pts, T, K_SIM, W, H, 0.005) == (319, 239, 358, 278)
    T[2, 3] = 0.001  # in front of the near plane: the whole canvas
    assert render_window(pts, T, K_SIM, W, H, 0.005) == (0, 0, W, H)
    T[:3, 3] = [5.0, 0.0, 0.1]  # off to the side
    assert render_window(pts, T, K_SIM, W, H, 0.005) is None


def test_scene_assets():
    assets = ps.build_scene(annotate_instruments=False, texture_seed=1)
    assert assets.annotated == ("needle",)
    names = set(assets.parts)
    assert {"needle", "phantom", "drape"} <= names
    assert {f"{a}_{p}" for a in ps.ARMS for p in ps.INSTRUMENT_PARTS} <= names
    # Closed instrument meshes, wound outwards (positive volume once vertices are merged).
    import trimesh

    for part, model in ps.instrument_models().items():
        mesh = trimesh.Trimesh(model.pts, model.faces)
        assert mesh.is_watertight, part
        assert mesh.volume > 0, part
    # Pad: top at z = 0 around ridges and incisions, ridges 2.5 mm high, incisions 3 mm deep.
    assert abs(ps.pad_height(10.0, 0.0)) <= 0.25
    assert ps.pad_height(10.0, ps.RIDGES_Y[0]) == pytest.approx(ps.RIDGE_HEIGHT, abs=0.25)
    assert ps.pad_height(ps.INCISIONS_X[1], 0.0) == pytest.approx(-ps.INCISION_DEPTH, abs=0.25)
    pad, uvs = ps.pad_mesh()
    assert pad.pts[:, 2].min() == -ps.PAD_THICKNESS
    assert uvs.min() >= 0.0
    assert uvs.max() < 1.0
    for key, tex in assets.textures.items():
        assert tex.dtype == np.uint8, key
        assert tex.shape[2:] == (3,), key
    np.testing.assert_array_equal(ps.skin_texture(1), assets.textures["skin"])
    assert (ps.skin_texture(2) != assets.textures["skin"]).any()
    with pytest.raises(ValueError, match="arm"):
        ps.part_poses(DEFAULT_LAYOUT, {"ecm": np.zeros(6)}, {})
