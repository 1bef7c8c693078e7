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

from collections.abc import Sequence

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

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


def stack_points(
    points: Sequence[NDArray[np.floating]], device: torch.device
) -> tuple[Tensor, Tensor]:
    """Point sets (N_i, D) stacked into one (n, N, D) float64 tensor on ``device``, padded
    with zeros to the largest (at least 1), and which entries are real (n, N)."""
    count = np.array([len(p) for p in points], np.int64)
    dim = points[0].shape[-1] if len(points) else 3
    out = np.zeros((len(points), max(1, int(count.max(initial=0))), dim))
    valid = np.arange(out.shape[1])[None] < count[:, None]
    if count.sum():
        out[valid] = np.concatenate([np.asarray(p, float).reshape(-1, dim) for p in points])
    return torch.as_tensor(out, device=device), torch.as_tensor(valid, device=device)


def nearest_arc_points(q: Tensor, arc: ArcModel) -> Tensor:
    """The centre-line points (..., 3), model frame, nearest to model points ``q`` (..., 3):
    the circle's point at the same angle, or the nearer end where that angle lies off the
    arc."""
    a = torch.remainder(torch.atan2(q[..., 1], q[..., 0]), 2 * np.pi)
    # the circle's point at angle a is the radius along q's direction in the plane (no
    # trigonometry per point: this runs on every depth point at every step)
    xy = q[..., :2]
    r_xy = torch.linalg.vector_norm(xy, dim=-1, keepdim=True)
    tail = torch.tensor([1.0, 0.0], dtype=q.dtype, device=q.device)
    on_circle = torch.where(r_xy > 0, xy / r_xy.clamp(min=1e-300), tail)
    tip = torch.tensor([np.cos(arc.arc_rad), np.sin(arc.arc_rad)], dtype=q.dtype, device=q.device)
    end = torch.where((a - arc.arc_rad < 2 * np.pi - a)[..., None], tip, tail)
    out: Tensor = torch.cat(
        [arc.radius * torch.where((a <= arc.arc_rad)[..., None], on_circle, end), 0.0 * q[..., 2:]],
        -1,
    )
    return out


def wire_distances(R: Tensor, t: Tensor, P: Tensor, arc: ArcModel) -> Tensor:
    """Distances (B, N), mm, of camera points ``P`` (B, N, 3) to the wire's surface (the
    centre line's distance less ``wire_radius``; negative inside) at poses ``R`` (B, 3, 3),
    ``t`` (B, 3)."""
    diff, _ = _offsets(R, t, P, arc)
    out: Tensor = torch.linalg.vector_norm(diff, dim=-1) - arc.wire_radius
    return out


def _offsets(R: Tensor, t: Tensor, P: Tensor, arc: ArcModel) -> tuple[Tensor, Tensor]:
    """Model-frame offsets (B, N, 3) of the points from their nearest centre-line points, and
    those points (B, N, 3), mm, at each pose."""
    q = (P - t[:, None]) @ R  # R^T (P - t), model frame
    c = nearest_arc_points(q, arc)
    return q - c, c


def wire_residuals(R: Tensor, t: Tensor, P: Tensor, arc: ArcModel) -> tuple[Tensor, Tensor]:
    """Residuals (B, N), mm, of camera points ``P`` (B, N, 3) against the wire at poses ``R``
    (B, 3, 3), ``t`` (B, 3) (:func:`wire_distances`), and their derivatives (B, N, 6) for the
    pose update ``R → exp(ω) R``, ``t → t + δt`` (ω first: the convention of :mod:`.fit`).

    A point's residual moves with the centre line's nearest point c (camera frame): by
    ``(u × R c)·ω − u·δt`` with u the unit direction from c to the point (the nearest point's
    arc parameter is stationary, so its own change does not enter)."""
    diff, c = _offsets(R, t, P, arc)
    dist = torch.linalg.vector_norm(diff, dim=-1)
    n = diff / dist.clamp(min=1e-9)[..., None]  # u in the model frame: u = R n
    # u × (R c) = R (n × c), with c_z = 0; both halves of J rotate by R in one product
    nx, ny, nz = n.unbind(-1)
    n_c = torch.stack([-nz * c[..., 1], nz * c[..., 0], nx * c[..., 1] - ny * c[..., 0]], -1)
    b, m = P.shape[:2]
    J = (torch.stack([n_c, -n], -2).reshape(b, 2 * m, 3) @ R.transpose(1, 2)).reshape(b, m, 6)
    return dist - arc.wire_radius, J
