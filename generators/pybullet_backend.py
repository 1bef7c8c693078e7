"""PyBullet rendering backend: headless RGB, metric depth and instance maps of the scene.

:class:`PyBulletBackend` implements :class:`~bopsurg.generators.backend.RenderBackend` with
pybullet's software TinyRenderer (default, exact) or its EGL plugin (optional). The scene is
built by :mod:`bopsurg.generators.pybullet_scene`: every part (needle, instrument parts,
phantom, drape) is a separate base-only multibody whose pose is set from forward kinematics
in :meth:`PyBulletBackend.set_state`, so there is no URDF (no mimic-joint or joint-order
quirks).

Pixel convention: OpenCV intrinsics ``K`` (pixel centres at integer coordinates). TinyRenderer
samples pixels at integer window coordinates and flips rows, so its projection uses the
principal point ``(cx, cy + 1)``; the EGL plugin is real OpenGL and uses ``(cx + 0.5,
cy + 0.5)`` (see ``libraries.md`` §2). Depth is camera-frame z (not range) in mm, 0 where
nothing was hit.

Object-alone renders (:meth:`PyBulletBackend.render_object_depth`) use a second pybullet
client holding only the annotated objects, all hidden (alpha 0, which TinyRenderer skips at
no cost) except the one rendered, and only the pixel window that the object's projection can
cover is rendered, so BOP's 3×-canvas renders cost about as much as the object's pixels
(1-3 ms). That client always uses TinyRenderer, also with ``renderer="egl"``: an EGL call
costs ~10 ms whatever its size, and both renderers sample exact pixel centres, so their
silhouettes differ only where a pixel centre lies within float rounding of an edge (a few
pixels per frame, if any). With TinyRenderer, ``render``'s instance map equals the
object-alone mask wherever nothing occludes the object.

Lighting: :class:`~bopsurg.generators.backend.LightSpec` maps to ``getCameraImage``'s
``lightDirection`` (towards the light, world frame), ``lightColor`` and the ambient, diffuse
and specular coefficients. ``shadows`` switches TinyRenderer's shadow map on; it is computed
from a light ``light_distance`` away looking at the world origin, with a depth bias too large
for mm-scale casters, so it mostly dims the image slightly rather than drawing tool shadows.

Options (``bopsurg generate --backend-option KEY=VALUE``, see :data:`OPTION_KEYS`): the
``renderer``, the ``texture_seed`` of the procedural textures and the shadow light's
``light_distance``; the scene itself comes as a backend-independent
:class:`~bopsurg.generators.backend.SceneSpec`.

Speed: build the scene once (:meth:`~PyBulletBackend.load_scene`), then only poses change;
nothing is re-uploaded per frame.

Stdout: pybullet prints ``pybullet build time`` to stderr on import (harmless). The EGL plugin
prints GL information to **stdout** through C stdio when it is loaded and unloaded; this
module sends those writes to stderr (file descriptor 1 is pointed at 2 around the calls), so
stdout stays clean for CLI output.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import logging
import os
import sys
import tempfile
import weakref
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import pybullet as p
from numpy.typing import NDArray

from bopsurg.bop.meshes import ObjectModel
from bopsurg.generators.backend import (
    ARMS,
    NEEDLE,
    CameraSpec,
    LightSpec,
    RenderedFrame,
    SceneSpec,
    SceneState,
    default_state,
)
from bopsurg.generators.pybullet_render import (
    PIXEL_OFFSETS,
    ClosesOnExit,
    WindowRender,
    depth_buffer_to_mm,
    projection_matrix,
    render_in_window,
    render_window,
    render_window_depth,
    view_matrix,
    write_obj,
)
from bopsurg.generators.pybullet_scene import (
    SceneAssets,
    VisualPart,
    build_scene,
    part_poses,
)
from bopsurg.metrics.point_subsets import hull_vertices

if TYPE_CHECKING:  # typing.Self is Python 3.11+; annotations are not evaluated at run time
    from bopsurg.generators.domain import Appearance
    from bopsurg.generators.pybullet_domain import ThreadBodies

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Recognised options of :class:`PyBulletBackend` (``--backend-option KEY=VALUE``).
OPTION_KEYS = ("renderer", "texture_seed", "light_distance")
#: Renderers: pybullet's software TinyRenderer, or the EGL plugin (OpenGL, Mesa llvmpipe
#: without a GPU).
RENDERERS = ("tiny", "egl")

# The EGL plugin keeps one renderer per process, shared by every client that loads it:
# two EGL scenes would draw into each other, and unloading one crashes the other. So at most
# one live backend per process may use it.
_egl_owner: weakref.ref[PyBulletBackend] | None = None


@contextlib.contextmanager
def stdout_to_stderr() -> Iterator[None]:
    """Send writes to file descriptor 1 to 2 (C libraries that print, like the EGL plugin)."""
    if sys.stdout is not None:
        sys.stdout.flush()
    libc = ctypes.CDLL(None)
    libc.fflush(None)
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        libc.fflush(None)  # C stdio buffers what it printed; flush it while 1 is still stderr
        os.dup2(saved, 1)
        os.close(saved)


def load_egl(client: int) -> int:
    """Load pybullet's EGL renderer plugin into a client (before any body is created).

    Returns:
        The plugin id.

    Raises:
        RuntimeError: The plugin is missing or fails to load (no EGL library).
    """
    spec = importlib.util.find_spec("eglRenderer")
    if spec is None or spec.origin is None:
        raise RuntimeError("pybullet's eglRenderer plugin is not installed")
    with stdout_to_stderr():
        plugin = p.loadPlugin(spec.origin, "_eglRendererPlugin", physicsClientId=client)
    if plugin < 0:
        raise RuntimeError("pybullet's EGL renderer plugin failed to load")
    return int(plugin)


def upload_part(client: int, part: VisualPart, folder: Path, texture: int | None = None) -> int:
    """Create a base-only multibody (no collision, no mass) showing one part, m.

    Args:
        client: pybullet client.
        part: The part (mesh in mm).
        folder: Where to write the part's OBJ file (read at once; may be deleted afterwards).
        texture: pybullet texture id for a textured part.

    Returns:
        The body's unique id.
    """
    path = folder / f"{part.name}.obj"
    if not path.exists():
        write_obj(path, part.model, part.uvs, double_sided=part.double_sided)
    shape = p.createVisualShape(
        p.GEOM_MESH,
        fileName=str(path),
        rgbaColor=list(part.rgba),
        specularColor=list(part.specular),
        physicsClientId=client,
    )
    if shape < 0:
        raise RuntimeError(f"pybullet could not create the visual shape of {part.name!r}")
    body = p.createMultiBody(baseMass=0.0, baseVisualShapeIndex=shape, physicsClientId=client)
    if texture is not None:
        p.changeVisualShape(body, -1, textureUniqueId=texture, physicsClientId=client)
    return int(body)


def _quaternions(poses: list[F64]) -> NDArray[np.float64]:
    """(N, 4) xyzw quaternions of 4×4 poses (one scipy call for all)."""
    from scipy.spatial.transform import Rotation  # here: the depth renderer needs no scipy

    quats: NDArray[np.float64] = Rotation.from_matrix(
        np.stack([T[:3, :3] for T in poses])
    ).as_quat()
    return quats


@dataclass(frozen=True)
class PyBulletOptions:
    """Options of :class:`PyBulletBackend`.

    Attributes:
        renderer: ``"tiny"`` (TinyRenderer, exact) or ``"egl"`` (faster; depth quantised to
            µm; one EGL backend per process at a time).
        texture_seed: Seed of the procedural textures.
        light_distance: Distance of the shadow-casting light from the world origin, m
            (TinyRenderer's shadow map looks at the origin).
    """

    renderer: str = "tiny"
    texture_seed: int = 0
    light_distance: float = 0.3


def parse_options(options: Mapping[str, Any]) -> PyBulletOptions:
    """Check backend options (strings from the command line, or typed values).

    Raises:
        ValueError: An unknown key or a bad value (the message names the key).
    """
    unknown = sorted(set(options) - set(OPTION_KEYS))
    if unknown:
        raise ValueError(f"unknown option {unknown[0]!r}; expected some of {OPTION_KEYS}")
    renderer = str(options.get("renderer", "tiny"))
    if renderer not in RENDERERS:
        raise ValueError(f"'renderer' must be one of {RENDERERS}, got {renderer!r}")
    try:
        texture_seed = int(options.get("texture_seed", 0))
        light_distance = float(options.get("light_distance", 0.3))
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"'texture_seed' must be an integer, 'light_distance' a number: {err}"
        ) from err
    if not light_distance > 0:
        raise ValueError(f"'light_distance' must be positive, got {light_distance}")
    return PyBulletOptions(renderer, texture_seed, light_distance)


class PyBulletBackend(ClosesOnExit):  # type: ignore[misc, unused-ignore]
    """The built-in rendering backend (pybullet, headless, one DIRECT client per instance).

    Usage::

        with PyBulletBackend({"renderer": "tiny"}) as backend:
            backend.load_scene(SceneSpec(annotate_instruments=True))
            backend.set_state(state)
            frame = backend.render(camera, LightSpec())
            amodal = backend.render_object_depth("needle", big_camera)

    Several instances can live in one process; each owns its pybullet clients.

    Args:
        options: See :class:`PyBulletOptions` (keys :data:`OPTION_KEYS`; None = defaults).

    Raises:
        ValueError: An unknown option or a bad value.
    """

    def __init__(self, options: Mapping[str, Any] | None = None) -> None:
        self.options = parse_options(options or {})
        self._client: int | None = None
        self._solo: int | None = None  # annotated objects only, for object-alone renders
        self._scene: SceneSpec | None = None
        self._assets: SceneAssets | None = None
        self._bodies: dict[str, int] = {}
        self._solo_bodies: dict[str, int] = {}
        self._solo_shown: str | None = None
        self._poses: dict[str, F64] = {}
        self._hulls: dict[str, F64] = {}  # annotated objects' hull points, m
        self._lut = np.zeros(1, dtype=np.int32)  # body id + 1 -> instance value
        self._jaws: dict[str, float] = default_state().jaws
        self._thread: ThreadBodies | None = None  # the suture (--domain), made on demand

    # ------------------------------------------------------------------- lifetime

    def close(self) -> None:
        """Disconnect the pybullet clients (idempotent)."""
        global _egl_owner
        egl = self.options.renderer == "egl"
        for client in (self._client, self._solo):
            if client is None:
                continue
            with contextlib.suppress(p.error):
                if egl and client == self._client:
                    with stdout_to_stderr():  # the plugin prints when it is unloaded
                        p.disconnect(physicsClientId=client)
                else:
                    p.disconnect(physicsClientId=client)
        self._client = self._solo = None
        self._bodies, self._solo_bodies, self._solo_shown = {}, {}, None
        self._thread = None
        if _egl_owner is not None and _egl_owner() is self:
            _egl_owner = None

    # ---------------------------------------------------------------------- scene

    def load_scene(self, scene: SceneSpec) -> None:
        """Build the scene (replacing any previous one), posed at the default state.

        Args:
            scene: Needle, layout, and whether the instruments' wrists and jaws are annotated
                too (obj_ids 2..7, see :mod:`~.pybullet_scene`).

        Raises:
            RuntimeError: With ``renderer="egl"``: the plugin does not load, or another live
                backend of this process uses it.
        """
        self.close()
        try:
            self._build(scene)
        except BaseException:
            self.close()  # no half-built scene: load_scene() must be called again
            self._scene = self._assets = None
            raise

    def _build(self, scene: SceneSpec) -> None:
        """Create the clients, upload every part, pose them at the default state."""
        self._scene = scene
        egl = self.options.renderer == "egl"
        assets = build_scene(
            scene.needle,
            scene.layout,
            annotate_instruments=scene.annotate_instruments,
            texture_seed=self.options.texture_seed,
            instruments=scene.instruments,
        )
        if scene.needle_model is not None:  # the user's mesh; its winding may be inconsistent
            part = assets.parts[NEEDLE]
            assets.parts[NEEDLE] = replace(part, model=scene.needle_model.model, double_sided=True)
        self._assets = assets
        if egl:
            self._claim_egl()
        self._client = p.connect(p.DIRECT)
        if egl:
            load_egl(self._client)  # before any body, or the plugin does not see them
        # pybullet reads meshes and textures from files only: write them to a private
        # temporary folder, removed as soon as everything is loaded.
        with tempfile.TemporaryDirectory(prefix="bopsurg_scene_") as tmp:
            folder = Path(tmp)
            textures = self._load_textures(assets, folder)
            # Creation order is draw order: near things first, so that TinyRenderer's depth
            # test rejects hidden tissue and drape pixels before shading them.
            self._bodies = {
                name: upload_part(
                    self._client, part, folder, textures[part.texture] if part.texture else None
                )
                for name, part in assets.parts.items()
            }
            # Object-alone renders: a second client (always TinyRenderer: it skips alpha-0
            # bodies, and its cost is per covered pixel, not per call like EGL's).
            self._solo = p.connect(p.DIRECT)
            for name in assets.annotated:
                body = upload_part(self._solo, assets.parts[name], folder)
                p.changeVisualShape(body, -1, rgbaColor=[1, 1, 1, 0], physicsClientId=self._solo)
                self._solo_bodies[name] = body
        self._hulls = {
            name: hull_vertices(assets.parts[name].model.pts) * 1e-3 for name in assets.annotated
        }
        # seg + 1 indexes the table; its last entry (0) catches anything out of range.
        self._lut = np.zeros(max(self._bodies.values()) + 3, dtype=np.int32)
        for k, name in enumerate(assets.annotated):
            self._lut[self._bodies[name] + 1] = k + 1
        self._poses = {name: np.eye(4) for name in assets.parts}
        state = default_state(scene.layout.arms)
        self._jaws = state.jaws
        needle = scene.needle_model_pose(state.needle_pose)
        self._apply_poses(part_poses(scene.layout, state.psm_joints, state.jaws, needle))
        log.debug(
            "scene loaded: %d bodies, annotated %s, renderer %s",
            len(self._bodies),
            assets.annotated,
            self.options.renderer,
        )

    def _claim_egl(self) -> None:
        """Become the process's only EGL user, or raise RuntimeError if another one is."""
        global _egl_owner
        owner = _egl_owner() if _egl_owner is not None else None
        if owner is not None and owner is not self and owner._client is not None:
            raise RuntimeError(
                "another PyBulletBackend in this process already uses the EGL renderer "
                "(pybullet's EGL plugin holds one scene per process); close it first"
            )
        _egl_owner = weakref.ref(self)

    def _load_textures(self, assets: SceneAssets, folder: Path) -> dict[str, int]:
        """Load the procedural textures into the main client (via PNG files in ``folder``)."""
        ids = {}
        for key, image in assets.textures.items():
            path = folder / f"{key}.png"
            if not cv2.imwrite(str(path), np.ascontiguousarray(image[..., ::-1])):
                raise RuntimeError(f"could not write the texture {path}")
            ids[key] = p.loadTexture(str(path), physicsClientId=self._client)
            if ids[key] < 0:
                raise RuntimeError(f"pybullet could not load the texture {path}")
        return ids

    def _require(self) -> tuple[int, SceneAssets, SceneSpec]:
        if self._client is None or self._assets is None or self._scene is None:
            raise RuntimeError("no scene: call load_scene() first")
        return self._client, self._assets, self._scene

    def annotated_objects(self) -> list[tuple[str, int]]:
        """(name, BOP obj_id) of the annotated objects: the needle (1), then instrument parts."""
        _, assets, _ = self._require()
        return [(name, k + 1) for k, name in enumerate(assets.annotated)]

    def object_model(self, name: str) -> ObjectModel:
        """BOP model (mm, in the object's frame) of an annotated object or any scene part.

        Raises:
            KeyError: No such object.
        """
        _, assets, _ = self._require()
        if name not in assets.parts:
            raise KeyError(f"no object {name!r}; annotated: {list(assets.annotated)}")
        model: ObjectModel = assets.parts[name].model
        return model

    # ---------------------------------------------------------------------- state

    def set_state(self, state: SceneState) -> None:
        """Pose the instruments (FK of each arm's joints and jaw) and the needle.

        Arms missing from ``state.psm_joints`` keep their pose; a missing jaw angle keeps the
        previous one. ``state.ecm_joints`` is not used: cameras come with each render call.

        Raises:
            ValueError: An unknown arm name or a malformed needle pose.
        """
        _, _, scene = self._require()
        needle = np.asarray(state.needle_pose, dtype=np.float64)
        if needle.shape != (4, 4):
            raise ValueError(f"needle_pose must be 4x4, got shape {needle.shape}")
        arms = scene.layout.arms
        unknown = sorted(set(state.jaws) - set(arms))
        if unknown:
            raise ValueError(f"unknown arm {unknown[0]!r} in jaws; expected one of {arms}")
        jaws = dict(self._jaws)
        jaws.update({k: float(v) for k, v in state.jaws.items()})
        poses = part_poses(scene.layout, state.psm_joints, jaws, scene.needle_model_pose(needle))
        self._jaws = jaws
        self._apply_poses(poses)

    def _apply_poses(self, poses: dict[str, F64]) -> None:
        client, _, _ = self._require()
        names = list(poses)
        quats = _quaternions([poses[n] for n in names])
        for name, q in zip(names, quats, strict=True):
            T = poses[name]
            self._poses[name] = T
            p.resetBasePositionAndOrientation(
                self._bodies[name], T[:3, 3].tolist(), q.tolist(), physicsClientId=client
            )

    def object_pose(self, name: str) -> F64:
        """``T_world_object`` (4, 4), m, of an object's model frame.

        Raises:
            KeyError: No such object.
        """
        self._require()
        if name not in self._poses:
            raise KeyError(f"no object {name!r}")
        return self._poses[name].copy()

    # ------------------------------------------------------------------ rendering

    @staticmethod
    def _camera_args(
        camera: CameraSpec, K: F64, width: int, height: int, renderer: str
    ) -> dict[str, Any]:
        """getCameraImage arguments of a camera (with intrinsics ``K``, size, renderer)."""
        return {
            "width": width,
            "height": height,
            "viewMatrix": view_matrix(np.asarray(camera.T_world_cam, dtype=np.float64)),
            "projectionMatrix": projection_matrix(
                K, width, height, camera.near, camera.far, PIXEL_OFFSETS[renderer]
            ),
            "renderer": p.ER_BULLET_HARDWARE_OPENGL if renderer == "egl" else p.ER_TINY_RENDERER,
        }

    def render(self, camera: CameraSpec, light: LightSpec) -> RenderedFrame:
        """Render the whole scene: RGB, z-depth (mm) and the annotated-instance map."""
        client, _, _ = self._require()
        renderer = self.options.renderer
        K = np.asarray(camera.K, dtype=np.float64)
        direction = np.asarray(light.direction, dtype=np.float64)
        direction = direction / np.linalg.norm(direction)
        # The EGL plugin prints to stdout on some calls: keep stdout clean.
        quiet = stdout_to_stderr() if renderer == "egl" else contextlib.nullcontext()
        with quiet:
            _, _, rgba, depth, seg = p.getCameraImage(
                **self._camera_args(camera, K, camera.width, camera.height, renderer),
                lightDirection=direction.tolist(),
                lightColor=np.asarray(light.color, dtype=np.float64).tolist(),
                lightDistance=self.options.light_distance,
                shadow=int(bool(light.shadows)),
                lightAmbientCoeff=float(light.ambient),
                lightDiffuseCoeff=float(light.diffuse),
                lightSpecularCoeff=float(light.specular),
                physicsClientId=client,
            )
        shape = (camera.height, camera.width)
        rgb = np.ascontiguousarray(np.asarray(rgba, dtype=np.uint8).reshape(*shape, 4)[..., :3])
        seg = np.asarray(seg).reshape(shape)
        z = depth_buffer_to_mm(np.asarray(depth).reshape(shape), camera.near, camera.far, seg)
        # Background is -1; base-only bodies carry no link bits, so seg is the body id.
        instance = np.take(self._lut, seg + 1, mode="clip")
        return RenderedFrame(rgb=rgb, depth=z, instance=instance)

    def render_object_depth(self, name: str, camera: CameraSpec) -> F64:
        """Depth (mm) of one annotated object alone (nothing occludes it).

        The camera may be larger than the image (BOP's 3× canvas with the principal point
        shifted by (W, H)); only the window the object's projection can cover is rendered.

        Raises:
            KeyError: ``name`` is not an annotated object.
        """
        _, assets, _ = self._require()
        if name not in assets.annotated:
            raise KeyError(f"{name!r} is not annotated; annotated: {list(assets.annotated)}")
        K = np.asarray(camera.K, dtype=np.float64)
        T_cam_obj = np.linalg.solve(camera.T_world_cam, self._poses[name])

        def render(Kw: F64, w: int, h: int) -> tuple[NDArray[Any], NDArray[Any]]:
            return self._render_solo(name, self._camera_args(camera, Kw, w, h, "tiny"))

        depth: F64 = render_in_window(
            self._hulls[name],
            T_cam_obj,
            K,
            (camera.width, camera.height),
            (camera.near, camera.far),
            render,
        )
        return depth

    # ------------------------------------------------------- domain randomisation

    def set_appearance(self, appearance: Appearance) -> None:
        """Materials of the loaded scene (``--domain``; see :mod:`~.pybullet_domain`)."""
        from bopsurg.generators.pybullet_domain import apply_appearance

        client, _, _ = self._require()
        apply_appearance(client, self._bodies, appearance)

    def set_thread(
        self, points: F64, radius_mm: float, rgba: tuple[float, float, float, float]
    ) -> None:
        """Show the suture along ``points`` (N, 3), world, m: rgb and depth, not annotated."""
        from bopsurg.generators.pybullet_domain import ThreadBodies

        client, _, _ = self._require()
        if self._thread is None:
            self._thread = ThreadBodies(client)
        self._thread.show(points, radius_mm, rgba)

    def _render_solo(self, name: str, args: dict[str, Any]) -> tuple[NDArray[Any], NDArray[Any]]:
        """Depth and segmentation buffers of the object in the solo client (TinyRenderer)."""
        solo = self._solo
        assert solo is not None
        if self._solo_shown != name:
            if self._solo_shown is not None:
                p.changeVisualShape(
                    self._solo_bodies[self._solo_shown],
                    -1,
                    rgbaColor=[1, 1, 1, 0],
                    physicsClientId=solo,
                )
            p.changeVisualShape(
                self._solo_bodies[name], -1, rgbaColor=[1, 1, 1, 1], physicsClientId=solo
            )
            self._solo_shown = name
        T = self._poses[name]
        q = _quaternions([T])[0]
        p.resetBasePositionAndOrientation(
            self._solo_bodies[name], T[:3, 3].tolist(), q.tolist(), physicsClientId=solo
        )
        # The segmentation buffer costs nothing and tells the background exactly.
        _, _, _, depth, seg = p.getCameraImage(**args, physicsClientId=solo)
        return depth, seg


__all__ = [
    "ARMS",
    "OPTION_KEYS",
    "PIXEL_OFFSETS",
    "ClosesOnExit",
    "PyBulletBackend",
    "PyBulletOptions",
    "WindowRender",
    "depth_buffer_to_mm",
    "projection_matrix",
    "render_in_window",
    "render_window",
    "render_window_depth",
    "view_matrix",
    "write_obj",
]
