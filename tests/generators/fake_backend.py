"""A tiny deterministic stand-in for a render backend and a recording (no pybullet).

The "needle" renders as a square patch at the projection of its model origin, at the depth
of that origin; a vertical bar in front of the tissue occludes part of the image. Enough to
test replay, writing, visibility, dropping and resuming independently of any renderer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bopsurg.bop.meshes import ObjectModel
from bopsurg.generators.backend import (
    CameraSpec,
    LightSpec,
    RenderedFrame,
    SceneSpec,
    SceneState,
)
from bopsurg.generators.kinematics import pose

HALF = 12  # patch half size, px
TISSUE_MM = 400.0
BAR_MM = 30.0


class FakeBackend:
    def __init__(self) -> None:
        self.state: SceneState | None = None

    def load_scene(self, scene: SceneSpec) -> None:
        self.scene = scene

    def annotated_objects(self) -> list[tuple[str, int]]:
        return [("needle", 1)]

    def object_model(self, name: str) -> ObjectModel:
        pts = np.array([[-5.0, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]])
        return ObjectModel(pts=pts, faces=np.array([[0, 1, 2], [0, 2, 3]]))

    def set_state(self, state: SceneState) -> None:
        self.state = state

    def object_pose(self, name: str) -> np.ndarray:
        assert self.state is not None
        return self.state.needle_pose

    def _object_depth(self, camera: CameraSpec) -> np.ndarray:
        T = np.linalg.solve(camera.T_world_cam, self.object_pose("needle"))
        x, y, z = T[:3, 3]
        u = camera.K[0, 0] * x / z + camera.K[0, 2]
        v = camera.K[1, 1] * y / z + camera.K[1, 2]
        depth = np.zeros((camera.height, camera.width))
        if z > 0:
            r0, r1 = int(np.rint(v)) - HALF, int(np.rint(v)) + HALF
            c0, c1 = int(np.rint(u)) - HALF, int(np.rint(u)) + HALF
            depth[max(r0, 0) : max(r1, 0), max(c0, 0) : max(c1, 0)] = z * 1000.0
        return depth

    def render(self, camera: CameraSpec, light: LightSpec) -> RenderedFrame:
        obj = self._object_depth(camera)
        depth = np.full((camera.height, camera.width), TISSUE_MM)
        depth[:, 300:330] = BAR_MM
        hit = (obj > 0) & (obj < depth)
        depth[hit] = obj[hit]
        rgb = np.zeros((camera.height, camera.width, 3), np.uint8)
        rgb[..., 0] = 150
        rgb[hit] = (200, 200, 200)
        return RenderedFrame(rgb=rgb, depth=depth, instance=hit.astype(np.int32))

    def render_object_depth(self, name: str, camera: CameraSpec) -> np.ndarray:
        return self._object_depth(camera)

    def close(self) -> None:
        pass


@dataclass
class FakeRecording:
    """The needle slides along world x from -40 mm to +40 mm, 60 mm below... on the tissue."""

    start: float = 0.0
    end: float = 4.0
    meta: dict = field(default_factory=dict)  # a Recording's facts (none: bopsurg's needle)
    layout: None = None  # the default layout
    robot: str = "simulator"

    def state_at(self, t: float) -> SceneState:
        x = -0.04 + 0.08 * (t - self.start) / (self.end - self.start)
        return SceneState(
            psm_joints={},
            jaws={},
            ecm_joints=np.zeros(4),
            needle_pose=pose(np.eye(3), [x, 0.0, 0.0]),
        )
