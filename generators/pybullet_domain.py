"""PyBullet side of ``--domain``: materials of a loaded scene and the suture thread's bodies.

:class:`~bopsurg.generators.pybullet_backend.PyBulletBackend` delegates its
:class:`~bopsurg.generators.domain.DomainBackend` methods here. Nothing here runs for the
default ``paper`` profile, so its renders are unchanged.

Materials change through ``changeVisualShape`` (TinyRenderer multiplies the texture by the
colour, wrapping values above 1, so every multiplier is ≤ 1); a room tinted like the
background (the drape's plane continued, walls and a ceiling 0.4 m out, inside the cameras'
1 m far plane) replaces the renderer's white void in far, tilted and low views.

The thread is a chain of base-only bodies sharing one visual shape: a 6-sided tube of the
thread's radius, 1.3 segments long so that neighbours overlap at bends and small stretches
of the simulated chain leave no gaps. Bodies created after the scene get ids beyond the
backend's instance table, whose last entry (0) maps them to "not annotated".
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import pybullet as p
from numpy.typing import NDArray

from bopsurg.bop.meshes import ObjectModel
from bopsurg.generators.backend import ALL_ARMS
from bopsurg.generators.domain import MARK_COLOURS, Appearance
from bopsurg.generators.pybullet_backend import upload_part, write_obj
from bopsurg.generators.pybullet_scene import (
    MATTE_SPECULAR,
    PAD_THICKNESS,
    VisualPart,
    cylinder_mesh,
    pad_mesh,
    paint_marks,
    skin_texture,
)

F64 = NDArray[np.float64]

#: Overlap of the rendered thread segments: tube length / segment length.
SEGMENT_OVERLAP = 1.3
#: How far below the scene a pad that is not shown is put, m: beyond every camera's far
#: plane (1 m).
HIDDEN_DEPTH_M = 100.0


def _texture(client: int, image: NDArray[np.uint8], folder: Path, key: str) -> int:
    path = folder / f"{key}.png"
    if not cv2.imwrite(str(path), np.ascontiguousarray(image[..., ::-1])):
        raise RuntimeError(f"could not write the texture {path}")
    tex = int(p.loadTexture(str(path), physicsClientId=client))
    if tex < 0:
        raise RuntimeError(f"pybullet could not load the texture {path}")
    return tex


def flat_texture(size: int = 256) -> NDArray[np.uint8]:
    """Plain plastic: light grey (0.84) with a faint fixed grain, (size, size, 3) uint8."""
    grain = np.random.default_rng(12345).normal(0.0, 3.0, (size, size))
    v = np.clip(215.0 + grain, 0, 250).astype(np.uint8)
    return np.repeat(v[..., None], 3, axis=2)


#: The backdrop's grid lines (x and y), mm: a frame from the drape's edge to the walls, which
#: stand this far out. Cameras stay within 0.19 m of the pad's centre horizontally and 0.13 m
#: above it (the ECM's poses, the dolly and the orbit at up to 120 mm from the needle), so
#: all of the room lies nearer than their 1 m far plane: farther geometry would be clipped
#: to the white void.
BACKDROP_LINES = (250.0, 320.0, 400.0)
#: The drape texture's mean colour: the backdrop continues the drape in the distance.
DRAPE_MEAN_RGB = (0.20, 0.47, 0.52)


#: Heights of the backdrop walls' cell rows, mm (from the drape's plane to the ceiling).
BACKDROP_WALL_Z = (-PAD_THICKNESS, 130.0, 260.0, 400.0)


def _quads(corners: NDArray[np.float64], normal: tuple[float, float, float]) -> ObjectModel:
    """Planar quads (4 corners, xyz, cells) mm, in order around each, as two triangles each,
    wound to face ``normal``."""
    first = corners[:, :, 0]
    if np.dot(np.cross(first[1] - first[0], first[2] - first[0]), normal) < 0:
        corners = corners[::-1]
    pts = corners.transpose(2, 0, 1).reshape(-1, 3)
    base = 4 * np.arange(corners.shape[2])[:, None]
    faces = np.concatenate([base + np.array([0, 1, 2]), base + np.array([0, 2, 3])])
    return ObjectModel(pts=pts, faces=faces, normals=np.tile(normal, (len(pts), 1)))


def backdrop_mesh() -> ObjectModel:
    """A room around the scene, mm: a flat square frame around the drape (z = −8 mm) out to
    the walls, facing up, four walls 0.4 m out and a ceiling 0.4 m up, facing in.

    Without it a far, tilted or low view (an orbiting endoscope looks across the tissue)
    sees TinyRenderer's empty (white) background beyond the drape's edge. Cells grow with
    the distance, and none lies under the drape (TinyRenderer pays for every pixel of a
    triangle's screen box, hidden or not).
    """
    lines = np.array(BACKDROP_LINES)
    g = np.concatenate([-lines[::-1], lines])
    x0, y0 = (v.ravel() for v in np.meshgrid(g[:-1], g[:-1]))
    x1, y1 = (v.ravel() for v in np.meshgrid(g[1:], g[1:]))
    outside = (np.abs(x0 + x1) >= 2 * lines[0]) | (np.abs(y0 + y1) >= 2 * lines[0])

    def level(x0: F64, x1: F64, y0: F64, y1: F64, z: float, up: float) -> ObjectModel:
        h = np.full_like(x0, z)
        return _quads(np.stack([[x0, y0, h], [x1, y0, h], [x1, y1, h], [x0, y1, h]]), (0, 0, up))

    parts = [
        level(x0[outside], x1[outside], y0[outside], y1[outside], -PAD_THICKNESS, 1.0),  # floor
        level(x0, x1, y0, y1, BACKDROP_WALL_Z[-1], -1.0),  # ceiling, over everything
    ]
    a0, h0 = (v.ravel() for v in np.meshgrid(g[:-1], BACKDROP_WALL_Z[:-1]))
    a1, h1 = (v.ravel() for v in np.meshgrid(g[1:], BACKDROP_WALL_Z[1:]))
    for sign in (1.0, -1.0):  # walls at x = ±0.4 m and y = ±0.4 m, facing the centre
        w = np.full_like(a0, sign * lines[-1])
        parts.append(
            _quads(np.stack([[w, a0, h0], [w, a1, h0], [w, a1, h1], [w, a0, h1]]), (-sign, 0, 0))
        )
        parts.append(
            _quads(np.stack([[a0, w, h0], [a1, w, h0], [a1, w, h1], [a0, w, h1]]), (0, -sign, 0))
        )
    offsets = np.cumsum([0] + [len(m.pts) for m in parts[:-1]])
    return ObjectModel(
        pts=np.concatenate([m.pts for m in parts]),
        faces=np.concatenate([m.faces + o for m, o in zip(parts, offsets, strict=True)]),
        normals=np.concatenate([m.normals for m in parts]),
    )


def apply_appearance(client: int, bodies: Mapping[str, int], appearance: Appearance) -> None:
    """Set the materials of the scene's bodies (by part name) in ``client``.

    Args:
        client: The scene's pybullet client.
        bodies: Body id by part name (``phantom``, ``drape``, ``needle``, ``psm1_shaft``...).
        appearance: The drawn materials.
    """
    a = appearance
    with tempfile.TemporaryDirectory(prefix="bopsurg_look_") as tmp:
        if a.phantom_surface == "flat":
            image = flat_texture()
        else:
            image = skin_texture(a.phantom_texture_seed, pad_shape=a.phantom_shape)
        if a.phantom_marks is not None:
            m = a.phantom_marks
            image = paint_marks(
                image,
                shape=m.shape,
                size_mm=m.size_mm,
                spacing_mm=m.spacing_mm,
                offset_mm=m.offset_mm,
                rgb=MARK_COLOURS[m.colour],
                pad_shape=a.phantom_shape,
            )
        tex = _texture(client, image, Path(tmp), "phantom")
        phantom = bodies["phantom"]
        if a.phantom_shape != "incisions":
            # pybullet cannot swap a body's mesh: show a pad of this shape and move the
            # scene's own pad (static, never posed again) far below everything
            pad, uvs = pad_mesh(a.phantom_shape)
            white = (1.0, 1.0, 1.0, 1.0)
            part = VisualPart(f"phantom_{a.phantom_shape}", pad, white, MATTE_SPECULAR, uvs=uvs)
            p.resetBasePositionAndOrientation(
                phantom, [0.0, 0.0, -HIDDEN_DEPTH_M], [0, 0, 0, 1], physicsClientId=client
            )
            phantom = upload_part(client, part, Path(tmp))
    p.changeVisualShape(
        phantom,
        -1,
        textureUniqueId=tex,
        rgbaColor=list(a.phantom_rgba),
        physicsClientId=client,
    )
    p.changeVisualShape(
        bodies["drape"], -1, rgbaColor=list(a.background_rgba), physicsClientId=client
    )
    far = [c * t for c, t in zip(DRAPE_MEAN_RGB, a.background_rgba[:3], strict=True)]
    with tempfile.TemporaryDirectory(prefix="bopsurg_look_") as tmp:
        path = Path(tmp) / "backdrop.obj"
        write_obj(path, backdrop_mesh())
        shape = p.createVisualShape(
            p.GEOM_MESH,
            fileName=str(path),
            rgbaColor=[*far, 1.0],
            specularColor=[0.0, 0.0, 0.0],
            physicsClientId=client,
        )
    if shape < 0:
        raise RuntimeError("pybullet could not create the backdrop's visual shape")
    p.createMultiBody(baseMass=0.0, baseVisualShapeIndex=shape, physicsClientId=client)
    p.changeVisualShape(
        bodies["needle"],
        -1,
        rgbaColor=list(a.needle_rgba),
        specularColor=list(a.needle_specular),
        physicsClientId=client,
    )
    looks = {
        "shaft": a.shaft_rgba,
        "wrist": a.metal_rgba,
        "yaw": a.metal_rgba,
        "jaw1": a.jaw_rgba,
        "jaw2": a.jaw_rgba,
    }
    for arm in ALL_ARMS:
        for part, rgba in looks.items():
            name = f"{arm}_{part}"
            if name in bodies:
                p.changeVisualShape(bodies[name], -1, rgbaColor=list(rgba), physicsClientId=client)


def segment_quaternions(directions: F64) -> F64:
    """(N, 4) xyzw quaternions turning +z onto each unit direction (N, 3)."""
    d = directions
    q = np.stack([-d[:, 1], d[:, 0], np.zeros(len(d)), 1.0 + d[:, 2]], axis=1)
    flip = q[:, 3] < 1e-9  # pointing along −z: half a turn about x
    q[flip] = (1.0, 0.0, 0.0, 0.0)
    out: F64 = q / np.linalg.norm(q, axis=1, keepdims=True)
    return out


class ThreadBodies:
    """The thread's bodies in one client, created at the first :meth:`show`.

    Args:
        client: The scene's pybullet client.
    """

    def __init__(self, client: int) -> None:
        self.client = client
        self.bodies: list[int] = []

    def _create(self, n: int, length_mm: float, radius_mm: float, rgba: list[float]) -> None:
        half = 0.5 * SEGMENT_OVERLAP * length_mm
        with tempfile.TemporaryDirectory(prefix="bopsurg_thread_") as tmp:
            path = Path(tmp) / "thread.obj"
            write_obj(path, cylinder_mesh(radius_mm, -half, half, sides=6))
            shape = p.createVisualShape(
                p.GEOM_MESH,
                fileName=str(path),
                rgbaColor=rgba,
                specularColor=[0.2, 0.2, 0.2],
                physicsClientId=self.client,
            )
        if shape < 0:
            raise RuntimeError("pybullet could not create the thread's visual shape")
        self.bodies = [
            p.createMultiBody(baseMass=0.0, baseVisualShapeIndex=shape, physicsClientId=self.client)
            for _ in range(n)
        ]

    def show(self, points: F64, radius_mm: float, rgba: tuple[float, float, float, float]) -> None:
        """Pose the segments along ``points`` (N + 1, 3), m (N fixed after the first call)."""
        pts = np.asarray(points, dtype=np.float64)
        delta = np.diff(pts, axis=0)
        length = np.linalg.norm(delta, axis=1)
        if not self.bodies:
            self._create(len(delta), 1e3 * float(np.median(length)), radius_mm, list(rgba))
        if len(delta) != len(self.bodies):
            raise ValueError(f"the thread has {len(self.bodies)} segments, got {len(delta)}")
        mid = 0.5 * (pts[1:] + pts[:-1])
        quats = segment_quaternions(delta / np.maximum(length, 1e-12)[:, None])
        for body, c, q in zip(self.bodies, mid.tolist(), quats.tolist(), strict=True):
            p.resetBasePositionAndOrientation(body, c, q, physicsClientId=self.client)
