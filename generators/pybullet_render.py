"""pybullet rendering primitives: OpenCV cameras as OpenGL matrices, depth buffers in mm,
renders cut to the pixel window an object can cover, and meshes written as OBJ files.

Shared by the scene backend (:mod:`bopsurg.generators.pybullet_backend`) and the depth
renderer plugin (:mod:`bopsurg.generators.depth_renderer`); kept apart so that the depth
renderer (every ``bopsurg eval`` with VSD) loads none of the scene machinery. Conventions
are the backend's (see its module docstring): OpenCV intrinsics with pixel centres at integer
coordinates, z-depth in mm, 0 where nothing was hit.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.meshes import ObjectModel

if TYPE_CHECKING:  # typing.Self is Python 3.11+; annotations are not evaluated at run time
    from typing_extensions import Self

F64 = NDArray[np.float64]

#: Principal-point offsets (x, y), px, that make each renderer follow OpenCV's convention.
PIXEL_OFFSETS = {"tiny": (0.0, 1.0), "egl": (0.5, 0.5)}

# OpenCV camera axes (x right, y down, z forward) -> OpenGL ones (y up, z backward).
_CV2GL = np.diag([1.0, -1.0, -1.0, 1.0])


def projection_matrix(
    K: F64, width: int, height: int, near: float, far: float, offset: tuple[float, float]
) -> list[float]:
    """OpenGL projection (column-major, as pybullet wants it) of an OpenCV camera.

    Args:
        K: (3, 3) intrinsics, px.
        width, height: Image size, px.
        near, far: Clipping distances, m.
        offset: Principal-point offset of the renderer, px (:data:`PIXEL_OFFSETS`).
    """
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    ox, oy = offset
    P = np.array(
        [
            [2 * fx / width, -2 * skew / width, 1 - 2 * (cx + ox) / width, 0.0],
            [0.0, 2 * fy / height, 2 * (cy + oy) / height - 1, 0.0],
            [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )
    return P.T.ravel().tolist()


def view_matrix(T_world_cam: F64) -> list[float]:
    """OpenGL view matrix (column-major) of a camera pose with OpenCV axes, m."""
    values: list[float] = (_CV2GL @ np.linalg.inv(T_world_cam)).T.ravel().tolist()
    return values


def depth_buffer_to_mm(
    buffer: NDArray[Any], near: float, far: float, seg: NDArray[Any] | None = None
) -> F64:
    """Camera-frame z (mm) from a [0, 1] depth buffer, 0 on the background.

    Args:
        buffer: Depth buffer from ``getCameraImage``.
        near, far: The projection's clipping distances, m.
        seg: The segmentation buffer of the same render: background is where it is −1. Without
            it, background is where the buffer is within 1e-6 of 1 (TinyRenderer's cleared
            buffer reads 1 − 6e-8 after float32 rounding, not exactly 1).
    """
    d = np.asarray(buffer, dtype=np.float64)
    background = (np.asarray(seg) < 0) if seg is not None else (d >= 1.0 - 1e-6)
    # z = far·near / (far − (far − near)·d), in place (this runs on every frame)
    d *= -(far - near)
    d += far
    z = np.divide(1000.0 * far * near, d, out=d)
    z[background] = 0.0
    return z


def render_window(
    points: F64, T_cam_obj: F64, K: F64, width: int, height: int, near: float
) -> tuple[int, int, int, int] | None:
    """Pixel window ``(u0, v0, u1, v1)`` (end exclusive) that contains an object's projection.

    Args:
        points: (N, 3) points whose convex hull contains the object (its frame), m.
        T_cam_obj: Object pose in the camera, m.
        K: Intrinsics, px.
        width, height: Canvas size, px.
        near: Near clipping distance, m.

    Returns:
        The window clipped to the canvas (the whole canvas when a point is not in front of
        the near plane), or None when the projection misses the canvas.
    """
    P = points @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    if P[:, 2].min() <= near:
        return 0, 0, width, height
    u = K[0, 0] * P[:, 0] / P[:, 2] + K[0, 1] * P[:, 1] / P[:, 2] + K[0, 2]
    v = K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]
    # Pixel centres are at integer coordinates; one pixel of margin against rounding.
    u0 = max(int(np.floor(u.min())) - 1, 0)
    v0 = max(int(np.floor(v.min())) - 1, 0)
    u1 = min(int(np.ceil(u.max())) + 2, width)
    v1 = min(int(np.ceil(v.max())) + 2, height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, v0, u1, v1


#: Renders depth and segmentation buffers of a window: ``(K of the window, width, height)``.
WindowRender = Callable[[F64, int, int], tuple[NDArray[Any], NDArray[Any]]]


def render_window_depth(
    points: F64,
    T_cam_obj: F64,
    K: F64,
    size: tuple[int, int],
    clip: tuple[float, float],
    render: WindowRender,
) -> tuple[F64, tuple[int, int]] | None:
    """Depth (mm) of one object in the pixel window of the canvas that it can cover.

    Args:
        points: (N, 3) points whose convex hull contains the object (its frame), m.
        T_cam_obj: Object pose in the camera, m.
        K: Intrinsics of the canvas, px.
        size: (width, height) of the canvas, px.
        clip: (near, far) clipping distances of the render, m.
        render: Renders the window's buffers; called once, only if the object can be seen.

    Returns:
        The window's z-depth (mm, 0 where the object is absent) and the (row, column) of its
        top-left pixel on the canvas; None when the projection misses the canvas.
    """
    width, height = size
    near, far = clip
    window = render_window(points, T_cam_obj, K, width, height, near)
    if window is None:
        return None
    u0, v0, u1, v1 = window
    Kw = K.copy()
    Kw[0, 2] -= u0
    Kw[1, 2] -= v0
    w, h = u1 - u0, v1 - v0
    depth, seg = render(Kw, w, h)
    mm = depth_buffer_to_mm(
        np.asarray(depth).reshape(h, w), near, far, np.asarray(seg).reshape(h, w)
    )
    return mm, (v0, u0)


def render_in_window(
    points: F64,
    T_cam_obj: F64,
    K: F64,
    size: tuple[int, int],
    clip: tuple[float, float],
    render: WindowRender,
) -> F64:
    """:func:`render_window_depth` pasted on the whole (height, width) canvas (0 elsewhere)."""
    width, height = size
    out = np.zeros((height, width))
    rendered = render_window_depth(points, T_cam_obj, K, size, clip, render)
    if rendered is not None:
        depth, (v0, u0) = rendered
        out[v0 : v0 + depth.shape[0], u0 : u0 + depth.shape[1]] = depth
    return out


class ClosesOnExit:
    """``with`` support and closing on garbage collection, for classes with ``close()``."""

    def close(self) -> None:
        """Release resources (idempotent)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()


def write_obj(
    path: Path, model: ObjectModel, uvs: F64 | None = None, *, double_sided: bool = False
) -> None:
    """Write a model as a Wavefront OBJ in **metres** (pybullet reads meshes from files).

    Mesh files rather than ``createVisualShape(vertices=...)`` arrays: the EGL plugin crashes
    on array meshes, and arrays are limited to about 130k vertices. Nine significant digits
    round-trip float32, which is what pybullet keeps.

    Args:
        path: Output file.
        model: Mesh in mm.
        uvs: (V, 2) texture coordinates, or None.
        double_sided: Also write every triangle with the opposite winding (TinyRenderer culls
            back faces, so a mesh with inconsistent winding would lose faces).
    """
    faces = model.faces
    if double_sided:
        faces = np.concatenate([faces, faces[:, ::-1]])
    lines = [_rows("v", model.pts * 1e-3)]
    if uvs is not None:
        lines.append(_rows("vt", uvs))
    if model.normals is not None:
        lines.append(_rows("vn", model.normals))
    f = faces + 1
    if uvs is not None and model.normals is not None:
        corner = np.repeat(f, 3, axis=1)  # a/a/a: same index for position, uv and normal
        lines.append(_rows("f", corner, "%d/%d/%d %d/%d/%d %d/%d/%d"))
    elif model.normals is not None:
        lines.append(_rows("f", np.repeat(f, 2, axis=1), "%d//%d %d//%d %d//%d"))
    elif uvs is not None:
        lines.append(_rows("f", np.repeat(f, 2, axis=1), "%d/%d %d/%d %d/%d"))
    else:
        lines.append(_rows("f", f, "%d %d %d"))
    path.write_text("".join(lines))


def _rows(tag: str, values: NDArray[Any], fmt: str | None = None) -> str:
    """OBJ lines ``tag v0 v1 ...`` of a 2D array (vectorised formatting)."""
    if len(values) == 0:
        return ""
    fmt = fmt or " ".join(["%.9g"] * values.shape[1])
    template = f"{tag} {fmt}\n"
    return "".join(template * len(values)) % tuple(values.ravel().tolist())
