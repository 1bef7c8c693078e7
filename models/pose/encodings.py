"""Pose encodings of the pose head: 6D rotation, allocentric ↔ egocentric, SITE translation.

Conventions (BOP): ``x_cam = R x_model + t``, t in mm, K a pinhole matrix in px with OpenCV's
pixel-centre convention (pixel (u, v) covers [u − ½, u + ½] × [v − ½, v + ½]). Every function is
batched over a leading dimension B and differentiable.

The network predicts the **allocentric** rotation (what a translation-invariant ROI crop can
see) as 6 numbers, and the translation as SITE ``(δx, δy, δz)`` relative to the crop; the
functions here turn those into the egocentric ``R`` and ``t`` and back.

The ROI and dense-target helpers live in :mod:`.roi` and :mod:`.targets`; the package
(:mod:`bopsurg.models.pose`) is the one import for all of them.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

# t̂_z below −1 + this: the object sits behind the camera on the optical axis (never in BOP
# data); R_c is then any 180° turn, and the closed form below would divide by zero.
_ANTIPODAL_EPS = 1e-6


def rot6d_from_matrix(R: torch.Tensor) -> torch.Tensor:
    """6D rotation code: the first two columns of R, ``[R[:, 0]; R[:, 1]]``.

    Args:
        R: (B, 3, 3) rotation matrices.

    Returns:
        (B, 6): ``(R00, R10, R20, R01, R11, R21)``.
    """
    return torch.cat([R[:, :, 0], R[:, :, 1]], dim=1)


def matrix_from_rot6d(x: torch.Tensor) -> torch.Tensor:
    """Rotation matrix from a 6D code by Gram-Schmidt (inverse of :func:`rot6d_from_matrix`).

    ``b1 = N(a1)``, ``b3 = N(b1 × a2)``, ``b2 = b3 × b1``, ``R = [b1 b2 b3]``.

    Args:
        x: (B, 6) codes ``[a1; a2]`` (any scale; a1 and a2 must not be parallel).

    Returns:
        (B, 3, 3) proper rotations.
    """
    a1, a2 = x[:, :3], x[:, 3:]
    b1 = F.normalize(a1, dim=1)
    b3 = F.normalize(torch.linalg.cross(b1, a2, dim=1), dim=1)
    b2 = torch.linalg.cross(b3, b1, dim=1)
    return torch.stack([b1, b2, b3], dim=2)


def ray_rotation(t: torch.Tensor) -> torch.Tensor:
    """R_c: the rotation about ``N(e_z × t̂)`` by ``acos(t̂_z)`` that turns e_z onto ``t̂ = t/|t|``.

    Written in closed form ``R_c = I + [v]× + [v]×² / (1 + c)`` with ``v = e_z × t̂`` and
    ``c = t̂_z`` (Rodrigues with the unnormalised axis), which has no ``|v|`` to divide by: it is
    exactly I when t̂ = e_z and smooth (differentiable in t) around it. For t̂ ≈ −e_z it returns
    a 180° turn about the x axis.

    Args:
        t: (B, 3) translations (any unit; only the direction matters).

    Returns:
        (B, 3, 3) rotations.
    """
    d = F.normalize(t, dim=1)
    dx, dy, c = d.unbind(dim=1)
    zero = torch.zeros_like(c)
    # [v]× for v = e_z × t̂ = (−t̂_y, t̂_x, 0)
    vx = torch.stack(
        [
            torch.stack([zero, zero, dx], dim=1),
            torch.stack([zero, zero, dy], dim=1),
            torch.stack([-dx, -dy, zero], dim=1),
        ],
        dim=1,
    )
    regular = c > -1.0 + _ANTIPODAL_EPS
    # where() with a safe denominator: no inf in the unused branch, so no NaN gradients either
    denom = torch.where(regular, 1.0 + c, torch.ones_like(c))
    eye = torch.eye(3, dtype=t.dtype, device=t.device).expand_as(vx)
    R_c = eye + vx + (vx @ vx) / denom[:, None, None]
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=t.dtype, device=t.device))
    return torch.where(regular[:, None, None], R_c, flip.expand_as(R_c))


def allo_to_ego(R_allo: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Egocentric rotation ``R_ego = R_c(t) · R_allo`` (differentiable w.r.t. both).

    Args:
        R_allo: (B, 3, 3) allocentric rotations.
        t: (B, 3) translations, mm.

    Returns:
        (B, 3, 3) egocentric rotations (BOP ``R``).
    """
    return ray_rotation(t) @ R_allo


def ego_to_allo(R_ego: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Allocentric rotation ``R_allo = R_c(t)^T · R_ego`` (inverse of :func:`allo_to_ego`).

    Args:
        R_ego: (B, 3, 3) egocentric rotations (BOP ``R``).
        t: (B, 3) translations, mm.

    Returns:
        (B, 3, 3) allocentric rotations.
    """
    return ray_rotation(t).transpose(1, 2) @ R_ego


class SiteRoi(NamedTuple):
    """The ROI a SITE translation is expressed in (batched over B).

    Attributes:
        K: (B, 3, 3) intrinsics, px.
        centre: (B, 2) crop centre (c_x, c_y), px (the jittered one at train time).
        wh: (B, 2) box width and height, px (un-jittered; the detection's at test time).
        side: (B,) crop side, px.
        roi_out: side of the output maps, px.
        z_unit_mm: mm per unit of δz (1000: δz in metres).
    """

    K: torch.Tensor
    centre: torch.Tensor
    wh: torch.Tensor
    side: torch.Tensor
    roi_out: int
    z_unit_mm: float


def site_encode(t: torch.Tensor, roi: SiteRoi) -> torch.Tensor:
    """SITE target ``(δx, δy, δz)`` of a translation, relative to its ROI.

    With the projected object origin ``o = π(K t)`` and the zoom ``r = roi_out / side``:
    ``δx = (o_x − c_x)/w``, ``δy = (o_y − c_y)/h``, ``δz = t_z / r / z_unit_mm``.

    Args:
        t: (B, 3) translations, mm.
        roi: the ROIs (intrinsics, crop centre and side, box size, map side, δz unit).

    Returns:
        (B, 3) ``(δx, δy, δz)``, dimensionless except δz (z_unit_mm · px/px).
    """
    p = (roi.K @ t[:, :, None])[:, :, 0]
    o = p[:, :2] / p[:, 2:3]
    r = roi.roi_out / roi.side
    dz = t[:, 2] / r / roi.z_unit_mm
    return torch.cat([(o - roi.centre) / roi.wh, dz[:, None]], dim=1)


def site_decode(ratio: torch.Tensor, roi: SiteRoi) -> torch.Tensor:
    """Translation from SITE ``(δx, δy, δz)``: inverse of :func:`site_encode`.

    ``o = δ_xy · wh + c``, ``t_z = δz · z_unit_mm · r``, ``t = t_z · K⁻¹ [o_x, o_y, 1]``.

    Args:
        ratio: (B, 3) SITE values (network output "site").
        roi: as in :func:`site_encode`.

    Returns:
        (B, 3) translations, mm.
    """
    o = ratio[:, :2] * roi.wh + roi.centre
    tz = ratio[:, 2] * roi.z_unit_mm * (roi.roi_out / roi.side)
    o_h = torch.cat([o, torch.ones_like(o[:, :1])], dim=1)
    ray = torch.linalg.solve(roi.K, o_h[:, :, None])[:, :, 0]  # K⁻¹ o, z = 1 for a pinhole
    out: torch.Tensor = ray / ray[:, 2:3] * tz[:, None]
    return out
