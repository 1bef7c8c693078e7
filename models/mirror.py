"""Mirror augmentation of pose-head training samples: the needle seen from its other face.

A planar needle looks alike from its two faces, with tip and tail swapped; which face the
camera sees is the sign of n·v (the arc's normal against the line of sight). The recorded
episodes hold the needle so that the camera, looking down, nearly always sees the same face
(n·v > 0.5 in 3 of 2,937 sampled training needles), and a head trained on them answers every
needle seen from the other face with tip and tail swapped (the model card's AMBF frames).

Mirroring a sample shows the other face exactly. Flip the image about the principal point's
column (u → 2·c_x − u): that is the camera's reflection F = diag(−1, 1, 1), and the mirrored
image shows the needle reflected, F·R·x + F·t. The needle is its own mirror image through its
plane (a round wire on a planar arc): ``x → M x + d`` maps it onto itself
(:class:`bopsurg.mirror.PlaneReflection`, from the mesh and ``models_info``'s
``plane_normal``; M = diag(1, 1, −1), d = 0 for bopsurg's needle, whose plane is z = 0). So
the same image shows the needle itself at the proper pose ``R' = F R M``, ``t' = F (t + R d)``,
whose normal makes n'·v' = −n·v. A model point x seen at a pixel is ``M (x − d)`` after the
mirror. Units: px, mm.
"""

from __future__ import annotations

import dataclasses

import torch

from bopsurg.mirror import PlaneReflection
from bopsurg.models.data import PoseBatch


def mirror_batch(batch: PoseBatch, flip: torch.Tensor, reflection: PlaneReflection) -> PoseBatch:
    """``batch`` with the samples ``flip`` ((B,) bool) mirrored about the principal point's
    column of their images; the others unchanged.

    The context crops are flipped along x and their affines moved to the mirrored image
    (context px ``q = (x − c_0)·a + C/2``, pixel j at q = j: flipping the array takes q to
    C − 1 − q, so ``c_0' = 2·c_x − c_0 + 1/a``); the visible box's pixel edges [x − ½, x − ½ + w]
    mirror to ``x' = 2·c_x − x − w + 1``; the pose becomes ``F R M``, ``F (t + R d)`` and the
    visible pixels' coordinates ``M (x − d)``, with ``reflection`` the object's symmetry
    through its plane. Assumes no skew (K[0, 1] = 0), as BOP cameras have.
    """
    if not bool(flip.any()):
        return batch
    f = flip.to(batch.rgb.device)
    cx = batch.K[:, 0, 2]
    a = batch.ctx[:, 0]

    def flipped(x: torch.Tensor) -> torch.Tensor:
        shape = (-1,) + (1,) * (x.dim() - 1)
        return torch.where(f.view(shape), x.flip(-1), x)

    ctx = batch.ctx.clone()
    ctx[:, 1] = torch.where(f, 2.0 * cx - batch.ctx[:, 1] + 1.0 / a, batch.ctx[:, 1])
    bbox = batch.bbox.clone()
    bbox[:, 0] = torch.where(f, 2.0 * cx - batch.bbox[:, 0] - batch.bbox[:, 2] + 1.0, bbox[:, 0])
    # F (camera) per sample, identity where not flipped; M and d (model) where flipped
    F = torch.ones(len(f), 3, dtype=batch.R.dtype, device=batch.R.device)
    F[f, 0] = -1.0
    M = torch.as_tensor(reflection.M, dtype=batch.R.dtype, device=batch.R.device)
    d = torch.as_tensor(reflection.d, dtype=batch.R.dtype, device=batch.R.device)
    R = torch.where(f[:, None, None], F[:, :, None] * (batch.R @ M), batch.R)
    t = torch.where(f[:, None], F * (batch.t + batch.R @ d), batch.t)
    # coordinates: x -> M (x - d) on the visible pixels (the background stays 0)
    x = batch.xyz.float()
    mx = torch.einsum("ij,bjhw->bihw", M.float(), x - d.float()[None, :, None, None])
    mx = torch.where(batch.mask[:, None], mx, torch.zeros_like(mx)).to(batch.xyz.dtype)
    xyz = flipped(torch.where(f.view(-1, 1, 1, 1), mx, batch.xyz))
    return dataclasses.replace(
        batch, rgb=flipped(batch.rgb), mask=flipped(batch.mask), xyz=xyz, ctx=ctx, bbox=bbox,
        R=R, t=t,
    )  # fmt: skip
