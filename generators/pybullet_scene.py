"""Procedural assets of the suturing scene, built by code (no downloaded meshes).

Everything here is plain numpy: meshes as :class:`~bopsurg.bop.meshes.ObjectModel` in **mm**
(BOP units) in each part's own frame, texture images as uint8 arrays, and part poses in the
world frame in **metres** (ROS / CRTK SI). :mod:`bopsurg.generators.pybullet_backend` uploads
them to pybullet (scaling the vertices by 1e-3), so the same models serve as BOP ``models/``.

The scene (world +Z up, tissue top at z = 0 around the origin, see
:mod:`bopsurg.generators.kinematics`):

- ``needle``: :func:`bopsurg.needle.needle_mesh`, silver-grey, posed by ``T_world_needle``.
- two Large Needle Driver instruments ``psm1`` and ``psm2``, each made of separate rigid
  parts posed from :func:`~bopsurg.generators.kinematics.psm_link_frames`:

  - ``<arm>_shaft``: Ø 8 mm black cylinder in the roll-link frame, along its −z, ending just
    short of the roll-link origin (the wrist pitch axis);
  - ``<arm>_wrist``: the pitch link (clevis), a 13 × 6 × 8 mm metal box in the wrist-pitch
    frame, spanning its +x axis from the pitch axis to beyond the yaw axis (9 mm);
  - ``<arm>_yaw``: the jaw pivot hub, a Ø 4 mm cylinder on the yaw axis (wrist-yaw frame z);
  - ``<arm>_jaw1`` / ``<arm>_jaw2``: 10 mm tapered jaws along the tool-tip frame's +z, rotated
    by ∓jaw/2 about the tip frame's x axis (the yaw axis), so they open symmetrically about
    the tip z axis by the jaw angle; jaw1 lies on the tip frame's +y side.

  With ``instruments="lnd"`` (``generate --domain wide``) the parts keep their frames but
  look closer to the Large Needle Driver: a Ø 8.4 mm shaft, a clevis of two drums (about the
  pitch and the yaw axes) joined by a web, a Ø 4 mm pivot pin, and rounded jaws
  (half-elliptic sections, blunt round tip), see :func:`lnd_instrument_models`.

- ``phantom``: an 80 × 60 × 8 mm suturing pad (top at z = 0) with two raised ridges and three
  incisions, skin-like procedural texture (``--domain wide`` also shows a ``groove`` pad: one
  crease the pad's length between two raised lips, as the AMBF simulator's phantom has,
  :data:`PAD_SHAPES`); ``drape``: a 0.5 m square blue-green drape at the
  pad's bottom (z = −8 mm).

Annotated objects (BOP obj_ids, in this order): ``needle`` = 1, and with instruments
annotated ``psm1_wrist, psm1_jaw1, psm1_jaw2, psm2_wrist, psm2_jaw1, psm2_jaw2`` = 2..7; each
model frame is the part frame above.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.bop.meshes import ObjectModel
from bopsurg.generators.backend import ARMS as ARMS  # re-exported: the default scene's arms
from bopsurg.generators.kinematics import PsmKinematics, SceneLayout, psm_link_frames, rot_x
from bopsurg.needle import NeedleSpec, needle_mesh

F64 = NDArray[np.float64]

#: A scene's arms are ``SceneLayout.arms``, in annotation order; index i is
#: ``SceneLayout.psm_base(i)``.
#: Instrument parts per arm; the annotated ones (with ``annotate_instruments``) are marked.
INSTRUMENT_PARTS = ("shaft", "wrist", "yaw", "jaw1", "jaw2")
ANNOTATED_INSTRUMENT_PARTS = ("wrist", "jaw1", "jaw2")

# Instrument geometry, mm (Large Needle Driver, approximate).
SHAFT_RADIUS = 4.0
SHAFT_LENGTH = 300.0  # longer than the maximal insertion, so it always reaches the RCM
SHAFT_END = -1.5  # the shaft stops just short of the pitch axis, inside the clevis
WRIST_SIZE = (13.0, 6.0, 8.0)  # along the link (x), the yaw axis (y), the pitch axis (z)
WRIST_X0 = -3.0  # the clevis starts 3 mm proximal of the pitch axis
HUB_RADIUS = 2.0
HUB_LENGTH = 5.0
JAW_LENGTH = 10.0
JAW_ROOT = -1.0  # jaws start 1 mm behind the pivot, inside the hub
JAW_WIDTH = (3.0, 1.6)  # along the yaw axis, at the root and at the tip
JAW_THICKNESS = (1.4, 0.6)  # in the opening direction, at the root and at the tip

# Phantom geometry, mm.
PAD_SIZE = (80.0, 60.0)
PAD_THICKNESS = 8.0
RIDGES_Y = (-20.0, 20.0)  # centre lines of the raised ridges (along x)
RIDGE_HEIGHT = 2.5
RIDGE_HALF_WIDTH = 4.0
INCISIONS_X = (-20.0, 0.0, 20.0)  # centre lines of the incisions (along y)
INCISION_HALF_LENGTH = 12.0
INCISION_HALF_WIDTH = 0.6  # at the top; the flat bottom is 0.1 mm narrower on each side
INCISION_DEPTH = 3.0
#: Pad shapes: ``incisions`` (the default above) or ``groove``: a crease of depth
#: GROOVE_DEPTH and half-width GROOVE_HALF_WIDTH along y at x = 0, the pad's whole length,
#: between two lips LIP_HEIGHT high, LIP_OFFSET either side; no ridges, no incisions.
PAD_SHAPES = ("incisions", "groove")
GROOVE_HALF_WIDTH = 1.2
GROOVE_DEPTH = 2.0
LIP_OFFSET = 3.0
LIP_HALF_WIDTH = 2.5
LIP_HEIGHT = 1.5
DRAPE_SIZE = 500.0

# Colours (RGBA in [0, 1]) and specular colours.
NEEDLE_RGBA = (0.78, 0.78, 0.80, 1.0)
SHAFT_RGBA = (0.09, 0.09, 0.10, 1.0)
METAL_RGBA = (0.64, 0.65, 0.67, 1.0)
JAW_RGBA = (0.55, 0.56, 0.58, 1.0)
METAL_SPECULAR = (0.9, 0.9, 0.9)
MATTE_SPECULAR = (0.05, 0.05, 0.05)


@dataclass(frozen=True, eq=False)
class VisualPart:
    """One rigid visual part of the scene.

    Attributes:
        name: Unique part name (``needle``, ``psm1_jaw1``, ``phantom``, ...).
        model: Mesh in mm in the part frame, outward-wound triangles and vertex normals.
        rgba: Colour (multiplies the texture when there is one).
        specular: Specular colour.
        uvs: (V, 2) texture coordinates in [0, 1), or None.
        texture: Key of the part's texture in :attr:`SceneAssets.textures`, or None.
        double_sided: Upload each triangle with both windings (pybullet's TinyRenderer culls
            back faces; meshes whose winding is not consistent would lose faces).
    """

    name: str
    model: ObjectModel
    rgba: tuple[float, float, float, float]
    specular: tuple[float, float, float] = MATTE_SPECULAR
    uvs: F64 | None = None
    texture: str | None = None
    double_sided: bool = False


@dataclass(frozen=True)
class SceneAssets:
    """All parts of a scene, their textures and the annotated objects.

    Attributes:
        parts: The parts, by name.
        textures: (H, W, 3) uint8 RGB images, by key.
        annotated: Names of the annotated objects in BOP obj_id order (obj_id = index + 1).
        layout: Where the robots stand.
    """

    parts: dict[str, VisualPart]
    textures: dict[str, NDArray[np.uint8]]
    annotated: tuple[str, ...]
    layout: SceneLayout = field(default_factory=SceneLayout)


# ----------------------------------------------------------------------------- primitives


def _flat_polygons(polygons: list[F64]) -> ObjectModel:
    """Flat-shaded mesh of convex planar polygons (each (n, 3), counter-clockwise from outside)."""
    pts: list[F64] = []
    faces: list[list[int]] = []
    normals: list[F64] = []
    base = 0
    for poly in polygons:
        poly = np.asarray(poly, dtype=np.float64)
        n = np.cross(poly[1] - poly[0], poly[2] - poly[0])
        n = n / np.linalg.norm(n)
        pts.append(poly)
        normals.append(np.repeat(n[None], len(poly), axis=0))
        faces.extend([base, base + k, base + k + 1] for k in range(1, len(poly) - 1))
        base += len(poly)
    return ObjectModel(
        pts=np.concatenate(pts), faces=np.asarray(faces), normals=np.concatenate(normals)
    )


def _merge(models: list[ObjectModel]) -> ObjectModel:
    """One mesh holding several (vertex indices re-based)."""
    offsets = np.cumsum([0] + [m.n_vertices for m in models[:-1]])
    return ObjectModel(
        pts=np.concatenate([m.pts for m in models]),
        faces=np.concatenate([m.faces + o for m, o in zip(models, offsets, strict=True)]),
        normals=np.concatenate([m.normals for m in models]),  # type: ignore[misc, unused-ignore]
    )


def frustum_mesh(
    z0: float,
    z1: float,
    size0: tuple[float, float],
    size1: tuple[float, float],
    offset0: tuple[float, float] = (0.0, 0.0),
    offset1: tuple[float, float] = (0.0, 0.0),
) -> ObjectModel:
    """Flat-shaded closed hexahedron along z with rectangular ends, mm.

    Args:
        z0, z1: z of the two ends (z0 < z1).
        size0, size1: (x, y) sizes of the ends.
        offset0, offset1: (x, y) centres of the ends.
    """

    def rect(z: float, size: tuple[float, float], off: tuple[float, float]) -> F64:
        hx, hy = 0.5 * size[0], 0.5 * size[1]
        return np.array(
            [
                [off[0] - hx, off[1] - hy, z],
                [off[0] + hx, off[1] - hy, z],
                [off[0] + hx, off[1] + hy, z],
                [off[0] - hx, off[1] + hy, z],
            ]
        )

    a, b = rect(z0, size0, offset0), rect(z1, size1, offset1)
    polys = [a[::-1], b]  # the z0 end faces −z, the z1 end +z
    for k in range(4):
        j = (k + 1) % 4
        polys.append(np.array([a[k], a[j], b[j], b[k]]))
    return _flat_polygons(polys)


def box_mesh(size: ArrayLike, center: ArrayLike = (0.0, 0.0, 0.0)) -> ObjectModel:
    """Flat-shaded box with edge lengths ``size`` (3,) centred at ``center``, mm."""
    sx, sy, sz = np.asarray(size, dtype=np.float64)
    cx, cy, cz = np.asarray(center, dtype=np.float64)
    return frustum_mesh(cz - sz / 2, cz + sz / 2, (sx, sy), (sx, sy), (cx, cy), (cx, cy))


def cylinder_mesh(
    radius: float, z0: float, z1: float, sides: int = 24, max_segment: float | None = None
) -> ObjectModel:
    """Closed cylinder along z from ``z0`` to ``z1``: smooth sides, flat caps, mm.

    Args:
        radius: Radius, mm.
        z0, z1: Ends, mm (z0 < z1).
        sides: Vertices per ring.
        max_segment: Longest side triangle along z, mm (None = one segment). TinyRenderer
            tests every pixel of each triangle's screen bounding box, so long thin triangles
            seen obliquely are slow: split long cylinders.
    """
    n_seg = 1 if max_segment is None else max(1, int(np.ceil((z1 - z0) / max_segment)))
    phi = 2.0 * np.pi * np.arange(sides) / sides
    ring = np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)
    radial = np.concatenate([ring / radius, np.zeros((sides, 1))], axis=1)
    zs = np.linspace(z0, z1, n_seg + 1)
    rings = [np.concatenate([ring, np.full((sides, 1), z)], axis=1) for z in zs]
    j = np.arange(sides)
    k = (j + 1) % sides
    faces = []
    for s in range(n_seg):
        a, b = s * sides, (s + 1) * sides
        faces += [np.stack([a + j, a + k, b + k], 1), np.stack([a + j, b + k, b + j], 1)]
    side = ObjectModel(
        pts=np.concatenate(rings),
        faces=np.concatenate(faces),
        normals=np.tile(radial, (n_seg + 1, 1)),
    )
    caps = _flat_polygons([rings[0][::-1], rings[-1]])
    return _merge([side, caps])


def jaw_mesh(side: int) -> ObjectModel:
    """One tapered jaw in its own frame (pivot at the origin, along +z), mm.

    Args:
        side: +1 for the jaw on the +y side of the closed pair (its grasping face at y = 0),
            −1 for the other one.
    """
    t0, t1 = JAW_THICKNESS
    return frustum_mesh(
        JAW_ROOT,
        JAW_LENGTH,
        (JAW_WIDTH[0], t0),
        (JAW_WIDTH[1], t1),
        (0.0, side * 0.5 * t0),
        (0.0, side * 0.5 * t1),
    )


def instrument_models() -> dict[str, ObjectModel]:
    """Meshes of one instrument's parts (:data:`INSTRUMENT_PARTS`), mm, each in its part frame."""
    sx = WRIST_SIZE[0]
    return {
        "shaft": cylinder_mesh(
            SHAFT_RADIUS, SHAFT_END - SHAFT_LENGTH, SHAFT_END, sides=24, max_segment=4.0
        ),
        "wrist": box_mesh(WRIST_SIZE, (WRIST_X0 + 0.5 * sx, 0.0, 0.0)),
        "yaw": cylinder_mesh(HUB_RADIUS, -0.5 * HUB_LENGTH, 0.5 * HUB_LENGTH, sides=20),
        "jaw1": jaw_mesh(+1),
        "jaw2": jaw_mesh(-1),
    }


# Large Needle Driver look (``SceneSpec.instruments = "lnd"``, used by ``--domain wide``), mm:
# a Ø 8.4 mm shaft, a rounded clevis (drums about the pitch and yaw axes joined by a web),
# rounded jaws (half-elliptic sections tapering to a blunt round tip).
LND_SHAFT_RADIUS = 4.2
LND_SHAFT_END = -4.2  # the shaft's end stays clear of the clevis drum (radius 3.9)
LND_PITCH_DRUM = (3.9, 7.6)  # radius, length along the pitch axis
LND_YAW_DRUM = (2.6, 5.2)  # radius, length along the yaw axis, centred on it
LND_WEB = (5.2, 6.4)  # the web between the drums: size along the yaw axis, the pitch axis
LND_HUB = (2.0, 6.0)  # the jaw pivot pin: radius, length
LND_JAW_LENGTH = 9.5
LND_JAW_WIDTH = (3.4, 1.3)  # across, at the root and near the tip
LND_JAW_THICKNESS = (1.9, 0.7)  # the half-ellipse's height, at the root and near the tip
#: Instrument styles of :func:`instrument_models`.
INSTRUMENT_STYLES = ("simple", "lnd")


def _transformed(model: ObjectModel, R: F64, t: ArrayLike = (0.0, 0.0, 0.0)) -> ObjectModel:
    """The model rotated by R (3×3) and moved by t (mm)."""
    normals = None if model.normals is None else model.normals @ R.T
    return ObjectModel(
        pts=model.pts @ R.T + np.asarray(t, np.float64), faces=model.faces, normals=normals
    )


def rounded_jaw_mesh(side: int, sections: int = 14, arc: int = 10) -> ObjectModel:
    """A Large Needle Driver jaw: half-elliptic sections along +z, blunt round tip, mm.

    The grasping face is the plane y = 0 and the jaw bulges to ``side`` (+1: +y); it starts
    1 mm behind the pivot (z = −1) and ends in a rounded tip at :data:`LND_JAW_LENGTH`.
    The mesh is not consistently wound: upload it double-sided.
    """
    z0, z1 = JAW_ROOT, LND_JAW_LENGTH
    u = np.linspace(0.0, 1.0, sections)
    z = z0 + (z1 - z0) * u
    tip = np.sqrt(np.clip(1.0 - np.clip((u - 0.7) / 0.3, 0.0, 1.0) ** 2, 0.0, 1.0))
    a = 0.5 * (LND_JAW_WIDTH[0] + (LND_JAW_WIDTH[1] - LND_JAW_WIDTH[0]) * u) * tip
    b = (LND_JAW_THICKNESS[0] + (LND_JAW_THICKNESS[1] - LND_JAW_THICKNESS[0]) * u) * tip
    phi = np.linspace(0.0, np.pi, arc)
    cx, sy = np.cos(phi), np.sin(phi)
    ring = np.stack(
        [a[:, None] * cx[None], side * b[:, None] * sy[None], np.repeat(z[:, None], arc, 1)], -1
    )  # (sections, arc, 3)
    nrm = np.stack(
        [
            cx[None] / np.maximum(a[:, None], 1e-3),
            side * sy[None] / np.maximum(b[:, None], 1e-3),
            np.zeros((sections, arc)),
        ],
        -1,
    )
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    i = np.arange(sections - 1)[:, None] * arc
    j = np.arange(arc - 1)[None, :]
    q = (i + j).ravel()
    curved = np.concatenate(
        [np.stack([q, q + 1, q + arc + 1], 1), np.stack([q, q + arc + 1, q + arc], 1)]
    )
    surface = ObjectModel(pts=ring.reshape(-1, 3), faces=curved, normals=nrm.reshape(-1, 3))
    # the flat grasping face: quads between the two edges (phi = 0 and pi) of each section
    edge = np.concatenate([ring[:, 0], ring[:, -1]])
    k = np.arange(sections - 1)
    n = sections
    flat_faces = np.concatenate(
        [np.stack([k, k + 1, n + k + 1], 1), np.stack([k, n + k + 1, n + k], 1)]
    )
    flat = ObjectModel(
        pts=edge, faces=flat_faces, normals=np.tile([0.0, -float(side), 0.0], (2 * n, 1))
    )
    root = _flat_polygons([ring[0]])
    return _merge([surface, flat, root])


def lnd_instrument_models() -> dict[str, ObjectModel]:
    """The parts of a Large Needle Driver (:data:`INSTRUMENT_PARTS`), mm, in their frames.

    Part frames as :func:`instrument_models`: the pitch axis is the wrist frame's z, the yaw
    axis its y at x = 9 mm (:data:`~bopsurg.generators.kinematics.L_PITCH2YAW`).
    """
    to_y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # z -> y
    r_p, l_p = LND_PITCH_DRUM
    r_y, l_y = LND_YAW_DRUM
    web_y, web_z = LND_WEB
    yaw_x = 9.0
    wrist = _merge(
        [
            cylinder_mesh(r_p, -0.5 * l_p, 0.5 * l_p, sides=24),
            box_mesh((yaw_x, web_y, web_z), (0.5 * yaw_x, 0.0, 0.0)),
            _transformed(
                cylinder_mesh(r_y, -0.5 * l_y, 0.5 * l_y, sides=20), to_y, (yaw_x, 0.0, 0.0)
            ),
        ]
    )
    return {
        "shaft": cylinder_mesh(
            LND_SHAFT_RADIUS, LND_SHAFT_END - SHAFT_LENGTH, LND_SHAFT_END, sides=24, max_segment=4.0
        ),
        "wrist": wrist,
        "yaw": cylinder_mesh(LND_HUB[0], -0.5 * LND_HUB[1], 0.5 * LND_HUB[1], sides=16),
        "jaw1": rounded_jaw_mesh(+1),
        "jaw2": rounded_jaw_mesh(-1),
    }


def instrument_part_poses(
    q: ArrayLike, jaw: float, T_world_base: F64, kinematics: PsmKinematics | None = None
) -> dict[str, F64]:
    """World poses (4×4, m) of one instrument's part frames.

    Args:
        q: (6,) PSM joints (rad, insertion in m).
        jaw: Jaw opening angle, rad (total angle between the jaws).
        T_world_base: ``T_world_base`` of the arm (its RCM frame).
        kinematics: The PSM and tool (default: the simulator's).

    Returns:
        ``T_world_part`` by part name (:data:`INSTRUMENT_PARTS`).
    """
    frames = psm_link_frames(q, kinematics)
    roll, pitch, yaw, tip = (T_world_base @ frames[k] for k in (3, 4, 5, 6))
    half = np.eye(4)
    half[:3, :3] = rot_x(-0.5 * jaw)
    jaw1 = tip @ half
    half[:3, :3] = rot_x(0.5 * jaw)
    jaw2 = tip @ half
    return {"shaft": roll, "wrist": pitch, "yaw": yaw, "jaw1": jaw1, "jaw2": jaw2}


# ------------------------------------------------------------------------------ phantom


def _check_pad_shape(shape: str) -> None:
    if shape not in PAD_SHAPES:
        raise ValueError(f"unknown pad shape {shape!r}; expected one of {PAD_SHAPES}")


def pad_cuts(shape: str = "incisions") -> tuple[tuple[float, ...], float]:
    """Where a pad is cut: the x (mm) of each cut's centre line (cuts run along y) and their
    half-length (mm): the incisions, or the groove (the pad's whole length)."""
    _check_pad_shape(shape)
    if shape == "groove":
        return (0.0,), 0.5 * PAD_SIZE[1]
    return INCISIONS_X, INCISION_HALF_LENGTH


def pad_height(x: ArrayLike, y: ArrayLike, shape: str = "incisions") -> F64:
    """Height (mm) of the pad's top surface above z = 0 at (x, y) mm (ridges and lips +,
    incisions and the groove −) for a pad of ``shape`` (:data:`PAD_SHAPES`)."""
    _check_pad_shape(shape)
    x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    h = 0.25 * np.sin(x / 6.3 + 0.7) * np.sin(y / 5.1 + 0.3)  # gentle undulation

    def bump(d: F64) -> F64:  # raised cosine of unit height on |d| < 1
        return np.where(np.abs(d) < 1.0, 0.5 * (1.0 + np.cos(np.pi * np.clip(d, -1, 1))), 0.0)

    if shape == "groove":
        for xc in (-LIP_OFFSET, LIP_OFFSET):
            h = h + LIP_HEIGHT * bump((x - xc) / LIP_HALF_WIDTH)
        return h - GROOVE_DEPTH * bump(x / GROOVE_HALF_WIDTH)
    for yc in RIDGES_Y:
        h = h + RIDGE_HEIGHT * bump((y - yc) / RIDGE_HALF_WIDTH)
    # Incisions: flat-bottomed slots with walls 0.1 mm wide, so nearly vertical.
    along = np.clip((INCISION_HALF_LENGTH - np.abs(y)) / 0.1, 0.0, 1.0)
    for xc in INCISIONS_X:
        across = np.clip((INCISION_HALF_WIDTH - np.abs(x - xc)) / 0.1, 0.0, 1.0)
        h = h - INCISION_DEPTH * across * along
    return h


def _pad_grid(shape: str = "incisions") -> tuple[F64, F64]:
    """Grid lines (x, y), mm: 1 mm spacing, finer on the ridges or the lips and the groove,
    and on every incision edge."""
    hx, hy = 0.5 * PAD_SIZE[0], 0.5 * PAD_SIZE[1]
    xs = [np.arange(-hx, hx + 1e-9, 1.0)]
    ys = [np.arange(-hy, hy + 1e-9, 1.0)]
    if shape == "groove":
        reach = LIP_OFFSET + LIP_HALF_WIDTH
        xs.append(np.arange(-reach, reach + 1e-9, 0.25))
    else:
        for xc in INCISIONS_X:
            w = INCISION_HALF_WIDTH
            xs.append(np.array([xc - w, xc - w + 0.1, xc + w - 0.1, xc + w]))
        for yc in RIDGES_Y:
            ys.append(np.arange(yc - RIDGE_HALF_WIDTH, yc + RIDGE_HALF_WIDTH + 1e-9, 0.5))
        ys.append(np.array([-INCISION_HALF_LENGTH, -INCISION_HALF_LENGTH + 0.1]))
        ys.append(np.array([INCISION_HALF_LENGTH - 0.1, INCISION_HALF_LENGTH]))
    # Unique to 1 µm (floating-point twins would make degenerate triangles).
    gx: F64 = np.unique(np.round(np.concatenate(xs), 6)).astype(np.float64, copy=False)
    gy: F64 = np.unique(np.round(np.concatenate(ys), 6)).astype(np.float64, copy=False)
    return gx, gy


def pad_mesh(shape: str = "incisions") -> tuple[ObjectModel, F64]:
    """The suturing pad: textured top height field plus side walls (no bottom), mm.

    Args:
        shape: One of :data:`PAD_SHAPES`.

    Returns:
        The mesh in the world frame (the pad is static) and its (V, 2) texture coordinates.

    Raises:
        ValueError: An unknown shape.
    """
    _check_pad_shape(shape)
    gx, gy = _pad_grid(shape)
    xx, yy = np.meshgrid(gx, gy)  # (ny, nx)
    zz = pad_height(xx, yy, shape)
    dzdy, dzdx = np.gradient(zz, gy, gx)
    n = np.stack([-dzdx, -dzdy, np.ones_like(zz)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    ny, nx = xx.shape
    hx, hy = 0.5 * PAD_SIZE[0], 0.5 * PAD_SIZE[1]
    top_pts = np.stack([xx, yy, zz], axis=-1).reshape(-1, 3)
    top_uv = np.stack([(xx + hx) / (2 * hx), (yy + hy) / (2 * hy)], axis=-1).reshape(-1, 2)
    idx = np.arange(ny * nx).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    top_faces = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    )
    top = ObjectModel(pts=top_pts, faces=top_faces, normals=n.reshape(-1, 3))

    # Side walls: the boundary of the height field, straight down to the pad's bottom.
    walls, wall_uvs = [], []
    edges = (
        (top_pts[idx[0, :]], np.array([0.0, -1.0, 0.0])),  # y = -hy, outward −y
        (top_pts[idx[:, -1]], np.array([1.0, 0.0, 0.0])),  # x = +hx
        (top_pts[idx[-1, ::-1]], np.array([0.0, 1.0, 0.0])),  # y = +hy
        (top_pts[idx[::-1, 0]], np.array([-1.0, 0.0, 0.0])),  # x = -hx
    )
    for upper, normal in edges:
        lower = upper.copy()
        lower[:, 2] = -PAD_THICKNESS
        m = len(upper)
        j = np.arange(m - 1)
        faces = np.concatenate(
            [np.stack([j, m + j, m + j + 1], 1), np.stack([j, m + j + 1, j + 1], 1)]
        )
        walls.append(
            ObjectModel(
                pts=np.concatenate([upper, lower]),
                faces=faces,
                normals=np.repeat(normal[None], 2 * m, axis=0),
            )
        )
        s = np.linspace(0.0, 0.999, m)
        wall_uvs.append(
            np.concatenate([np.stack([s, np.full(m, 0.02)], 1), np.stack([s, np.full(m, 0.1)], 1)])
        )
    model = _merge([top, *walls])
    uvs = np.clip(np.concatenate([top_uv, *wall_uvs]), 0.0, 0.999)
    return model, uvs


def drape_mesh(cells: int = 25) -> tuple[ObjectModel, F64]:
    """The drape: a square grid at the pad's bottom (z = −8 mm), facing up, mm, with uvs.

    Args:
        cells: Grid cells per side. Small triangles keep TinyRenderer fast (it tests every
            pixel of a triangle's screen bounding box, twice when the triangle is clipped).
    """
    h = 0.5 * DRAPE_SIZE
    g = np.linspace(-h, h, cells + 1)
    xx, yy = np.meshgrid(g, g)
    pts = np.stack([xx, yy, np.full_like(xx, -PAD_THICKNESS)], axis=-1).reshape(-1, 3)
    idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    )
    model = ObjectModel(pts=pts, faces=faces, normals=np.tile([0.0, 0.0, 1.0], (len(pts), 1)))
    uvs = np.clip((pts[:, :2] + h) / (2 * h), 0.0, 0.999)
    return model, uvs


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> F64:
    """Gaussian-filtered white noise with unit standard deviation."""
    n = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
    return (n / max(float(n.std()), 1e-6)).astype(np.float64)


def _frozen(a: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Read-only, so a cached texture cannot be changed by a caller."""
    a.flags.writeable = False
    return a


@functools.lru_cache(maxsize=4)  # a backend per replay: build each texture once per process
def skin_texture(
    seed: int = 0, size: tuple[int, int] = (1024, 768), pad_shape: str = "incisions"
) -> NDArray[np.uint8]:
    """Pink-red tissue texture of the pad top, (H, W, 3) uint8 RGB.

    Column c maps to texture u = c / W and row r to v = 1 − r / H (OpenGL's convention, which
    pybullet follows: the image's top row is v = 1), i.e. to pad coordinates
    x = (u − 0.5) · 80 mm, y = (v − 0.5) · 60 mm.

    Args:
        seed: Seed of the noise and the vessel pattern.
        size: (width, height) in texels.
        pad_shape: The pad it covers (:data:`PAD_SHAPES`), whose cuts are painted dark.
    """
    rng = np.random.default_rng(seed)
    w, h = size
    shade = (
        1.0
        + 0.05 * _smooth_noise(rng, (h, w), 60)
        + 0.04 * _smooth_noise(rng, (h, w), 15)
        + 0.03 * _smooth_noise(rng, (h, w), 3)
        + 0.02 * rng.standard_normal((h, w))
    )
    # Redness varies over the pad: more saturated (less green/blue) patches.
    red = np.clip(0.5 + 0.35 * _smooth_noise(rng, (h, w), 30), 0.0, 1.0)
    img = np.empty((h, w, 3))
    img[..., 0] = (0.88 + 0.04 * red) * shade
    img[..., 1] = (0.60 - 0.16 * red) * shade
    img[..., 2] = (0.58 - 0.14 * red) * shade
    # Capillaries: random-walk curves in dark red, softened.
    vessels = np.zeros((h, w), np.float32)
    for _ in range(14):
        p = rng.uniform([0, 0], [w, h])
        ang = rng.uniform(0, 2 * np.pi)
        pts = []
        for _ in range(int(rng.integers(20, 60))):
            ang += rng.normal(0.0, 0.25)
            p = p + 8.0 * np.array([np.cos(ang), np.sin(ang)])
            pts.append(p.copy())
        width = int(rng.integers(1, 4))
        cv2.polylines(vessels, [np.asarray(pts, np.int32)], False, 1.0, width, cv2.LINE_AA)
    vessels = cv2.GaussianBlur(vessels, (0, 0), 1.2)[..., None].astype(np.float64)
    img = img * (1 - 0.45 * vessels) + 0.45 * vessels * np.array([0.55, 0.12, 0.15])
    # Incisions (or the groove): dark red walls and bottoms.
    x = (np.arange(w) + 0.5) / w * PAD_SIZE[0] - 0.5 * PAD_SIZE[0]
    y = 0.5 * PAD_SIZE[1] - (np.arange(h) + 0.5) / h * PAD_SIZE[1]  # row 0 is the +y edge
    cut = pad_height(x[None, :], y[:, None], pad_shape) < -0.5
    img[cut] = img[cut] * 0.35 + 0.65 * np.array([0.45, 0.10, 0.11])
    return _frozen((np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))


#: Shapes of the suture targets that :func:`paint_marks` paints.
MARK_SHAPES = ("square", "diamond", "dot")


def paint_marks(
    image: NDArray[np.uint8],
    *,
    shape: str,
    size_mm: float,
    spacing_mm: float,
    offset_mm: float,
    rgb: tuple[float, float, float],
    pad_shape: str = "incisions",
) -> NDArray[np.uint8]:
    """The pad texture ``image`` with suture targets painted on either side of each cut (the
    incisions, or the groove of a ``groove`` pad).

    Training pads (and the AMBF simulator's phantom) mark where a stitch enters and leaves:
    pairs of coloured squares or dots ``offset_mm`` either side of the cut, every
    ``spacing_mm`` along it, over the cut's length and one spacing beyond. They are
    strong, needle-sized distractors for a detector that never saw them.

    Args:
        image: (H, W, 3) uint8 RGB pad texture, mapped onto the whole 80 × 60 mm top as
            :func:`skin_texture` describes (any size: texels need not be square).
        shape: One of :data:`MARK_SHAPES`.
        size_mm: Side (square, diamond) or diameter (dot), mm.
        spacing_mm: Distance between neighbouring targets along the cut, mm.
        offset_mm: Distance of a target's centre from the cut's centre line, mm.
        rgb: Colour in [0, 1]; the texture's shading shows through a little.
        pad_shape: The pad's shape (:data:`PAD_SHAPES`): where its cuts are (:func:`pad_cuts`).

    Raises:
        ValueError: An unknown shape or pad shape, or a size, spacing or offset that is not
            positive.
    """
    if shape not in MARK_SHAPES:
        raise ValueError(f"unknown mark shape {shape!r}; expected one of {MARK_SHAPES}")
    if not min(size_mm, spacing_mm, offset_mm) > 0:
        raise ValueError("mark size, spacing and offset must be positive (mm)")
    h, w = image.shape[:2]
    sx, sy = w / PAD_SIZE[0], h / PAD_SIZE[1]  # texels per mm
    cuts, half_length = pad_cuts(pad_shape)
    n = int((half_length + spacing_mm) // spacing_mm)
    ys = spacing_mm * np.arange(-n, n + 1)
    centres = np.array([(xc + side * offset_mm, y) for xc in cuts for side in (-1, 1) for y in ys])
    # Unit outline of one target (mm, about its centre), then every target at once.
    r = 0.5 * size_mm
    if shape == "dot":
        a = np.linspace(0.0, 2 * np.pi, 32, endpoint=False)
        outline = r * np.stack([np.cos(a), np.sin(a)], axis=1)
    elif shape == "square":
        outline = r * np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    else:
        outline = r * np.sqrt(2.0) * np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    pts = centres[:, None, :] + outline[None]  # (targets, corners, 2) mm
    # Coverage by 4 x 4 supersampling: cv2's antialiased fill paints about half a texel too
    # much. On the fine grid, texel c spans [c, c + 1) and cv2 puts a pixel's centre at c.
    k = 4
    cols = (pts[..., 0] + 0.5 * PAD_SIZE[0]) * (k * sx) - 0.5
    rows = (0.5 * PAD_SIZE[1] - pts[..., 1]) * (k * sy) - 0.5  # row 0 is the +y edge
    shift = 4  # cv2's fixed-point fraction bits
    poly = np.round(np.stack([cols, rows], axis=-1) * (1 << shift)).astype(np.int32)
    fine = np.zeros((k * h, k * w), np.uint8)
    cv2.fillPoly(fine, list(poly), 255, cv2.LINE_8, shift)
    cover = cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA)
    alpha = cover[..., None].astype(np.float64) / 255.0
    base = image.astype(np.float64) / 255.0
    shade = base.mean(axis=2, keepdims=True) / max(float(base.mean()), 1e-6)
    mark = np.asarray(rgb, np.float64) * (0.85 + 0.15 * shade)
    out = base * (1.0 - alpha) + alpha * mark
    painted: NDArray[np.uint8] = (np.clip(out, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return painted


@functools.lru_cache(maxsize=4)
def drape_texture(seed: int = 0, size: int = 1024) -> NDArray[np.uint8]:
    """Blue-green surgical drape texture, (size, size, 3) uint8 RGB (weave and folds)."""
    rng = np.random.default_rng(seed + 1)
    i = np.arange(size)
    weave = 0.5 * (np.cos(np.pi * i)[:, None] + np.cos(np.pi * i)[None, :])
    shade = (
        1.0
        + 0.10 * _smooth_noise(rng, (size, size), 40)
        + 0.03 * weave
        + 0.03 * rng.standard_normal((size, size))
    )
    img = np.array([0.20, 0.47, 0.52])[None, None, :] * shade[..., None]
    return _frozen((np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))


# -------------------------------------------------------------------------------- scene


def build_scene(
    needle: NeedleSpec | None = None,
    layout: SceneLayout | None = None,
    *,
    annotate_instruments: bool = False,
    texture_seed: int = 0,
    instruments: str = "simple",
) -> SceneAssets:
    """All parts of the suturing scene.

    Args:
        needle: Needle geometry (default :class:`~bopsurg.needle.NeedleSpec`).
        layout: Robot layout (default :class:`~bopsurg.generators.kinematics.SceneLayout`).
        annotate_instruments: Also annotate the instruments' wrists and jaws.
        texture_seed: Seed of the procedural textures.
        instruments: :data:`INSTRUMENT_STYLES`: ``simple`` (boxes) or ``lnd`` (the Large
            Needle Driver's rounded clevis and jaws, :func:`lnd_instrument_models`).

    Raises:
        ValueError: An unknown instrument style.
    """
    if instruments not in INSTRUMENT_STYLES:
        raise ValueError(
            f"unknown instruments {instruments!r}; expected one of {INSTRUMENT_STYLES}"
        )
    layout = layout or SceneLayout()
    parts: dict[str, VisualPart] = {}
    # The needle mesh is consistently wound outwards, so back-face culling loses nothing.
    parts["needle"] = VisualPart("needle", needle_mesh(needle), NEEDLE_RGBA, METAL_SPECULAR)
    looks = {
        "shaft": (SHAFT_RGBA, MATTE_SPECULAR),
        "wrist": (METAL_RGBA, METAL_SPECULAR),
        "yaw": (METAL_RGBA, METAL_SPECULAR),
        "jaw1": (JAW_RGBA, METAL_SPECULAR),
        "jaw2": (JAW_RGBA, METAL_SPECULAR),
    }
    for arm in layout.arms:
        models = instrument_models() if instruments == "simple" else lnd_instrument_models()
        for part, model in models.items():
            rgba, spec = looks[part]
            two = instruments == "lnd"  # merged shells and lofts: not consistently wound
            parts[f"{arm}_{part}"] = VisualPart(
                f"{arm}_{part}", model, rgba, spec, double_sided=two
            )
    pad, pad_uv = pad_mesh()
    parts["phantom"] = VisualPart(
        "phantom", pad, (1.0, 1.0, 1.0, 1.0), MATTE_SPECULAR, uvs=pad_uv, texture="skin"
    )
    drape, drape_uv = drape_mesh()
    parts["drape"] = VisualPart(
        "drape", drape, (1.0, 1.0, 1.0, 1.0), MATTE_SPECULAR, uvs=drape_uv, texture="drape"
    )
    annotated = ["needle"]
    if annotate_instruments:
        annotated += [f"{arm}_{part}" for arm in layout.arms for part in ANNOTATED_INSTRUMENT_PARTS]
    textures = {"skin": skin_texture(texture_seed), "drape": drape_texture(texture_seed)}
    return SceneAssets(parts=parts, textures=textures, annotated=tuple(annotated), layout=layout)


def part_poses(
    layout: SceneLayout,
    psm_joints: Mapping[str, ArrayLike],
    jaws: Mapping[str, float],
    needle_pose: F64 | None = None,
) -> dict[str, F64]:
    """World poses (4×4, m) of the moving parts for a robot state.

    Args:
        layout: Robot layout.
        psm_joints: (6,) joints by arm name (``layout.arms``); arms missing here are left out.
        jaws: Jaw angle by arm name, rad (0 when missing).
        needle_pose: ``T_world_needle``, or None to leave the needle out.

    Raises:
        ValueError: An unknown arm name.
    """
    out: dict[str, F64] = {}
    for arm, q in psm_joints.items():
        base = layout.arm_base(arm)
        poses = instrument_part_poses(q, float(jaws.get(arm, 0.0)), base, layout.kinematics)
        out.update({f"{arm}_{k}": v for k, v in poses.items()})
    if needle_pose is not None:
        out["needle"] = np.asarray(needle_pose, dtype=np.float64)
    return out
