"""The needle's wire in 3D: camera points on its surface from a depth image, and how far they
lie from the wire of a pose (with the derivatives a least-squares fit needs).

A depth image gives, for each pixel of the wire, a point of the wire's visible surface:
within ``wire_radius`` of the arc's centre line. The residual of a point is its distance to
the centre line (the nearest point of the arc, its ends included) less that radius, mm.

Units: mm, px; poses model-to-camera in the estimator's needle frame (:class:`.arc.ArcModel`:
arc centre at the origin, tail at angle 0 on +x, tip at ``arc_rad`` about +z),
``x_cam = R x_model + t``; depth in mm, 0 where there is no reading.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from bopsurg.models.refine.arc import ArcModel

F64 = NDArray[np.float64]


def depth_points(uv: F64, depth: NDArray[np.floating], K: F64) -> F64:
    """3D camera points (N', 3), mm, of image points ``uv`` (N, 2) px (OpenCV pixel centres),
    each read at its nearest pixel of ``depth`` (H, W), mm; points outside the image or
    without a reading (0, NaN) are dropped."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    depth = np.asarray(depth)
    ij = np.round(uv).astype(np.int64)
    h, w = depth.shape
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    uv, ij = uv[inside], ij[inside]
    z = depth[ij[:, 1], ij[:, 0]].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    uv, z = uv[ok], z[ok]
    K = np.asarray(K, float)
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1)


def nearest_arc_points(q: F64, arc: ArcModel) -> F64:
    """The centre-line points (..., 3), model frame, nearest to model points ``q`` (..., 3):
    the circle's point at the same angle, or the nearer end where that angle lies off the
    arc."""
    a = np.arctan2(q[..., 1], q[..., 0]) % (2 * np.pi)
    past_tip = a - arc.arc_rad
    before_tail = 2 * np.pi - a
    theta = np.where(a <= arc.arc_rad, a, np.where(past_tip < before_tail, arc.arc_rad, 0.0))
    out: F64 = arc.radius * np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], -1)
    return out


def wire_distances(R: F64, t: F64, P: F64, arc: ArcModel) -> F64:
    """Distances (S, N), mm, of camera points ``P`` (N, 3) to the wire's surface (the centre
    line's distance less ``wire_radius``; negative inside) at poses ``R`` (S, 3, 3), ``t``
    (S, 3)."""
    diff, _ = _offsets(R, t, P, arc)
    out: F64 = np.linalg.norm(diff, axis=-1) - arc.wire_radius
    return out


def _offsets(R: F64, t: F64, P: F64, arc: ArcModel) -> tuple[F64, F64]:
    """Model-frame offsets (S, N, 3) of the points from their nearest centre-line points, and
    those points (S, N, 3), mm, at each pose."""
    q = np.einsum("sji,snj->sni", R, P[None] - t[:, None])  # R^T (P - t), model frame
    c = nearest_arc_points(q, arc)
    return q - c, c


def wire_residuals(R: F64, t: F64, P: F64, arc: ArcModel) -> tuple[F64, F64]:
    """Residuals (B, N), mm, of camera points ``P`` (N, 3) against the wire at poses ``R``
    (B, 3, 3), ``t`` (B, 3) (:func:`wire_distances`), and their derivatives (B, N, 6) for the
    pose update ``R → exp(ω) R``, ``t → t + δt`` (ω first: the convention of :mod:`.fit`).

    A point's residual moves with the centre line's nearest point c (camera frame): by
    ``(u × R c)·ω − u·δt`` with u the unit direction from c to the point (the nearest point's
    arc parameter is stationary, so its own change does not enter)."""
    diff, c = _offsets(R, t, P, arc)
    dist = np.linalg.norm(diff, axis=-1)
    u = np.einsum("bij,bnj->bni", R, diff / np.maximum(dist, 1e-9)[..., None])
    a = np.einsum("bij,bnj->bni", R, c)
    return dist - arc.wire_radius, np.concatenate([np.cross(u, a), -u], axis=-1)
