"""Dense training targets: object-frame xyz maps, their normalisation, and surface regions.

The xyz target of a pixel is the object-frame point (mm) seen there, obtained from a rendered
depth map and the GT pose (no coordinate renderer needed). The network regresses it
normalised to about [0, 1] with ONE isotropic scale (the model's max extent): a per-axis extent
would blow up the wire-thickness axis of a thin needle. Regions label each pixel with its
nearest farthest-point-sampled (FPS) model point.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True, eq=False)
class XyzNormaliser:
    """Isotropic map between object-frame mm and the network's normalised xyz.

    ``x_n = (x − centre) / scale + 0.5``: the model's bbox maps into [0, 1]³, its longest side
    spanning exactly [0, 1], the others centred on 0.5.

    Attributes:
        centre: (3,) model bbox centre, mm.
        scale: max bbox extent, mm.
    """

    centre: torch.Tensor
    scale: float

    @classmethod
    def from_vertices(cls, v: torch.Tensor) -> XyzNormaliser:
        """From model vertices (V, 3), mm: centre = bbox centre, scale = max extent."""
        lo, hi = v.min(dim=0).values, v.max(dim=0).values
        return cls(centre=0.5 * (lo + hi), scale=float((hi - lo).max()))

    def normalise(self, xyz: torch.Tensor) -> torch.Tensor:
        """(..., 3) mm → (..., 3) normalised (dtype and device of ``xyz``)."""
        return (xyz - self.centre.to(xyz)) / self.scale + 0.5

    def denormalise(self, xyz_n: torch.Tensor) -> torch.Tensor:
        """(..., 3) normalised → (..., 3) mm."""
        return (xyz_n - 0.5) * self.scale + self.centre.to(xyz_n)


def farthest_point_sampling(points: torch.Tensor, k: int) -> torch.Tensor:
    """k well-spread points of a point set, deterministic.

    The first pick is the point farthest from the centroid; each next pick is the point
    farthest from all picks so far (ties: the lowest index).

    Args:
        points: (V, 3) points (model vertices), mm.
        k: number of picks, 1 ≤ k ≤ V.

    Returns:
        (k, 3) picked points, in pick order.
    """
    V = points.shape[0]
    if not 1 <= k <= V:
        raise ValueError(f"k must be in [1, {V}], got {k}")
    first = torch.argmax((points - points.mean(dim=0)).square().sum(dim=1))
    picks = [first]
    dist = (points - points[first]).square().sum(dim=1)  # squared distance to the nearest pick
    for _ in range(k - 1):  # k sequential picks, each one vectorised over all points
        nxt = torch.argmax(dist)
        picks.append(nxt)
        dist = torch.minimum(dist, (points - points[nxt]).square().sum(dim=1))
    return points[torch.stack(picks)]


def xyz_to_region(xyz: torch.Tensor, mask: torch.Tensor, fps: torch.Tensor) -> torch.Tensor:
    """Region labels: 0 for background, ``1 + argmin_k |xyz − fps_k|`` on the foreground.

    Args:
        xyz: (..., 3) object-frame points, e.g. (B, H, W, 3), mm (or any frame shared with fps).
        mask: (...) bool foreground.
        fps: (R, 3) region centres from :func:`farthest_point_sampling`, same frame as xyz.

    Returns:
        (...) long labels in [0, R].
    """
    flat = xyz.reshape(-1, 3).to(fps.dtype)
    # exact pairwise distances (the matmul shortcut loses precision far from the origin)
    d = torch.cdist(flat, fps, compute_mode="donot_use_mm_for_euclid_dist")
    labels = (d.argmin(dim=1) + 1).reshape(xyz.shape[:-1])
    return torch.where(mask.bool(), labels, torch.zeros_like(labels))


def xyz_from_depth(
    depth: torch.Tensor,
    mask: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
) -> torch.Tensor:
    """Object-frame xyz map by back-projecting a depth map: ``X = Rᵀ(z K⁻¹[u, v, 1]ᵀ − t)``.

    Args:
        depth: (B, H, W) z-depth (BOP convention, along the optical axis), mm; 0 = no data.
        mask: (B, H, W) bool, the object's pixels.
        K: (B, 3, 3) intrinsics, px; (u, v) are pixel indices (OpenCV pixel centres).
        R: (B, 3, 3) object-to-camera rotations.
        t: (B, 3) object-to-camera translations, mm.

    Returns:
        (B, H, W, 3) object-frame points, mm; 0 where the mask is false or the depth is 0.
    """
    _, h, w = depth.shape
    v, u = torch.meshgrid(
        torch.arange(h, dtype=depth.dtype, device=depth.device),
        torch.arange(w, dtype=depth.dtype, device=depth.device),
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)  # (H, W, 3)
    rays = torch.einsum("bij,hwj->bhwi", torch.linalg.inv(K), pix)  # z = 1 for a pinhole K
    cam = rays * depth[..., None]
    obj = torch.einsum("bhwi,bij->bhwj", cam - t[:, None, None, :], R)  # Rᵀ(cam − t)
    valid = mask.bool() & (depth > 0)
    return torch.where(valid[..., None], obj, torch.zeros_like(obj))
