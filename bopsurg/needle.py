"""A suturing needle built by code: a tube swept along a circular arc with a tapered tip.

The needle lies in the model XY plane, its centre line on a circle of radius
``arc_radius`` around the model origin; the body starts at the swaged tail on the +X axis and
runs counter-clockwise (towards +Y) for ``body_deg`` degrees, then tapers to a point over
``tip_deg`` degrees. The tail is a slightly thicker, flat-ended swage (where the suture is
crimped), so tip and tail are distinguishable in shape. Units: mm.

Defaults follow the paper's needle (surgical_scene_facts): centre-line radius 10.18 mm, wire
Ø 0.72 mm, ≈120° body plus tip, BOP diameter ≈ 18.65 mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bopsurg.bop.meshes import ObjectModel


@dataclass(frozen=True)
class NeedleSpec:
    """Needle geometry, mm and degrees.

    Attributes:
        arc_radius: Radius of the centre line.
        wire_diameter: Diameter of the wire body.
        body_deg: Arc of the full-diameter body, from the tail.
        tip_deg: Arc over which the wire tapers to the point.
        swage_deg: Arc of the thicker swaged tail.
        swage_scale: Swage diameter / wire diameter.
        rings: Cross-sections along the arc.
        sides: Vertices per cross-section.
    """

    arc_radius: float = 10.18
    wire_diameter: float = 0.72
    body_deg: float = 120.0
    tip_deg: float = 8.5
    swage_deg: float = 8.0
    swage_scale: float = 1.15
    rings: int = 96
    sides: int = 12

    @property
    def total_deg(self) -> float:
        """Whole arc, tail to tip."""
        return self.body_deg + self.tip_deg

    @classmethod
    def circle_fraction(cls, fraction: float, **kwargs: float) -> NeedleSpec:
        """A needle spanning ``fraction`` of a circle (3/8 → 135°, 1/2 → 180°) incl. its tip."""
        tip = float(kwargs.pop("tip_deg", cls.tip_deg))
        return cls(body_deg=360.0 * fraction - tip, tip_deg=tip, **kwargs)  # type: ignore[arg-type]


def needle_centerline(spec: NeedleSpec, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre-line points and unit tangents at arc angles ``s`` (radians), each (n, 3)."""
    c, sn = np.cos(s), np.sin(s)
    pts = np.stack([spec.arc_radius * c, spec.arc_radius * sn, np.zeros_like(s)], axis=1)
    tangents = np.stack([-sn, c, np.zeros_like(s)], axis=1)
    return pts, tangents


def needle_radius_profile(spec: NeedleSpec, s_deg: np.ndarray) -> np.ndarray:
    """Wire radius (mm) at arc angles ``s_deg`` (degrees from the tail)."""
    r = np.full_like(s_deg, 0.5 * spec.wire_diameter, dtype=np.float64)
    r[s_deg < spec.swage_deg] *= spec.swage_scale
    tip = s_deg > spec.body_deg
    frac = (s_deg[tip] - spec.body_deg) / spec.tip_deg
    r[tip] *= np.clip(1.0 - frac, 0.0, 1.0)
    return r


def needle_mesh(spec: NeedleSpec | None = None) -> ObjectModel:
    """Closed triangle mesh of the needle (vertices, faces, outward normals), mm.

    Returns:
        The model; vertex 0 is the tail-cap centre and the last vertex the tip point.
    """
    spec = spec or NeedleSpec()
    # Denser rings near the tip, where the radius changes fast.
    body = np.linspace(0.0, spec.body_deg, spec.rings - spec.rings // 6, endpoint=False)
    tip = np.linspace(spec.body_deg, spec.total_deg, spec.rings // 6 + 1)[:-1]
    s_deg = np.concatenate([body, tip])
    # Step at the swage shoulder: a second ring at the same angle makes the shoulder flat.
    shoulder = np.searchsorted(s_deg, spec.swage_deg)
    s_deg = np.insert(s_deg, shoulder, spec.swage_deg - 1e-6)
    s = np.deg2rad(s_deg)
    centers, tangents = needle_centerline(spec, s)
    radial = centers / np.linalg.norm(centers, axis=1, keepdims=True)  # in-plane, outward
    normal = np.cross(tangents, radial)  # +Z for a counter-clockwise arc
    phi = 2.0 * np.pi * np.arange(spec.sides) / spec.sides
    cos_p, sin_p = np.cos(phi), np.sin(phi)
    dirs = radial[:, None, :] * cos_p[None, :, None] + normal[:, None, :] * sin_p[None, :, None]
    radius = needle_radius_profile(spec, s_deg)
    ring_pts = centers[:, None, :] + radius[:, None, None] * dirs  # (rings, sides, 3)

    n_rings, n_sides = ring_pts.shape[:2]
    tip_pt, _ = needle_centerline(spec, np.deg2rad(np.array([spec.total_deg])))
    vertices = np.concatenate([centers[:1], ring_pts.reshape(-1, 3), tip_pt], axis=0)
    normals = np.concatenate([-tangents[:1], dirs.reshape(-1, 3), tangents[-1:]], axis=0)

    ring = 1 + np.arange(n_rings)[:, None] * n_sides  # first vertex id of each ring
    j = np.arange(n_sides)[None, :]
    a = (ring[:-1] + j).ravel()
    b = (ring[:-1] + (j + 1) % n_sides).ravel()
    c = (ring[1:] + j).ravel()
    d = (ring[1:] + (j + 1) % n_sides).ravel()
    side_faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    tail = np.stack([np.zeros(n_sides, int), 1 + (j.ravel() + 1) % n_sides, 1 + j.ravel()], 1)
    last = ring[-1, 0]
    tip_id = vertices.shape[0] - 1
    tip_faces = np.stack(
        [last + j.ravel(), last + (j.ravel() + 1) % n_sides, np.full(n_sides, tip_id)], 1
    )
    # Side quads are built inward-facing (rings run counter-clockwise seen from +Z): reverse
    # them; the caps are already outward. Renderers that cull back faces need this right.
    faces = np.concatenate([tail, side_faces[:, ::-1], tip_faces]).astype(np.int64)
    return ObjectModel(pts=vertices, faces=faces, normals=normals)


def needle_keypoints(model: ObjectModel) -> dict[str, Any]:
    """``models_info`` extras of a :func:`needle_mesh` model: tip, tail (mm) and plane normal.

    Used by the ambiguity analysis (``bopsurg.evaluation.ambiguity``); BOP readers ignore
    unknown models_info keys.
    """
    return {
        "keypoints": {"tip": model.pts[-1].tolist(), "tail": model.pts[0].tolist()},
        "plane_normal": [0.0, 0.0, 1.0],
    }
