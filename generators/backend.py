"""The generator interface: what a render backend provides to replay and BOP writing.

Replay, viewpoint sampling and BOP writing (``bopsurg.generators.replay`` and friends) only
talk to a :class:`RenderBackend`; PyBullet is the default backend, registered under the
``bopsurg.render_backends`` entry-point group like any third-party one would be. The group's
entry is a :data:`BackendFactory`: called with the backend's own options (``bopsurg generate
--backend-option KEY=VALUE``, strings), it returns a backend, whose
:meth:`RenderBackend.load_scene` then receives the backend-independent :class:`SceneSpec`.
This module also holds the one default scene state (:func:`default_state`).

Units: the scene state and camera poses are in metres and radians (ROS / CRTK SI), images in
pixels; depth comes back in **millimetres** (BOP), 0 where nothing was hit. Camera frames
use OpenCV axes (x right, y down, z forward).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.meshes import ObjectModel
from bopsurg.generators.kinematics import DEFAULT_LAYOUT, SceneLayout
from bopsurg.generators.object_model import NeedleModel, needle_model_from_config
from bopsurg.needle import NeedleSpec

F64 = NDArray[np.float64]

#: The patient-side arms of the default scene (bopsurg's own and the simulator's recordings).
ARMS = ("psm1", "psm2")
#: Every patient-side arm a recording may carry.
ALL_ARMS = ("psm1", "psm2", "psm3")

#: Names of the annotated objects a backend must know, with their BOP obj_id.
#: The needle is object 1; instrument parts are optional further objects.
NEEDLE = "needle"


@dataclass(frozen=True)
class SceneState:
    """Everything that moves, at one instant.

    Attributes:
        psm_joints: Joint positions per arm (``"psm1"``, ``"psm2"``), (6,) rad / m.
        jaws: Jaw opening per arm, rad.
        ecm_joints: (4,) yaw, pitch (rad), insertion (m), roll (rad).
        needle_pose: ``T_world_needle`` (4, 4), m; the needle model frame is BOP's (arc in the
            model XY plane around the origin).
    """

    psm_joints: dict[str, F64]
    jaws: dict[str, float]
    ecm_joints: F64
    needle_pose: F64


#: The default scene state, for streams a recording lacks and for a backend before its first
#: :meth:`RenderBackend.set_state`. A parked PSM: shaft straight along its base −Z, 5 cm
#: inserted (the tip ~28 mm below the RCM, far above the tissue); jaws closed.
PARKED_PSM_JOINTS = np.array([0.0, 0.0, 0.05, 0.0, 0.0, 0.0])
PARKED_JAW = 0.0
#: The endoscope at its base pose (looking at the workspace centre).
DEFAULT_ECM_JOINTS = np.zeros(4)
#: The needle lying flat on the tissue at the world origin (model +Z up; 0.36 mm = wire radius).
DEFAULT_NEEDLE_POSE = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.36e-3], [0.0, 0.0, 0.0, 1.0]]
)


def default_state(arms: tuple[str, ...] = ARMS) -> SceneState:
    """The arms parked, the endoscope at its base pose, the needle on the tissue (copies)."""
    return SceneState(
        psm_joints={arm: PARKED_PSM_JOINTS.copy() for arm in arms},
        jaws=dict.fromkeys(arms, PARKED_JAW),
        ecm_joints=DEFAULT_ECM_JOINTS.copy(),
        needle_pose=DEFAULT_NEEDLE_POSE.copy(),
    )


@dataclass(frozen=True)
class SceneSpec:
    """What is in the scene, independent of the backend that renders it.

    Attributes:
        needle: Needle geometry (mm, degrees); a backend builds the needle model from it.
            With ``needle_model`` it is the needle the recordings pose (``needle_pose``).
        annotate_instruments: Also annotate the instruments' wrists and jaws (obj_ids 2..).
        layout: Where the arms and the endoscope stand (m).
        needle_model: The user's needle mesh (``generate --object-model``): a backend
            renders and returns (:meth:`RenderBackend.object_model`) this mesh instead, posed
            by :meth:`needle_model_pose`; None: the needle built from ``needle``.
        instruments: Instrument look: ``simple`` (the default) or ``lnd`` (closer to the
            Large Needle Driver; ``generate --domain wide`` asks for it). A backend may ignore it.
    """

    needle: NeedleSpec = field(default_factory=NeedleSpec)
    annotate_instruments: bool = False
    layout: SceneLayout = DEFAULT_LAYOUT
    needle_model: NeedleModel | None = None
    instruments: str = "simple"

    def needle_model_pose(self, T_world_needle: F64) -> F64:
        """``T_world_object`` (4, 4), m, of the annotated needle's model frame.

        ``T_world_needle`` (a :class:`SceneState`'s ``needle_pose``) itself, or with a
        ``needle_model`` ``T_world_needle @ T_needle_model``: the user's mesh laid on the
        recorded needle through the two fitted arcs.
        """
        T: F64 = np.asarray(T_world_needle, dtype=np.float64)
        if self.needle_model is None:
            return T
        moved: F64 = T @ self.needle_model.T_needle_model
        return moved


#: ``bopsurg generate`` settings keys that describe the scene (the rest are backend options).
SCENE_KEYS = ("needle", "annotate_instruments", "layout", "object_model")


def split_backend_config(config: Mapping[str, Any]) -> tuple[SceneSpec, dict[str, Any]]:
    """Split a generation's ``backend_config`` into the scene and the backend's options.

    Args:
        config: ``needle`` (:class:`NeedleSpec` keyword arguments, or one),
            ``annotate_instruments`` (bool), ``layout`` (:class:`SceneLayout`),
            ``object_model`` (a needle PLY path, or ``{"path", "sha256"}`` as the generation
            record holds it: loaded and fitted, :mod:`~bopsurg.generators.object_model`);
            every other key is an option of the backend (e.g. PyBullet's ``renderer``),
            passed on unchanged.

    Raises:
        TypeError: A scene key with a value of the wrong type.
        BopsurgError: ``object_model`` is missing, unreadable, changed or not a needle.
    """
    needle = config.get("needle")
    if needle is None:
        needle = NeedleSpec()
    elif isinstance(needle, Mapping):
        needle = NeedleSpec(**needle)
    elif not isinstance(needle, NeedleSpec):
        raise TypeError(f"'needle' must be NeedleSpec keyword arguments, got {needle!r}")
    layout = config.get("layout") or DEFAULT_LAYOUT
    if not isinstance(layout, SceneLayout):
        raise TypeError(f"'layout' must be a SceneLayout, got {type(layout).__name__}")
    model = config.get("object_model")
    scene = SceneSpec(
        needle=needle,
        annotate_instruments=bool(config.get("annotate_instruments", False)),
        layout=layout,
        needle_model=None if model is None else needle_model_from_config(model, needle),
    )
    return scene, {k: v for k, v in config.items() if k not in SCENE_KEYS}


@dataclass(frozen=True)
class CameraSpec:
    """A pinhole camera.

    Attributes:
        K: (3, 3) intrinsics, px (OpenCV: pixel centres at integer coordinates).
        width, height: Image size, px.
        T_world_cam: (4, 4) camera-to-world pose, m, OpenCV axes.
        near, far: Clipping distances, m.
    """

    K: F64
    width: int
    height: int
    T_world_cam: F64
    near: float = 0.005
    far: float = 1.0


@dataclass(frozen=True)
class LightSpec:
    """Lighting of one replay (what PyBullet's TinyRenderer can vary).

    Attributes:
        direction: (3,) direction towards the light, world frame (normalised by the backend).
        color: (3,) RGB in [0, 1].
        ambient, diffuse, specular: Reflection coefficients.
        shadows: Cast shadows.
    """

    direction: F64 = field(default_factory=lambda: np.array([0.0, -0.5, 1.0]))
    color: F64 = field(default_factory=lambda: np.ones(3))
    ambient: float = 0.55
    diffuse: float = 0.5
    specular: float = 0.3
    shadows: bool = False


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered view.

    Attributes:
        rgb: (H, W, 3) uint8.
        depth: (H, W) float64 z-depth, mm, 0 = nothing.
        instance: (H, W) int32, the annotated object visible at each pixel: the index into
            :meth:`RenderBackend.annotated_objects` + 1, 0 for anything else (tissue, tools
            that are not annotated, background).
    """

    rgb: NDArray[np.uint8]
    depth: F64
    instance: NDArray[np.int32]


@runtime_checkable
class RenderBackend(Protocol):
    """What a render backend provides (built by a :data:`BackendFactory`)."""

    def load_scene(self, scene: SceneSpec) -> None:
        """Build the scene (tissue, instruments, needle), replacing any previous one.

        Until the first :meth:`set_state` the scene shows :func:`default_state`. With a
        ``scene.needle_model`` the needle is that mesh, posed by
        :meth:`SceneSpec.needle_model_pose` (``object_model`` and ``object_pose`` report it).
        """
        ...

    def annotated_objects(self) -> list[tuple[str, int]]:
        """(name, BOP obj_id) of each annotated object, in a fixed order; the needle first."""
        ...

    def object_model(self, name: str) -> ObjectModel:
        """BOP model (vertices mm, in the object's model frame) of an annotated object.

        ``bopsurg generate`` writes it to ``models/obj_OBJID.ply``; it must be the geometry
        the backend renders, whether built by code or loaded from a file.
        """
        ...

    def set_state(self, state: SceneState) -> None:
        """Move the robots, the jaws and the needle."""
        ...

    def object_pose(self, name: str) -> F64:
        """``T_world_object`` (4, 4), m, of an annotated object's BOP model frame."""
        ...

    def render(self, camera: CameraSpec, light: LightSpec) -> RenderedFrame:
        """Render the whole scene."""
        ...

    def render_object_depth(self, name: str, camera: CameraSpec) -> F64:
        """Depth (mm) of one annotated object alone (nothing occludes it), for amodal masks.

        ``camera`` may be larger than the image (BOP's 3× canvas with a shifted principal
        point), so truncated parts are counted.
        """
        ...

    def close(self) -> None:
        """Release the backend's resources."""
        ...


#: What the ``bopsurg.render_backends`` entry point names: backend options (``--backend-option
#: KEY=VALUE``; strings from the command line, or any JSON value) → a backend. A backend
#: class whose ``__init__`` takes the options mapping is one.
BackendFactory = Callable[[Mapping[str, Any]], RenderBackend]


__all__ = [
    "ALL_ARMS",
    "ARMS",
    "DEFAULT_ECM_JOINTS",
    "DEFAULT_NEEDLE_POSE",
    "NEEDLE",
    "PARKED_JAW",
    "PARKED_PSM_JOINTS",
    "SCENE_KEYS",
    "BackendFactory",
    "CameraSpec",
    "LightSpec",
    "RenderBackend",
    "RenderedFrame",
    "SceneSpec",
    "SceneState",
    "default_state",
    "split_backend_config",
]
