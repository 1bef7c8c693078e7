"""Mirror augmentation of pose-head training samples: the needle seen from its other face.

A planar needle looks alike from its two faces, with tip and tail swapped; which face the
camera sees is the sign of n·v (the arc's normal against the line of sight). The recorded
episodes hold the needle so that the camera, looking down, nearly always sees the same face
(n·v > 0.5 in 3 of 2,937 sampled training needles), and a head trained on them answers every
needle seen from the other face with tip and tail swapped (the model card's AMBF frames).

Mirroring a sample shows the other face exactly. Flip the image about the principal point's
column (u → 2·c_x − u): that is the camera's reflection F = diag(−1, 1, 1), and the mirrored
image shows the needle reflected, F·R·x + F·t. The needle is symmetric about its own plane
(a round wire on a planar arc; M = diag(1, 1, −1) in its model frame maps it onto itself), so
the same image shows the needle itself at the proper pose ``R' = F R M``, ``t' = F t``, whose
normal makes n'·v' = −n·v. A model point x seen at a pixel is M·x after the mirror: the
coordinate maps' z changes sign. Units: px, mm.
"""

from __future__ import annotations

import dataclasses

import torch

from bopsurg.models.data import PoseBatch


def mirror_batch(batch: PoseBatch, flip: torch.Tensor) -> PoseBatch:
    """``batch`` with the samples ``flip`` ((B,) bool) mirrored about the principal point's
    column of their images; the others unchanged.

    The context crops are flipped along x and their affines moved to the mirrored image
    (context px ``q = (x − c_0)·a + C/2``, pixel j at q = j: flipping the array takes q to
    C − 1 − q, so ``c_0' = 2·c_x − c_0 + 1/a``); the visible box's pixel edges [x − ½, x − ½ + w]
    mirror to ``x' = 2·c_x − x − w + 1``; the pose becomes ``F R M``, ``F t``; the coordinates'
    z its negative. Assumes no skew (K[0, 1] = 0), as BOP cameras have.
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
    # the diagonals of F (camera) and M (model), per sample; identity where not flipped
    one = torch.ones(len(f), 3, dtype=batch.R.dtype, device=batch.R.device)
    F, M = one.clone(), one.clone()
    F[f, 0], M[f, 2] = -1.0, -1.0
    R = F[:, :, None] * batch.R * M[:, None, :]
    xyz = flipped(batch.xyz) * M.to(batch.xyz.dtype)[:, :, None, None]  # model x -> M x
    return dataclasses.replace(
        batch, rgb=flipped(batch.rgb), mask=flipped(batch.mask), xyz=xyz, ctx=ctx, bbox=bbox,
        R=R, t=F * batch.t,
    )  # fmt: skip
