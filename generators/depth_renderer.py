"""Depth renderer plugin for the core's VSD and visibility: any BOP model, pybullet TinyRenderer.

:class:`PyBulletDepthRenderer` implements :class:`bopsurg.plugins.DepthRenderer` headlessly
with its own pybullet DIRECT client. Each model is uploaded once (an OBJ file in metres, both
windings of every triangle so that models with inconsistent winding lose no faces) and kept
hidden (alpha 0, which TinyRenderer skips at no cost) until it is rendered again; the cache is
keyed by the model object and, failing that, by a hash of its vertices and faces.

Accuracy: TinyRenderer samples pixel centres exactly (principal point ``(cx, cy + 1)`` in its
projection, see ``libraries.md`` §2), and the near/far planes are fitted around the model's
bounding sphere for each call, so the float32 depth buffer resolves well under 1 µm at
surgical distances. Only the pixel window the model's projection can cover is rendered, so
BOP's 3× canvas costs about as much as the object's pixels.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import tempfile
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pybullet as p
from numpy.typing import ArrayLike, NDArray

from bopsurg.bop.meshes import ObjectModel
from bopsurg.generators.pybullet_render import (
    PIXEL_OFFSETS,
    ClosesOnExit,
    projection_matrix,
    render_window_depth,
    view_matrix,
    write_obj,
)

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
#: Depth (mm) of a window of the image and its top-left (row, column); None: not seen.
WindowDepth = tuple[F64, tuple[int, int]] | None

#: Closest near plane, mm: parts of a model nearer to the camera than this are clipped.
NEAR_MIN_MM = 1.0

#: Models with more vertices bound their renders' windows with their convex hull's vertices
#: (fewer points to project per render, one Qhull call per model); smaller ones use them all,
#: which bounds the projection identically (its extremes lie at hull vertices).
HULL_MIN_VERTICES = 4096

#: The camera is the world frame (the model sits at its pose in it).
_VIEW = view_matrix(np.eye(4))


def quaternion_xyzw(R: F64) -> list[float]:
    """Unit quaternion (x, y, z, w) of a rotation matrix, bit for bit scipy's
    ``Rotation.from_matrix(R).as_quat()`` (same case choice and operations), without importing
    scipy for it; matrices not orthogonal to 1e-12 (scipy first projects them onto the
    rotations) and reflections (scipy refuses them) are handed to scipy itself."""
    eye = np.eye(3)
    orthogonal = np.all(np.abs(R @ R.T - eye) <= 1e-12 + 1e-5 * eye)  # isclose, atol=1e-12
    if not orthogonal or np.linalg.det(R) <= 0:  # scipy projects, or raises on reflections
        from scipy.spatial.transform import Rotation

        quat: list[float] = Rotation.from_matrix(R).as_quat().tolist()
        return quat
    m = R.tolist()
    trace = m[0][0] + m[1][1] + m[2][2]
    decision = (m[0][0], m[1][1], m[2][2], trace)
    choice = decision.index(max(decision))  # the first maximum, as argmax
    q = [0.0, 0.0, 0.0, 0.0]
    if choice != 3:
        i = choice
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i] = 1 - trace + 2 * m[i][i]
        q[j] = m[j][i] + m[i][j]
        q[k] = m[k][i] + m[i][k]
        q[3] = m[k][j] - m[j][k]
    else:
        q[0] = m[2][1] - m[1][2]
        q[1] = m[0][2] - m[2][0]
        q[2] = m[1][0] - m[0][1]
        q[3] = 1 + trace
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return [x / norm for x in q]


@dataclass(frozen=True)
class _Mesh:
    """An uploaded model: its body, hull points (m) and bounding sphere (mm)."""

    body: int
    hull: F64
    center: F64
    radius: float


def model_key(model: ObjectModel) -> bytes:
    """Content hash of a model's geometry (vertices and faces)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.ascontiguousarray(model.pts, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(model.faces, dtype=np.int64).tobytes())
    return h.digest()


class PyBulletDepthRenderer(ClosesOnExit):  # type: ignore[misc, unused-ignore]
    """Renders z-depth (mm) of object models with pybullet's TinyRenderer, headless.

    Usage::

        renderer = PyBulletDepthRenderer()
        depth = renderer.render_depth(model, R, t, K, 640, 480)  # (480, 640) mm, 0 = empty
    """

    def __init__(self) -> None:
        self._client: int | None = None
        self._by_model: weakref.WeakKeyDictionary[ObjectModel, _Mesh] = weakref.WeakKeyDictionary()
        self._by_key: dict[bytes, _Mesh] = {}
        self._shown: int | None = None

    def close(self) -> None:
        """Disconnect the pybullet client and forget the uploaded models (idempotent)."""
        if self._client is not None:
            with contextlib.suppress(p.error):
                p.disconnect(physicsClientId=self._client)
        self._client = None
        self._by_model = weakref.WeakKeyDictionary()
        self._by_key = {}
        self._shown = None

    @property
    def cached_models(self) -> int:
        """Number of models uploaded so far."""
        return len(self._by_key)

    def _mesh(self, model: ObjectModel) -> _Mesh:
        """The uploaded mesh of a model, uploading it on first use."""
        with contextlib.suppress(TypeError):  # not weak-referenceable: fall back to the hash
            mesh = self._by_model.get(model)
            if mesh is not None:
                return mesh
        key = model_key(model)
        mesh = self._by_key.get(key)
        if mesh is None:
            mesh = self._upload(model)
            self._by_key[key] = mesh
        with contextlib.suppress(TypeError):
            self._by_model[model] = mesh
        return mesh

    def _upload(self, model: ObjectModel) -> _Mesh:
        if len(model.faces) == 0:
            raise ValueError("cannot render depth of a point cloud (the model has no faces)")
        if self._client is None:
            self._client = p.connect(p.DIRECT)
        with tempfile.TemporaryDirectory(prefix="bopsurg_depth_") as tmp:
            path = Path(tmp) / "model.obj"
            write_obj(path, ObjectModel(pts=model.pts, faces=model.faces), double_sided=True)
            shape = p.createVisualShape(
                p.GEOM_MESH, fileName=str(path), physicsClientId=self._client
            )
        if shape < 0:
            raise RuntimeError("pybullet could not create the model's visual shape")
        body = p.createMultiBody(baseVisualShapeIndex=shape, physicsClientId=self._client)
        p.changeVisualShape(body, -1, rgbaColor=[1, 1, 1, 0], physicsClientId=self._client)
        lo, hi = model.pts.min(axis=0), model.pts.max(axis=0)
        center = 0.5 * (lo + hi)
        radius = float(np.linalg.norm(model.pts - center, axis=1).max())
        log.debug("uploaded a model: %d vertices, %d faces", model.n_vertices, len(model.faces))
        bound = model.pts
        if model.n_vertices > HULL_MIN_VERTICES:
            from bopsurg.metrics.point_subsets import hull_vertices  # scipy: big models only

            bound = hull_vertices(model.pts)
        return _Mesh(body=body, hull=bound * 1e-3, center=center, radius=radius)

    def render_depth(
        self,
        model: ObjectModel,
        R: ArrayLike,
        t: ArrayLike,
        K: ArrayLike,
        width: int,
        height: int,
    ) -> F64:
        """Render the z-depth of ``model`` at pose ``x_cam = R x + t``.

        Args:
            model: Triangle mesh, mm.
            R: (3, 3) rotation, model to camera.
            t: (3,) translation, mm.
            K: (3, 3) intrinsics, px (pixel centres at integer coordinates).
            width, height: Image size, px (may be BOP's 3× canvas).

        Returns:
            (height, width) float64 depth in mm, 0 where the model is absent.

        Raises:
            ValueError: The model has no faces.
        """
        out = np.zeros((height, width))
        rendered = self.render_depth_window(model, R, t, K, width, height)
        if rendered is not None:
            depth, (r0, c0) = rendered
            out[r0 : r0 + depth.shape[0], c0 : c0 + depth.shape[1]] = depth
        return out

    def render_depth_window(
        self,
        model: ObjectModel,
        R: ArrayLike,
        t: ArrayLike,
        K: ArrayLike,
        width: int,
        height: int,
    ) -> WindowDepth:
        """:meth:`render_depth` cut to a window that holds every pixel the model covers.

        Returns:
            The window's depth (mm, 0 where the model is absent) and the (row, column) of its
            top-left pixel in the (height, width) image; None when the model cannot be seen
            (wholly behind the camera or off the image).

        Raises:
            ValueError: The model has no faces.
        """
        mesh = self._mesh(model)
        assert self._client is not None
        R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t_mm = np.asarray(t, dtype=np.float64).reshape(3)
        K = np.asarray(K, dtype=np.float64)
        # Near and far planes hug the bounding sphere: depth precision scales with z²/near.
        zc = float(R[2] @ mesh.center + t_mm[2])
        z_far = zc + mesh.radius
        if z_far <= NEAR_MIN_MM:
            return None
        near = 1e-3 * max(0.99 * (zc - mesh.radius), NEAR_MIN_MM)
        far = 1e-3 * (1.01 * z_far + 1.0)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = 1e-3 * t_mm
        client = self._client

        def render(Kw: F64, w: int, h: int) -> tuple[NDArray[Any], NDArray[Any]]:
            if self._shown != mesh.body:
                if self._shown is not None:
                    p.changeVisualShape(
                        self._shown, -1, rgbaColor=[1, 1, 1, 0], physicsClientId=client
                    )
                p.changeVisualShape(mesh.body, -1, rgbaColor=[1, 1, 1, 1], physicsClientId=client)
                self._shown = mesh.body
            p.resetBasePositionAndOrientation(
                mesh.body, T[:3, 3].tolist(), quaternion_xyzw(R), physicsClientId=client
            )
            _, _, _, depth, seg = p.getCameraImage(
                w,
                h,
                viewMatrix=_VIEW,
                projectionMatrix=projection_matrix(Kw, w, h, near, far, PIXEL_OFFSETS["tiny"]),
                renderer=p.ER_TINY_RENDERER,
                physicsClientId=client,
            )
            return depth, seg

        rendered: WindowDepth = render_window_depth(
            mesh.hull, T, K, (width, height), (near, far), render
        )
        return rendered
