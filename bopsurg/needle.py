"""A suturing needle built by code: a tube swept along a circular arc with a tapered tip.

The needle lies in the model XY plane, its centre line on a circle of radius
``arc_radius`` around the model origin; the body starts at the swaged tail on the +X axis and
runs counter-clockwise (towards +Y) for ``body_deg`` degrees, then tapers to a point over
``tip_deg`` degrees. The tail is a slightly thicker, flat-ended swage (where the suture is
crimped), so tip and tail are distinguishable in shape. Units: mm.

Defaults follow the paper's needle: centre-line radius 10.18 mm, wire Ø 0.72 mm, ≈120° body
plus tip, BOP diameter ≈ 18.65 mm.

:func:`fit_needle` goes the other way: it finds the arc (centre, normal, radius, extent, tip
and tail) of any needle mesh in its own model frame, so a user's CAD needle can stand in for
this one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bopsurg.bop.meshes import ObjectModel, compute_model_info
from bopsurg.errors import ModelError


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


# --------------------------------------------------------------------------- arc fitting

#: A needle's wire is thin next to its arc: the largest tube radius accepted, as a fraction
#: of the arc radius (the paper's needle: 0.36 / 10.18 = 0.035).
MAX_TUBE_FRACTION = 0.2
#: Arcs shorter than this cannot fix a circle well; a full ring has no tip or tail.
MIN_EXTENT_DEG, MAX_EXTENT_DEG = 30.0, 340.0
#: Fraction of the arc at each end where the wire's thickness tells the tip from the tail.
_END_FRACTION = 0.06
#: The tip end must be at most this fraction as thick as the tail end.
_TAPER_RATIO = 0.8


@dataclass(frozen=True)
class NeedleArc:
    """The arc of a needle in its model frame (mm, radians where not said otherwise).

    Attributes:
        center: (3,) centre of the centre-line circle.
        normal: (3,) unit normal of the needle plane, oriented so that the arc runs
            counter-clockwise about it from the tail to the tip (as in :func:`needle_mesh`,
            whose normal is +Z).
        radius: Radius of the centre line.
        extent_deg: Arc angle from the tail to the tip, degrees.
        tip: (3,) tip point: the centre line's end at the pointed end.
        tail: (3,) tail point: the centre line's end at the blunt (swaged) end.
        wire_radius: Median distance of the surface from the centre line.
        rms_mm: RMS distance of the vertices from the fitted tube (a fit-quality figure).
    """

    center: np.ndarray
    normal: np.ndarray
    radius: float
    extent_deg: float
    tip: np.ndarray
    tail: np.ndarray
    wire_radius: float
    rms_mm: float

    def frame(self) -> tuple[np.ndarray, np.ndarray]:
        """The arc's own frame in model coordinates: ``x_model = R @ x_arc + t``.

        In the arc frame the needle lies as :func:`needle_mesh` builds it: centre at the
        origin, plane z = 0, tail on +X, the arc running counter-clockwise (towards +Y) to
        the tip at ``extent_deg``.
        """
        x = self.tail - self.center
        x = x / np.linalg.norm(x)
        R = np.stack([x, np.cross(self.normal, x), self.normal], axis=1)
        return R, self.center.copy()

    def middle_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`frame`, turned about the normal so that +X points at the arc's middle.

        Two needles of slightly different extent overlap best when their middles coincide.
        """
        R, t = self.frame()
        a = 0.5 * np.deg2rad(self.extent_deg)
        c, s = np.cos(a), np.sin(a)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return R @ Rz, t


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors that span the plane orthogonal to ``normal``."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def fit_circle(x: np.ndarray, y: np.ndarray, iterations: int = 50) -> tuple[float, float, float]:
    """Circle (centre a, b and radius) through 2D points, least squares in the distances.

    Kåsa's algebraic fit (x² + y² = 2ax + 2by + c, linear) starts Gauss-Newton on the
    geometric residuals |p − c| − r: the algebraic fit alone is biased on a partial arc
    (0.1 mm on a 10 mm needle), the geometric one is not for a tube's symmetric surface.
    ``iterations=0`` gives the algebraic fit (for points with outliers, which the plain
    geometric least squares would follow).
    """
    A = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=1)
    (a, b, c), *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    r = float(np.sqrt(max(c + a * a + b * b, 0.0)))
    for _ in range(iterations):
        dx, dy = x - a, y - b
        d = np.maximum(np.hypot(dx, dy), 1e-12)
        jac = np.stack([-dx / d, -dy / d, -np.ones_like(d)], axis=1)
        step, *_ = np.linalg.lstsq(jac, -(d - r), rcond=None)
        a, b, r = a + step[0], b + step[1], r + step[2]
        if np.abs(step).max() < 1e-12 * max(r, 1.0):
            break
    return float(a), float(b), float(r)


def _needle_points(model: ObjectModel | np.ndarray, name: str) -> np.ndarray:
    """The (V, 3) float64 vertices of ``model``, checked: at least 10, all finite."""
    pts = np.asarray(model.pts if isinstance(model, ObjectModel) else model, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 10 or not np.isfinite(pts).all():
        raise ModelError(
            f"not a needle: expected (V >= 10, 3) finite vertices, got {pts.shape}", path=name
        )
    return pts


def _arc_span(angle: np.ndarray, name: str) -> tuple[float, float]:
    """``(start, extent)``, rad, of the arc the vertices' in-plane angles cover: the circle
    minus the largest angular gap between them, starting after that gap."""
    theta = np.sort(np.mod(angle, 2 * np.pi))
    gaps = np.diff(np.concatenate([theta, theta[:1] + 2 * np.pi]))
    k = int(np.argmax(gaps))
    start = float(theta[(k + 1) % len(theta)])  # first angle after the largest gap
    extent = 2 * np.pi - float(gaps[k])
    extent_deg = float(np.rad2deg(extent))
    if not MIN_EXTENT_DEG <= extent_deg <= MAX_EXTENT_DEG:
        raise ModelError(
            f"not a needle: its arc spans {extent_deg:.0f}°, expected "
            f"{MIN_EXTENT_DEG:.0f}–{MAX_EXTENT_DEG:.0f}° (an open arc with a tip and a tail)",
            path=name,
        )
    return start, extent


def _tip_at_far_end(
    angle: np.ndarray, start: float, extent: float, tube: np.ndarray, name: str
) -> bool:
    """Whether the tip (the end where the wire tapers: the thinner one) is at ``start +
    extent`` rather than at ``start``; ``tube`` is each vertex's distance from the arc, mm."""
    # Angle of every vertex along the arc, 0 at the start end, extent at the other.
    along = np.mod(angle - start, 2 * np.pi)
    along = np.where(along > extent + 1e-9, along - 2 * np.pi, along)  # round-off at start
    band = _END_FRACTION * extent
    near_start, near_end = along < band, along > extent - band
    if not near_start.any() or not near_end.any():
        raise ModelError("not a needle: too few vertices near its ends", path=name)
    thick_start = float(np.median(tube[near_start]))
    thick_end = float(np.median(tube[near_end]))
    if min(thick_start, thick_end) > _TAPER_RATIO * max(thick_start, thick_end):
        raise ModelError(
            "not a needle: neither end tapers to a point, so the tip cannot be told from the "
            f"tail (wire radius {thick_start:.3g} mm at one end, {thick_end:.3g} mm at the other)",
            path=name,
        )
    return thick_end < thick_start


def fit_needle(model: ObjectModel | np.ndarray, *, name: str = "model") -> NeedleArc:
    """Fit the arc of a curved suturing needle to a mesh's vertices, in its model frame.

    The plane is the least-variance direction of the vertices, the circle a least-squares
    fit of their in-plane coordinates (:func:`fit_circle`), the extent the circle minus the
    largest angular gap between vertices. The tip is the end where the wire is thinner (it
    tapers to a point), the tail the other (blunt or swaged) end. Vectorised over vertices.

    Args:
        model: The mesh (its vertices are used) or (V, 3) points, mm.
        name: What to call the model in error messages (e.g. its file).

    Returns:
        The arc; its :meth:`NeedleArc.frame` maps :func:`needle_mesh`'s frame into the model's.

    Raises:
        ModelError: The points are not a needle: not flat, not on a circle, a tube too thick
            for its arc, an arc too short or a closed ring, or neither end tapers.
    """
    pts = _needle_points(model, name)
    mean = pts.mean(axis=0)
    _, sv, vt = np.linalg.svd(pts - mean, full_matrices=False)
    normal = vt[2]
    if sv[1] <= 0 or sv[2] > 0.6 * sv[1]:
        raise ModelError(
            "not a needle: the vertices do not lie near a plane "
            f"(spread across/along the plane {sv[2] / max(sv[1], 1e-12):.2f})",
            path=name,
        )
    u, v = _plane_basis(normal)
    rel = pts - mean
    x, y, z = rel @ u, rel @ v, rel @ normal
    a, b, radius = fit_circle(x, y)
    dx, dy = x - a, y - b
    dist = np.hypot(dx, dy)
    tube = np.hypot(dist - radius, z)  # distance of each vertex from the centre line
    rms = float(np.sqrt(np.mean(tube**2)))
    if not radius > 0 or np.quantile(tube, 0.98) > MAX_TUBE_FRACTION * radius:
        raise ModelError(
            f"not a needle: the vertices do not lie on a thin arc (fitted radius {radius:.3g} mm, "
            f"98 % of vertices within {np.quantile(tube, 0.98):.3g} mm of it; a needle's wire "
            f"is under {MAX_TUBE_FRACTION:.0%} of its radius)",
            path=name,
        )
    angle = np.arctan2(dy, dx)
    start, extent = _arc_span(angle, name)
    extent_deg = float(np.rad2deg(extent))
    tip_at_end = _tip_at_far_end(angle, start, extent, tube, name)
    centre = mean + a * u + b * v
    ends = start + np.array([0.0, extent])
    end_pts = centre + radius * (np.cos(ends)[:, None] * u + np.sin(ends)[:, None] * v)
    tail, tip = (end_pts[0], end_pts[1]) if tip_at_end else (end_pts[1], end_pts[0])
    # Counter-clockwise about (u × v) = normal runs from the start end to the other end.
    oriented = normal if tip_at_end else -normal
    return NeedleArc(
        center=centre,
        normal=oriented / np.linalg.norm(oriented),
        radius=radius,
        extent_deg=extent_deg,
        tip=tip,
        tail=tail,
        wire_radius=float(np.median(tube)),
        rms_mm=rms,
    )


def needle_model_info(model: ObjectModel, arc: NeedleArc) -> dict[str, Any]:
    """``models_info`` entry of any needle mesh: diameter and box (mm), plus the fitted tip,
    tail (mm) and plane normal (for the ambiguity analysis of ``bopsurg eval``)."""
    return {
        **compute_model_info(model.pts),
        "keypoints": {"tip": arc.tip.tolist(), "tail": arc.tail.tolist()},
        "plane_normal": arc.normal.tolist(),
    }
