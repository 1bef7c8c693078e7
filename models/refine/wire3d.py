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


def strided_points(P: F64, most: int) -> F64:
    """At most ``most`` of the points ``P`` (N, D), evenly strided in their order (all of
    them when there are no more)."""
    if len(P) <= most:
        return P
    return P[np.linspace(0, len(P) - 1, most).round().astype(np.int64)]


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


def _nearest_xy(x: Tensor, y: Tensor, arc: ArcModel) -> tuple[Tensor, Tensor]:
    """The centre line's point (x, y) nearest to model points with plane coordinates ``x``,
    ``y`` (any shape), mm: the circle's point at the same angle, or the nearer end where that
    angle lies off the arc.

    No angle is computed (this runs on every depth point at every step): the angle lies on
    the arc where the point is not behind the tail (y ≥ 0) and not past the tip (tip × point
    ≥ 0), both for an arc up to a half turn, either for a longer one; the nearer end is the
    one with the larger dot product with the point."""
    c, s = float(np.cos(arc.arc_rad)), float(np.sin(arc.arc_rad))
    behind_tail, past_tip = y < 0, x * s - y * c < 0
    off = behind_tail | past_tip if arc.arc_rad <= np.pi else behind_tail & past_tip
    r_xy = torch.sqrt(x * x + y * y)
    inv = 1.0 / r_xy.clamp(min=1e-300)
    # the circle's point at the point's angle (the tail for the plane's origin)
    ux, uy = torch.where(r_xy > 0, x * inv, 1.0), y * inv
    tip_nearer = x * c + y * s > x
    # the ends as tensors of the points' dtype (a where of two Python floats is float32)
    tip_x, tip_y, one, zero = (x.new_tensor(v) for v in (c, s, 1.0, 0.0))
    ux = torch.where(off, torch.where(tip_nearer, tip_x, one), ux)
    uy = torch.where(off, torch.where(tip_nearer, tip_y, zero), uy)
    return arc.radius * ux, arc.radius * uy


def nearest_arc_points(q: Tensor, arc: ArcModel) -> Tensor:
    """The centre-line points (..., 3), model frame, nearest to model points ``q`` (..., 3):
    the circle's point at the same angle, or the nearer end where that angle lies off the
    arc."""
    cx, cy = _nearest_xy(q[..., 0], q[..., 1], arc)
    return torch.stack([cx, cy, torch.zeros_like(cx)], -1)


def _model_points(R: Tensor, t: Tensor, P_axes: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Camera points ``P_axes`` (B, 3, N) (laid out by axis) in the model frames of poses
    ``R``, ``t``: Rᵀ P − Rᵀ t, as its x, y, z (B, N): one product whose operands and result
    are contiguous along N, as is all the arithmetic after it."""
    Rt = R.transpose(1, 2)
    q = torch.baddbmm(-(Rt @ t[..., None].to(Rt.dtype)), Rt, P_axes.to(Rt.dtype))  # (B, 3, N)
    return q[:, 0], q[:, 1], q[:, 2]


def wire_distances(R: Tensor, t: Tensor, P: Tensor, arc: ArcModel) -> Tensor:
    """Distances (B, N), mm, of camera points ``P`` (B, N, 3) to the wire's surface (the
    centre line's distance less ``wire_radius``; negative inside) at poses ``R`` (B, 3, 3),
    ``t`` (B, 3)."""
    qx, qy, dz = _model_points(R, t, P.transpose(1, 2))
    cx, cy = _nearest_xy(qx, qy, arc)
    dx, dy = qx - cx, qy - cy
    out: Tensor = torch.sqrt(dx * dx + dy * dy + dz * dz) - arc.wire_radius
    return out


def wire_residuals_model(
    R: Tensor,
    t: Tensor,
    P_axes: Tensor,
    arc: ArcModel,
) -> tuple[Tensor, Tensor]:
    """:func:`wire_residuals` of camera points laid out by axis, ``P_axes`` (B, 3, N) (the
    fits lay them out once: they stay fixed while the poses move), with the derivatives in
    the model frame, by row: (B, 6, N), ``J_cam = blockdiag(R, R) · J_model`` per point
    (:func:`camera_normal_equations` turns their normal equations to the camera's: a 6×6
    product instead of one per point)."""
    qx, qy, qz = _model_points(R, t, P_axes)
    cx, cy = _nearest_xy(qx, qy, arc)
    dx, dy = qx - cx, qy - cy
    dist = torch.sqrt(dx * dx + dy * dy + qz * qz)
    inv = 1.0 / dist.clamp(min=1e-9)
    nx, ny, nz = dx * inv, dy * inv, qz * inv  # u in the model frame: u = R n
    # u × (R c) = R (n × c), with c_z = 0; d/dδt = −u
    J = torch.stack([-nz * cy, nz * cx, nx * cy - ny * cx, -nx, -ny, -nz], 1)
    return dist - arc.wire_radius, J


def camera_normal_equations(H: Tensor, g: Tensor, R: Tensor) -> tuple[Tensor, Tensor]:  # noqa: N803
    """Normal equations (B, 6, 6), (B, 6) of model-frame derivatives
    (:func:`wire_residuals_model`) turned to the camera's: D H Dᵀ, D g with D = blockdiag(R, R)."""
    b = len(R)
    D = torch.zeros((b, 6, 6), dtype=R.dtype, device=R.device)
    D[:, :3, :3], D[:, 3:, 3:] = R, R
    return D @ H @ D.transpose(1, 2), (D @ g[..., None])[..., 0]


def wire_residuals(R: Tensor, t: Tensor, P: Tensor, arc: ArcModel) -> tuple[Tensor, Tensor]:
    """Residuals (B, N), mm, of camera points ``P`` (B, N, 3) against the wire at poses ``R``
    (B, 3, 3), ``t`` (B, 3) (:func:`wire_distances`), and their derivatives (B, N, 6) for the
    pose update ``R → exp(ω) R``, ``t → t + δt`` (ω first: the convention of :mod:`.fit`).

    A point's residual moves with the centre line's nearest point c (camera frame): by
    ``(u × R c)·ω − u·δt`` with u the unit direction from c to the point (the nearest point's
    arc parameter is stationary, so its own change does not enter)."""
    r, J = wire_residuals_model(R, t, P.transpose(1, 2), arc)
    b, m = P.shape[:2]
    J_cam = (J.transpose(1, 2).reshape(b, 2 * m, 3) @ R.transpose(1, 2)).reshape(b, m, 6)
    return r, J_cam
