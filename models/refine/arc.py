"""The needle's geometry as the estimator models it: the arc of its centre line, its wire,
and the poses that share its image (the end-for-end half turn, the tilt mirror).

One home for the needle arc (the mesh itself is :func:`bopsurg.needle.needle_mesh`); the fits
(:mod:`.fit`, :mod:`.depth_fit`, :mod:`.wire3d`) and the end check (:mod:`.ends`) import it.
Units: mm; poses model-to-camera, ``x_cam = R x_model + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from bopsurg.bop.dataset import BopDataset
from bopsurg.errors import BopsurgError

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class ArcModel:
    """The needle's centre line: an arc of ``radius`` mm from angle 0 (tail) to ``arc_rad``,
    and its wire: radius ``wire_radius`` mm, tapering to a point over the last ``tip_rad``."""

    radius: float = 10.18
    arc_rad: float = float(np.deg2rad(128.5))
    wire_radius: float = 0.36
    tip_rad: float = float(np.deg2rad(8.5))

    @classmethod
    def from_keypoints(cls, tail: F64, tip: F64) -> ArcModel:
        """The arc of a :func:`bopsurg.needle.needle_mesh` model from its tail and tip (mm).

        The tail-cap centre lies on the centre line at angle 0 and the tip at the arc's end.
        """
        tail, tip = np.asarray(tail, float), np.asarray(tip, float)
        radius = float(np.hypot(tail[0], tail[1]))
        arc = float(np.arctan2(tip[1], tip[0]) % (2 * np.pi))
        if not (radius > 0 and arc > 0):
            raise ValueError(f"keypoints do not describe an arc (tail {tail}, tip {tip})")
        return cls(radius=radius, arc_rad=arc)

    def points(self, n: int) -> F64:
        """(n, 3) centre-line points from tail to tip, mm."""
        s = np.linspace(0.0, self.arc_rad, n)
        return np.stack([self.radius * np.cos(s), self.radius * np.sin(s), np.zeros(n)], axis=1)

    def wire_radii(self, n: int) -> F64:
        """(n,) wire radius at the :meth:`points`, mm (linear taper to 0 at the tip)."""
        s = np.linspace(0.0, self.arc_rad, n)
        taper = np.clip((self.arc_rad - s) / max(self.tip_rad, 1e-9), 0.0, 1.0)
        return self.wire_radius * taper


def dataset_arc(dataset: BopDataset, obj_id: int) -> ArcModel:
    """The arc of needle ``obj_id`` of a dataset, from its ``models_info`` tip and tail
    keypoints.

    Raises:
        BopsurgError: The keypoints are missing or do not describe an arc (one line naming
            models_info.json).
    """
    try:
        kp = dataset.models_info[obj_id]["keypoints"]
        return ArcModel.from_keypoints(kp["tail"], kp["tip"])
    except (KeyError, ValueError) as err:
        raise BopsurgError(
            f"{dataset.models_dir / 'models_info.json'}: obj {obj_id} needs tip and tail "
            f"keypoints ({err})"
        ) from err


def skew(v: Tensor) -> Tensor:
    """(..., 3) → (..., 3, 3) cross-product matrices."""
    z = torch.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack(
        [torch.stack([z, -w, y], -1), torch.stack([w, z, -x], -1), torch.stack([-y, x, z], -1)],
        -2,
    )


def exp_so3(w: Tensor) -> Tensor:
    """(..., 3) rotation vectors → (..., 3, 3) rotations (Rodrigues)."""
    theta = torch.linalg.vector_norm(w, dim=-1)[..., None, None]
    Kx = skew(w)
    small = theta < 1e-12
    th = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, torch.ones_like(th), torch.sin(th) / th)
    b = torch.where(small, torch.full_like(th, 0.5), (1.0 - torch.cos(th)) / th**2)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a * Kx + b * (Kx @ Kx)


def log_so3(R: Tensor) -> Tensor:
    """(..., 3, 3) rotations → (..., 3) rotation vectors (angles up to π)."""
    c = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    theta = torch.arccos(c)[..., None]
    v = torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        -1,
    )
    general = v * theta / (2.0 * torch.sin(theta).clamp(min=1e-300))
    # near a half turn v vanishes: the axis is the symmetric part's top eigenvector
    axis = torch.linalg.eigh(0.5 * (R + R.transpose(-1, -2)))[1][..., :, -1]
    out = torch.where(theta < np.pi - 1e-6, general, np.pi * axis)
    return torch.where(theta < 1e-9, 0.5 * v, out)


def half_turn(arc: ArcModel) -> F64:
    """(3, 3) the half turn S about the arc's bisector (model frame): ``R S`` is the swapped
    pose of ``R`` (the arc's centre is the model origin, so ``t`` stays)."""
    b = np.array([np.cos(arc.arc_rad / 2), np.sin(arc.arc_rad / 2), 0.0])
    return 2.0 * np.outer(b, b) - np.eye(3)


def same_ends(R: Tensor, t: Tensor, R_ref: Tensor, t_ref: Tensor, arc: ArcModel) -> Tensor:
    """Each rotation of ``R`` (..., 3, 3) or its half turn (the same arc, tip and tail
    swapped; ``t`` (..., 3) mm stays): the one whose tip lies on the nearer line of sight to
    the tip of the pose ``(R_ref, t_ref)`` (broadcast against ``R``, ``t``).

    A fit of the arc's shape alone (to points, or from a tilt-mirrored start) cannot tell the
    ends apart; this keeps the reference's (the pose head's: the end check judges it after)."""
    tip = torch.as_tensor(arc.points(2)[-1], dtype=R.dtype, device=R.device)
    S = torch.as_tensor(half_turn(arc), dtype=R.dtype, device=R.device)

    def sight(v: Tensor) -> Tensor:
        out: Tensor = v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp(min=1e-12)
        return out

    R_h = R @ S
    seen = sight(R_ref @ tip + t_ref)
    swap = (sight(R_h @ tip + t) * seen).sum(-1) > (sight(R @ tip + t) * seen).sum(-1)
    return torch.where(swap[..., None, None], R_h, R)


def mirror_pose(R: Tensor, t: Tensor) -> Tensor:
    """The rotations (..., 3, 3) whose arc plane is ``R``'s mirrored through the line of
    sight to ``t`` (..., 3) mm.

    A circle tilted by +θ or −θ about an axis across the line of sight projects to (almost)
    the same ellipse; this is the other branch of that two-fold ambiguity: the plane normal
    n goes to ``2(n·v)v − n`` (v the unit line of sight), by the smallest rotation.
    """
    v = t / torch.linalg.vector_norm(t, dim=-1, keepdim=True)
    n = R[..., :, 2]
    n2 = 2.0 * (n * v).sum(-1, keepdim=True) * v - n
    axis = torch.linalg.cross(n, n2)
    s = torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
    c = (n * n2).sum(-1, keepdim=True).clamp(-1.0, 1.0)
    turned = exp_so3(axis / s.clamp(min=1e-300) * torch.atan2(s, c)) @ R
    # normal along the line of sight: the mirror is the pose itself
    return torch.where((s < 1e-9)[..., None], R, turned)
