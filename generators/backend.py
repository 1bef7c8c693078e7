"""The generator interface: what a rendering backend provides to replay and BOP writing.

Replay, viewpoint sampling and BOP writing (``bopsurg.generators.replay`` and friends) only
talk to a :class:`RenderBackend`; PyBullet is the default backend, registered under the
``bopsurg.generators`` entry-point group like any third-party one would be.

Units: the scene state and camera poses are in metres and radians (ROS / CRTK SI), images in
pixels; depth comes back in **millimetres** (BOP), 0 where nothing was hit. Camera frames
use OpenCV axes (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

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
    """What a generator backend provides."""

    def load_scene(self, config: dict) -> None:
        """Build the scene (tissue, instruments, needle) from a config mapping."""
        ...

    def annotated_objects(self) -> list[tuple[str, int]]:
        """(name, BOP obj_id) of each annotated object, in a fixed order; the needle first."""
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
