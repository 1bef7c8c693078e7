"""Roll augmentation of pose-head training samples: the same scene seen by a camera turned
about its optical axis.

The recorded episodes show the needle in few image orientations (the ECM looks down at a
needle the instrument holds much the same way), and a head trained on them leans on that: the
model card's AMBF frames turned by 180 deg turn most needles end for end. Turning the camera
about its optical axis by θ shows every orientation, exactly: the camera points move by
``Rz(θ)``, so the pose becomes ``Rz R``, ``Rz t``, and a pixel p moves to
``pp + A (p − pp)`` with ``A = S Rot(θ) S⁻¹`` (``S = diag(f_x, f_y)``, ``pp`` the principal
point): a rotation about the principal point when ``f_x = f_y``. No skew (K[0, 1] = 0), as
BOP cameras have.

A context crop is an isotropic scaling of its image, so the turned image's crop, centred at
the turned centre ``c' = pp + A (c − pp)``, is the old crop turned by A about its own centre.
Its corners come from outside the old crop and are black; the needle's visible pixels never
do (they lie within the box, whose half-diagonal is 0.71 of its side, and the crop reaches
1.25 sides from its centre). Units: px, mm.
"""

from __future__ import annotations

import dataclasses

import torch
import torch.nn.functional as F

from bopsurg.models.data import PoseBatch


def _pixel_maps(K: torch.Tensor, angle: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 3, 3) camera rotations ``Rz(θ)`` and (B, 2, 2) pixel maps ``A = S Rot(θ) S⁻¹``."""
    c, s = torch.cos(angle), torch.sin(angle)
    Rz = torch.zeros(len(angle), 3, 3, dtype=K.dtype, device=K.device)
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = c, -s, s, c
    Rz[:, 2, 2] = 1.0
    fx, fy = K[:, 0, 0], K[:, 1, 1]
    A = Rz[:, :2, :2].clone()
    A[:, 0, 1] *= fx / fy
    A[:, 1, 0] *= fy / fx
    return Rz, A


def roll_batch(batch: PoseBatch, angle: torch.Tensor) -> PoseBatch:
    """``batch`` seen by cameras turned about their optical axes by ``angle`` ((B,) rad,
    positive from image +x towards +y); samples at angle 0 are unchanged.

    RGB is resampled bilinearly, the mask and the coordinates nearest (as the crops are
    cut); the context affine moves to the turned centre, the visible box is the turned mask's
    (to 1/a image px), the pose becomes ``Rz R``, ``Rz t``. A sample whose mask the context
    resolution loses entirely stays unturned.
    """
    turn = angle != 0
    if not bool(turn.any()):
        return batch
    K = batch.K.double()
    Rz, A = _pixel_maps(K, angle.to(K))
    C = batch.rgb.shape[-1]
    # output context px j reads the input at q = C/2 + A⁻¹ (j − C/2); pixel j sits at q = j
    idx = torch.arange(C, dtype=torch.float64)
    j = torch.stack(torch.meshgrid(idx, idx, indexing="xy"), -1) - C / 2  # (C, C, 2) x, y
    q = torch.einsum("bij,hwj->bhwi", torch.linalg.inv(A), j) + C / 2
    grid = (q / (C - 1) * 2 - 1).float()  # align_corners=True: index 0 -> -1, C-1 -> +1

    def sample(x: torch.Tensor, mode: str) -> torch.Tensor:
        return F.grid_sample(x.float(), grid, mode=mode, padding_mode="zeros", align_corners=True)

    rgb = sample(batch.rgb, "bilinear").round().clamp(0, 255).to(batch.rgb.dtype)
    mask = sample(batch.mask[:, None], "nearest")[:, 0] > 0.5
    xyz = sample(batch.xyz, "nearest").to(batch.xyz.dtype)
    turn &= mask.flatten(1).any(1)  # a mask lost to the context's resolution: leave it
    # the turned box: the mask's first/last column and row, in image px
    a = batch.ctx[:, 0].double()
    pp = K[:, :2, 2]
    centre = pp + torch.einsum("bij,bj->bi", A, batch.ctx[:, 1:].double() - pp)
    lo, hi = [], []
    for axis in (1, 2):  # columns (x): any over rows; rows (y): any over columns
        hit = mask.any(axis)
        lo.append(torch.where(hit, idx, torch.inf).amin(1))
        hi.append(torch.where(hit, idx, -torch.inf).amax(1))
    lo_t, hi_t = torch.stack(lo, 1), torch.stack(hi, 1)
    xy = centre + (lo_t - C / 2) / a[:, None]
    wh = (hi_t - lo_t) / a[:, None] + 1.0
    bbox = torch.cat([xy, wh], 1).to(batch.bbox.dtype)
    ctx = torch.cat([batch.ctx[:, :1], centre.to(batch.ctx.dtype)], 1)

    def keep(new: torch.Tensor, old: torch.Tensor) -> torch.Tensor:
        return torch.where(turn.view((-1,) + (1,) * (old.dim() - 1)), new, old)

    Rz_f = Rz.to(batch.R.dtype)
    return dataclasses.replace(
        batch,
        rgb=keep(rgb, batch.rgb), mask=keep(mask, batch.mask), xyz=keep(xyz, batch.xyz),
        ctx=keep(ctx, batch.ctx), bbox=keep(bbox, batch.bbox),
        R=keep(Rz_f @ batch.R, batch.R), t=keep(torch.einsum("bij,bj->bi", Rz_f, batch.t), batch.t),
    )  # fmt: skip
