"""GDR-Net training losses: mask, xyz, region, point matching (PM), centroid and z.

All terms follow GDR-Net's definitions (every weight 1 by default, total = weighted sum):

- mask: with ``cfg.mask_loss="bce"`` (default) the mean binary cross-entropy between the
  mask logits and the soft visible mask (the fraction of each cell covered, ``"mask_soft"``);
  with ``"l1"`` GDR-Net's mean L1 between the raw output and the 0/1 visible mask (GDR-Net
  uses the truncated mask, which equals the visible one without background replacement).
- xyz: ``Σ M·|x̂ − x̄| / max(1, ΣM)`` per channel, summed over the 3 channels (M = visible mask,
  sums over the whole batch).
- region: cross-entropy over R + 1 classes on the visible pixels, ``Σ M·CE / max(1, ΣM)``.
- pm: ``mean_i ‖R̂ x_i − R̄ x_i‖₁ / max extent`` on the egocentric rotation built from the
  *predicted* translation (differentiable through SITE decoding and allo → ego); with
  ``cfg.symmetric`` the smallest value over ``R̄ S_k`` (identity included).
- centroid: mean L1 on (δx, δy); z: L1 on δz.

Samples with an empty visible mask carry no geometry: they add nothing to xyz and region (their
mask sum is 0) and are left out of pm, centroid and z (mean over the other samples, 0 if none).
The mask term keeps them: "nothing here" is a valid mask target.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from bopsurg.models.pose.config import PoseConfig
from bopsurg.models.pose.encodings import SiteRoi, allo_to_ego, matrix_from_rot6d, site_decode


def point_matching(
    R_pred: torch.Tensor,
    R_gt: torch.Tensor,
    points: torch.Tensor,
    sym_rotations: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per-sample PM distance ``mean_i ‖R̂ x_i − R̄ S x_i‖₁``, minimised over the symmetries S.

    Args:
        R_pred: (B, 3, 3) predicted rotations.
        R_gt: (B, 3, 3) GT rotations.
        points: (P, 3) model points, mm.
        sym_rotations: (S, 3, 3) symmetry rotations of the model, or None; the identity is
            always included.

    Returns:
        (B,) distances, mm.
    """
    eye = torch.eye(3, dtype=R_gt.dtype, device=R_gt.device)[None]
    syms = eye if sym_rotations is None else torch.cat([eye, sym_rotations.to(R_gt)])
    R_gts = R_gt[:, None] @ syms[None]  # (B, S, 3, 3)
    p_pred = torch.einsum("bij,pj->bpi", R_pred, points)  # (B, P, 3)
    p_gt = torch.einsum("bsij,pj->bspi", R_gts, points)  # (B, S, P, 3)
    dist = (p_pred[:, None] - p_gt).abs().sum(dim=-1).mean(dim=-1)  # (B, S)
    return dist.min(dim=1).values


def gdr_losses(
    out: dict[str, torch.Tensor],
    target: dict[str, torch.Tensor],
    model_points: torch.Tensor,
    cfg: PoseConfig,
    sym_rotations: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """The GDR-Net loss terms of a batch of B ROIs (maps at S_out = s).

    Args:
        out: :class:`~.network.GdrPoseNet` outputs.
        target: ``"mask_visib"`` (B, 1, s, s) float {0, 1} (where xyz and region are
            defined); optionally ``"mask_soft"`` (B, 1, s, s) in [0, 1], the covered fraction
            of each cell, for the BCE mask term (default: ``"mask_visib"``); ``"xyz"``
            (B, 3, s, s) normalised; ``"region"`` (B, s, s) long; ``"R"`` (B, 3, 3)
            egocentric GT; ``"site"`` (B, 3) SITE GT; and for decoding the predicted
            translation ``"K"`` (B, 3, 3), ``"centre"`` (B, 2) px, ``"wh"`` (B, 2) px,
            ``"side"`` (B,) px. ``"t"`` may be present (unused).
        model_points: (P, 3) model points, mm (≤ 3000 keeps the PM term cheap).
        cfg: sizes, SITE unit, weights, and ``symmetric``.
        sym_rotations: (S, 3, 3) symmetry rotations; used only when ``cfg.symmetric``.

    Returns:
        Scalar tensors ``mask, xyz, region, pm, centroid, z, total`` (pm in model extents).
    """
    if cfg.symmetric and sym_rotations is None:
        raise ValueError("cfg.symmetric is set but no sym_rotations were given")
    losses = {
        **_map_losses(out, target, cfg),
        **_pose_losses(out, target, model_points, cfg, sym_rotations if cfg.symmetric else None),
    }
    weights = {
        "mask": cfg.w_mask,
        "xyz": cfg.w_xyz,
        "region": cfg.w_region,
        "pm": cfg.w_pm,
        "centroid": cfg.w_centroid,
        "z": cfg.w_z,
    }
    zero = torch.zeros_like(losses["mask"])
    losses["total"] = sum((weights[k] * v for k, v in losses.items()), zero)
    return losses


def _map_losses(
    out: dict[str, torch.Tensor], target: dict[str, torch.Tensor], cfg: PoseConfig
) -> dict[str, torch.Tensor]:
    """The dense terms: visible mask (all cells), coordinates and regions (object cells)."""
    m = target["mask_visib"]
    n_fg = m.sum().clamp(min=1)
    if cfg.mask_loss == "bce":
        soft = target.get("mask_soft", m)
        loss_mask = F.binary_cross_entropy_with_logits(out["mask"], soft)
    else:
        loss_mask = (out["mask"] - m).abs().mean()

    # where() before abs(): a non-finite background target cannot leak NaN into the gradient
    xyz_diff = torch.where(m > 0, out["xyz"] - target["xyz"], 0.0)
    loss_xyz = (xyz_diff.abs() * m).sum() / n_fg

    ce = F.cross_entropy(out["region"], target["region"], reduction="none")  # (B, s, s)
    loss_region = (ce * m[:, 0]).sum() / n_fg
    return {"mask": loss_mask, "xyz": loss_xyz, "region": loss_region}


def _pose_losses(
    out: dict[str, torch.Tensor],
    target: dict[str, torch.Tensor],
    model_points: torch.Tensor,
    cfg: PoseConfig,
    syms: torch.Tensor | None,
) -> dict[str, torch.Tensor]:
    """The pose terms, on the samples that show the object only (an empty ROI may come with a
    degenerate box): point matching (closest symmetry with ``syms``), SITE centre and depth."""
    valid = target["mask_visib"].flatten(1).sum(dim=1) > 0  # (B,)
    n_valid = valid.sum().clamp(min=1)
    site = out["site"][valid]
    roi = SiteRoi(
        *(target[k][valid] for k in ("K", "centre", "wh", "side")), cfg.roi_out, cfg.z_unit_mm
    )
    t_pred = site_decode(site, roi)
    R_pred = allo_to_ego(matrix_from_rot6d(out["rot6d"][valid]), t_pred)
    pts = model_points.to(R_pred)
    extent = (pts.max(dim=0).values - pts.min(dim=0).values).max()
    pm = point_matching(R_pred, target["R"][valid], pts, syms)
    loss_pm = pm.sum() / extent / n_valid

    d_site = (site - target["site"][valid]).abs()
    loss_centroid = d_site[:, :2].mean(dim=1).sum() / n_valid
    loss_z = d_site[:, 2].sum() / n_valid
    return {"pm": loss_pm, "centroid": loss_centroid, "z": loss_z}
