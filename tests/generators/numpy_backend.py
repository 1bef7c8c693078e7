"""A second render backend, pure numpy: the needle alone, z-buffered, on a grey background.

It exists to prove that the :class:`~bopsurg.generators.backend.RenderBackend` protocol is
complete: ``bopsurg generate`` runs end to end with it, found through the
``bopsurg.render_backends`` entry-point group like any third-party backend (the tests register
it from a temporary ``.dist-info`` folder). It implements nothing but the protocol.

Rasterisation: every (triangle, pixel-centre) pair inside the triangle's pixel bounding box is
tested at once with barycentric coordinates; depth is interpolated linearly in screen space
(exact for planar facets up to perspective, ample for a test) and the nearest hit wins.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.meshes import ObjectModel
from bopsurg.generators.backend import (
    NEEDLE,
    CameraSpec,
    LightSpec,
    RenderedFrame,
    SceneSpec,
    SceneState,
    default_state,
)
from bopsurg.needle import needle_mesh

F64 = NDArray[np.float64]

#: Options of :class:`NumpyNeedleBackend`.
OPTION_KEYS = ("grey",)


def rasterize_depth(model: ObjectModel, T_cam_obj: F64, camera: CameraSpec) -> F64:
    """(H, W) z-depth in mm of ``model`` (vertices mm) at ``T_cam_obj`` (m), 0 = empty."""
    R, t_mm = T_cam_obj[:3, :3], T_cam_obj[:3, 3] * 1000.0
    p = model.pts @ R.T + t_mm
    depth = np.zeros(camera.height * camera.width)
    tri = p[model.faces]  # (F, 3, 3)
    tri = tri[(tri[:, :, 2] > camera.near * 1000.0).all(axis=1)]
    if len(tri) == 0:
        return depth.reshape(camera.height, camera.width)
    K = camera.K
    u = K[0, 0] * tri[..., 0] / tri[..., 2] + K[0, 2]
    v = K[1, 1] * tri[..., 1] / tri[..., 2] + K[1, 2]
    u0 = np.clip(np.ceil(u.min(axis=1)), 0, camera.width).astype(np.int64)
    u1 = np.clip(np.floor(u.max(axis=1)) + 1, 0, camera.width).astype(np.int64)
    v0 = np.clip(np.ceil(v.min(axis=1)), 0, camera.height).astype(np.int64)
    v1 = np.clip(np.floor(v.max(axis=1)) + 1, 0, camera.height).astype(np.int64)
    nu, nv = np.maximum(u1 - u0, 0), np.maximum(v1 - v0, 0)
    counts = nu * nv
    f = np.repeat(np.arange(len(tri)), counts)  # one row per (triangle, pixel) candidate
    k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    nu_f = np.maximum(nu[f], 1)
    px, py = u0[f] + k % nu_f, v0[f] + k // nu_f
    (ax, bx, cx), (ay, by, cy) = u[f].T, v[f].T
    area = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
    w1 = ((px - ax) * (cy - ay) - (cx - ax) * (py - ay)) / np.where(area == 0, 1, area)
    w2 = ((bx - ax) * (py - ay) - (px - ax) * (by - ay)) / np.where(area == 0, 1, area)
    w0 = 1.0 - w1 - w2
    inside = (area != 0) & (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
    z = tri[f, :, 2]
    z_hit = (w0 * z[:, 0] + w1 * z[:, 1] + w2 * z[:, 2])[inside]
    index = (py * camera.width + px)[inside]
    depth[:] = np.inf
    np.minimum.at(depth, index, z_hit)
    depth[np.isinf(depth)] = 0.0
    return depth.reshape(camera.height, camera.width)


class NumpyNeedleBackend:
    """The needle alone, rendered by :func:`rasterize_depth`.

    Args:
        options: ``grey``: background grey level, 0-255 (default 90).
    """

    def __init__(self, options: Mapping[str, Any] | None = None) -> None:
        options = dict(options or {})
        unknown = sorted(set(options) - set(OPTION_KEYS))
        if unknown:
            raise ValueError(f"unknown option {unknown[0]!r}; expected some of {OPTION_KEYS}")
        self.grey = int(options.get("grey", 90))
        if not 0 <= self.grey <= 255:
            raise ValueError(f"'grey' must be in [0, 255], got {self.grey}")
        self._model: ObjectModel | None = None
        self._scene = SceneSpec()
        self._pose = default_state().needle_pose

    def load_scene(self, scene: SceneSpec) -> None:
        # The user's mesh (generate --object-model) when there is one, posed on the recorded
        # needle by the scene: all a backend has to do for it.
        user = scene.needle_model
        self._model = user.model if user is not None else needle_mesh(scene.needle)
        self._scene = scene
        self._pose = scene.needle_model_pose(default_state().needle_pose)

    def annotated_objects(self) -> list[tuple[str, int]]:
        return [(NEEDLE, 1)]

    def object_model(self, name: str) -> ObjectModel:
        if self._model is None:
            raise RuntimeError("no scene: call load_scene() first")
        if name != NEEDLE:
            raise KeyError(f"no object {name!r}")
        return self._model

    def set_state(self, state: SceneState) -> None:
        self._pose = self._scene.needle_model_pose(state.needle_pose)

    def object_pose(self, name: str) -> F64:
        self.object_model(name)
        return self._pose.copy()

    def render_object_depth(self, name: str, camera: CameraSpec) -> F64:
        T_cam_obj = np.linalg.solve(camera.T_world_cam, self.object_pose(name))
        return rasterize_depth(self.object_model(name), T_cam_obj, camera)

    def render(self, camera: CameraSpec, light: LightSpec) -> RenderedFrame:
        depth = self.render_object_depth(NEEDLE, camera)
        hit = depth > 0
        rgb = np.full((camera.height, camera.width, 3), self.grey, dtype=np.uint8)
        rgb[hit] = np.clip(255 * np.asarray(light.color) * light.ambient + 80, 0, 255)
        return RenderedFrame(rgb=rgb, depth=depth, instance=hit.astype(np.int32))

    def close(self) -> None:
        self._model = None
