"""PyBulletDepthRenderer: exact depth and silhouettes against analytic and ray-cast references.

The reference for meshes is trimesh ray casting through every pixel centre (OpenCV
convention: pixel (u, v) is the ray through K⁻¹ [u, v, 1]), restricted to the bounding box
of the projected vertices. Helpers here are reused by ``test_pybullet_backend``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("pybullet")
trimesh = pytest.importorskip("trimesh")
pytest.importorskip("rtree")  # trimesh ray casting

from bopsurg.bop.meshes import ObjectModel  # noqa: E402
from bopsurg.generators.depth_renderer import (  # noqa: E402
    PyBulletDepthRenderer,
    model_key,
    quaternion_xyzw,
)
from bopsurg.needle import needle_mesh  # noqa: E402
from bopsurg.plugins import DepthRenderer, load_plugin  # noqa: E402

K_SIM = np.array([[350.807, 0.0, 320.0], [0.0, 350.807, 240.0], [0.0, 0.0, 1.0]])
#: Off-centre, non-square pixels.
K_ODD = np.array([[341.2, 0.0, 301.3], [0.0, 362.9, 262.7], [0.0, 0.0, 1.0]])
W, H = 640, 480

_MESHES: dict[int, tuple[ObjectModel, object]] = {}


def _trimesh(model: ObjectModel):
    """trimesh of a model, cached (the ray-casting structures are built once)."""
    hit = _MESHES.get(id(model))
    if hit is None or hit[0] is not model:
        hit = (model, trimesh.Trimesh(model.pts, model.faces, process=False))
        _MESHES[id(model)] = hit
    return hit[1]


#: Depth is compared where the surface is not seen edge-on: incidence under ~84°. Beyond,
#: z changes by tens of mm per pixel, so float32 rounding of a vertex by 1e-3 px moves the
#: depth of such a pixel by 0.1 mm in any renderer; those pixels are counted apart.
MIN_COS_INCIDENCE = 0.1


class Reference:
    """Exact depth (mm) through every pixel centre and the incidence cosine of each hit."""

    def __init__(self, depth: np.ndarray, cos: np.ndarray) -> None:
        self.depth = depth
        self.cos = cos

    @property
    def mask(self) -> np.ndarray:
        return self.depth > 0


def raycast(
    model: ObjectModel, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int
) -> Reference:
    """Ray-cast the model's nearest surface through every pixel centre.

    Args:
        model: Mesh, mm (all vertices in front of the camera).
        R, t: Pose ``x_cam = R x + t``, t in mm.
        K: Intrinsics.
        width, height: Canvas size.
    """
    mesh = _trimesh(model)
    P = model.pts @ R.T + t
    assert P[:, 2].min() > 0, "the reference needs the whole model in front of the camera"
    u = K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2]
    v = K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]
    u0, u1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, width)
    v0, v1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, height)
    depth, cos = np.zeros((height, width)), np.zeros((height, width))
    if u0 >= u1 or v0 >= v1:
        return Reference(depth, cos)
    uu, vv = np.meshgrid(np.arange(u0, u1), np.arange(v0, v1))
    uu, vv = uu.ravel(), vv.ravel()
    rays = np.linalg.solve(K, np.stack([uu, vv, np.ones_like(uu)]).astype(float)).T  # z = 1
    dirs = rays @ R  # in the model frame
    origin = -R.T @ t  # camera centre in the model frame
    # multiple_hits=False keeps the nearest hit of each ray.
    tri, ray_idx, locs = mesh.ray.intersects_id(
        np.repeat(origin[None], len(rays), axis=0),
        dirs,
        multiple_hits=False,
        return_locations=True,
    )
    depth[vv[ray_idx], uu[ray_idx]] = (locs @ R.T + t)[:, 2]
    unit = dirs[ray_idx] / np.linalg.norm(dirs[ray_idx], axis=1, keepdims=True)
    cos[vv[ray_idx], uu[ray_idx]] = np.abs((mesh.face_normals[tri] * unit).sum(axis=1))
    return Reference(depth, cos)


def raycast_depth(
    model: ObjectModel, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int
) -> np.ndarray:
    """Exact z-depth (mm) through every pixel centre, 0 = miss (see :func:`raycast`)."""
    return raycast(model, R, t, K, width, height).depth


def compare(depth: np.ndarray, ref: np.ndarray | Reference) -> tuple[float, float]:
    """(IoU of the silhouettes, max |depth error| mm on their intersection).

    With a :class:`Reference`, the depth error leaves out grazing pixels (incidence cosine
    below :data:`MIN_COS_INCIDENCE`).
    """
    ref_depth = ref.depth if isinstance(ref, Reference) else ref
    a, b = depth > 0, ref_depth > 0
    union = (a | b).sum()
    iou = (a & b).sum() / union if union else 1.0
    both = a & b
    if isinstance(ref, Reference):
        both &= ref.cos >= MIN_COS_INCIDENCE
    err = float(np.abs(depth - ref_depth)[both].max()) if both.any() else 0.0
    return float(iou), err


def random_pose(rng: np.random.Generator, z_range=(40.0, 100.0)) -> tuple[np.ndarray, np.ndarray]:
    """Random rotation and a translation (mm) keeping a needle inside a 640×480 view."""
    R = Rotation.random(random_state=rng).as_matrix()
    z = rng.uniform(*z_range)
    t = np.array([rng.uniform(-0.25, 0.25) * z, rng.uniform(-0.2, 0.2) * z, z])
    return R, t


@pytest.fixture(scope="module")
def renderer():
    with PyBulletDepthRenderer() as r:
        yield r


@pytest.fixture(scope="module")
def needle() -> ObjectModel:
    return needle_mesh()


def test_protocol_and_entry_point():
    assert isinstance(PyBulletDepthRenderer(), DepthRenderer)
    assert load_plugin("renderer", "pybullet") is PyBulletDepthRenderer


def _square(size: float) -> ObjectModel:
    """A flat square in the model XY plane, wound to face −z (away from a camera behind)."""
    h = size / 2
    pts = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    return ObjectModel(pts=pts, faces=np.array([[0, 2, 1], [0, 3, 2]]))


@pytest.mark.parametrize("K", [K_SIM, K_ODD], ids=["sim", "odd"])
def test_flat_square_analytic_depth_and_silhouette(renderer, K):
    """A tilted square: depth = ray/plane intersection, mask = pixel centres inside it.

    Its triangles face away from the camera, so this also checks that both windings render.
    """
    square = _square(20.0)
    R = Rotation.from_euler("xyz", [25.0, -15.0, 10.0], degrees=True).as_matrix()
    t = np.array([4.0, -3.0, 70.0])
    depth = renderer.render_depth(square, R, t, K, W, H)
    uu, vv = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.linalg.solve(K, np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])).T
    n = R[:, 2]  # plane normal in the camera frame; the plane passes through t
    s = (n @ t) / (rays @ n)  # ray parameter = z (rays have z = 1)
    local = (rays * s[:, None] - t) @ R  # hit points in the model frame
    inside = (np.abs(local[:, 0]) < 10.0) & (np.abs(local[:, 1]) < 10.0)
    ref = np.where(inside, s, 0.0).reshape(H, W)
    iou, err = compare(depth, ref)
    # Pixel centres within float rounding of an edge may go either way.
    assert ((depth > 0) ^ (ref > 0)).sum() <= 2
    assert iou > 0.999
    assert err < 1e-3  # mm


def test_cube_front_face_depth(renderer):
    """An axis-aligned 10 mm cube straight ahead: its front face at z = t_z − 5 mm."""
    box = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    cube = ObjectModel(pts=box.vertices, faces=box.faces)
    t = np.array([0.0, 0.0, 50.0])
    K = np.array([[500.0, 0, 320.0], [0, 500.0, 240.0], [0, 0, 1]])
    depth = renderer.render_depth(cube, np.eye(3), t, K, W, H)
    # The front face spans ±5 mm at z = 45 mm: u = 320 ± 500·5/45 = 320 ± 55.6 px.
    mask = depth > 0
    cols, rows = np.nonzero(mask.any(axis=0))[0], np.nonzero(mask.any(axis=1))[0]
    assert (cols.min(), cols.max()) == (265, 375)
    assert (rows.min(), rows.max()) == (185, 295)
    assert np.abs(depth[mask] - 45.0).max() < 1e-4


@pytest.mark.parametrize("K", [K_SIM, K_ODD], ids=["sim", "odd"])
def test_needle_matches_raycast(renderer, needle, K):
    rng = np.random.default_rng(7)
    for _ in range(4):
        R, t = random_pose(rng)
        depth = renderer.render_depth(needle, R, t, K, W, H)
        ref = raycast(needle, R, t, K, W, H)
        assert ref.mask.sum() > 50
        iou, err = compare(depth, ref)
        assert iou >= 0.98, (iou, t)
        assert err <= 0.1, (err, t)
        # Grazing pixels (left out of err) are rare; even there the error stays sub-mm.
        assert (ref.mask & (ref.cos < MIN_COS_INCIDENCE)).mean() < 0.02 * ref.mask.mean()
        assert compare(depth, ref.depth)[1] < 1.0


def test_three_times_canvas(renderer, needle):
    """BOP's 3× canvas: the centre equals the 1× render; truncated parts are counted."""
    R = Rotation.from_euler("xyz", [80.0, 10.0, 30.0], degrees=True).as_matrix()
    t = np.array([-52.0, 10.0, 50.0])  # the needle sticks out of the image on the left
    small = renderer.render_depth(needle, R, t, K_SIM, W, H)
    K3 = K_SIM.copy()
    K3[:2, 2] += (W, H)
    big = renderer.render_depth(needle, R, t, K3, 3 * W, 3 * H)
    centre = big[H : 2 * H, W : 2 * W]
    assert ((centre > 0) ^ (small > 0)).sum() <= 2
    both = (centre > 0) & (small > 0)
    assert np.abs(centre - small)[both].max() < 1e-4  # mm; float32 rounding differs
    assert (big > 0).sum() > (small > 0).sum() + 50  # truncated pixels exist
    ref = raycast(needle, R, t, K3, 3 * W, 3 * H)
    iou, err = compare(big, ref)
    assert iou >= 0.98
    assert err <= 0.1


def test_cache_and_switching(needle):
    with PyBulletDepthRenderer() as r:
        R, t = np.eye(3), np.array([0.0, 0.0, 60.0])
        a = r.render_depth(needle, R, t, K_SIM, W, H)
        twin = ObjectModel(pts=needle.pts.copy(), faces=needle.faces.copy())
        assert model_key(twin) == model_key(needle)
        b = r.render_depth(twin, R, t, K_SIM, W, H)
        assert r.cached_models == 1
        np.testing.assert_array_equal(a, b)
        square = _square(5.0)
        c = r.render_depth(square, R, np.array([0.0, 0.0, 40.0]), K_SIM, W, H)
        assert r.cached_models == 2
        # Only the requested model is drawn: the needle is hidden again.
        ref = raycast_depth(square, R, np.array([0.0, 0.0, 40.0]), K_SIM, W, H)
        assert compare(c, ref)[0] > 0.99
        np.testing.assert_array_equal(r.render_depth(needle, R, t, K_SIM, W, H), a)


def test_edge_cases(renderer, needle):
    R = np.eye(3)
    behind = renderer.render_depth(needle, R, np.array([0.0, 0.0, -50.0]), K_SIM, W, H)
    assert not behind.any()
    aside = renderer.render_depth(needle, R, np.array([500.0, 0.0, 50.0]), K_SIM, W, H)
    assert not aside.any()
    # Straddling the camera plane: rendered (near-clipped) without error.
    close = renderer.render_depth(needle, R, np.array([0.0, 0.0, 2.0]), K_SIM, W, H)
    assert close.shape == (H, W)
    assert close.min() >= 0
    cloud = ObjectModel(pts=needle.pts, faces=np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="point cloud"):
        renderer.render_depth(cloud, R, np.array([0.0, 0.0, 50.0]), K_SIM, W, H)


def test_window_render_is_the_whole_render_cut(renderer, needle):
    R = Rotation.from_euler("xyz", [0.3, -0.4, 1.1]).as_matrix()
    t = np.array([4.0, -3.0, 70.0])
    whole = renderer.render_depth(needle, R, t, K_ODD, W, H)
    depth, (r0, c0) = renderer.render_depth_window(needle, R, t, K_ODD, W, H)
    assert depth.shape[0] * depth.shape[1] < W * H / 10
    pasted = np.zeros((H, W))
    pasted[r0 : r0 + depth.shape[0], c0 : c0 + depth.shape[1]] = depth
    np.testing.assert_array_equal(pasted, whole)
    assert renderer.render_depth_window(needle, R, np.array([0.0, 0.0, -50.0]), K_SIM, W, H) is None


def test_quaternions_are_scipys_bit_for_bit():
    """The poses pybullet gets are those it got through scipy (the renders do not change)."""
    Rs = Rotation.random(3000, random_state=4).as_matrix()
    axes = [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0])]
    noisy = Rs[:5] + 1e-9 * np.random.default_rng(1).standard_normal((5, 3, 3))  # scipy's SVD
    for R in [*Rs, *axes, *noisy]:
        want = Rotation.from_matrix(R).as_quat()
        np.testing.assert_array_equal(np.array(quaternion_xyzw(R)), want)
    with pytest.raises(ValueError, match="determinant"):
        quaternion_xyzw(np.diag([1.0, 1.0, -1.0]))


@pytest.mark.slow
def test_large_mesh_beyond_array_limit():
    """Meshes over pybullet's in-memory vertex limit (~130k) still upload (via OBJ files)."""
    sphere = trimesh.creation.icosphere(subdivisions=7, radius=10.0)  # 163,842 vertices
    model = ObjectModel(pts=sphere.vertices, faces=sphere.faces)
    with PyBulletDepthRenderer() as r:
        depth = r.render_depth(model, np.eye(3), np.array([0.0, 0.0, 80.0]), K_SIM, W, H)
    # Sphere: z at the image centre = 80 − 10 mm; silhouette radius ≈ f·r/√(d²−r²).
    assert depth[240, 320] == pytest.approx(70.0, abs=1e-3)
    radius_px = 350.807 * 10.0 / np.sqrt(80.0**2 - 10.0**2)
    assert (depth > 0).sum() == pytest.approx(np.pi * radius_px**2, rel=0.01)
