"""From network outputs to BOP poses: the direct (Patch-PnP) path and a RANSAC-PnP path.

The direct path decodes rot6d (allocentric) and SITE into ``R_ego`` and ``t`` (mm), batched
and differentiable. The RANSAC path (GDR-Net's optional ``TEST.USE_PNP``) solves OpenCV's
PnP on the dense 2D-3D correspondences of the predicted xyz map, one ROI at a time on the CPU.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from numpy.typing import NDArray

from bopsurg.models.pose.config import PoseConfig
from bopsurg.models.pose.encodings import SiteRoi, allo_to_ego, matrix_from_rot6d, site_decode
from bopsurg.models.pose.network import mask_probability
from bopsurg.models.pose.roi import roi_grid_to_image
from bopsurg.models.pose.targets import XyzNormaliser

MIN_PNP_POINTS = 6


def pose_from_output(
    out: dict[str, torch.Tensor],
    K: torch.Tensor,
    centre: torch.Tensor,
    wh: torch.Tensor,
    side: torch.Tensor,
    cfg: PoseConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Egocentric pose from the network's "rot6d" and "site" outputs.

    Args:
        out: network outputs (needs "rot6d" (B, 6) and "site" (B, 3)).
        K: (B, 3, 3) intrinsics, px.
        centre: (B, 2) crop centres, px.
        wh: (B, 2) box sizes, px (the detection's at test time).
        side: (B,) crop sides, px.
        cfg: ``roi_out`` and ``z_unit_mm``.

    Returns:
        R_ego (B, 3, 3) and t (B, 3) mm.
    """
    t = site_decode(out["site"], SiteRoi(K, centre, wh, side, cfg.roi_out, cfg.z_unit_mm))
    return allo_to_ego(matrix_from_rot6d(out["rot6d"]), t), t


def nearest_rotation(m: torch.Tensor) -> torch.Tensor:
    """The proper rotations nearest (Frobenius norm) to (B, 3, 3) matrices ``m``: ``U Vᵀ`` of
    their SVD, the last column of U flipped where that would be a reflection."""
    U, _, Vh = torch.linalg.svd(m)
    d = torch.sign(torch.linalg.det(U @ Vh))
    U = torch.cat([U[..., :2], U[..., 2:] * d[:, None, None]], dim=-1)
    out: torch.Tensor = U @ Vh
    return out


def mean_pose(R: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Average of k pose estimates of each of B objects: the mean translation and the chordal
    mean rotation (:func:`nearest_rotation` to the mean matrix).

    Args:
        R: (B, k, 3, 3) rotations.
        t: (B, k, 3) translations, mm.

    Returns:
        R (B, 3, 3) and t (B, 3) mm.
    """
    return nearest_rotation(R.mean(dim=1)), t.mean(dim=1)


def pnp_ransac_from_output(
    out: dict[str, torch.Tensor],
    K: torch.Tensor,
    centre: torch.Tensor,
    side: torch.Tensor,
    normaliser: XyzNormaliser,
    cfg: PoseConfig,
    mask_thr: float = 0.3,
    reproj_px: float = 2.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Pose by RANSAC-PnP on the predicted xyz map (EPnP hypotheses, LM refinement on inliers).

    Correspondences: every output-map pixel whose mask probability (:func:`mask_probability`)
    exceeds ``mask_thr`` (a cell about one third covered by the object); its 2D point is
    the pixel's image position (``centre + (u − S/2)·side/S``, px) and its 3D point the
    de-normalised predicted xyz (object frame, mm).

    Args:
        out: network outputs (needs "mask" (B, 1, S, S) and "xyz" (B, 3, S, S)).
        K: (B, 3, 3) intrinsics, px.
        centre: (B, 2) crop centres, px.
        side: (B,) crop sides, px.
        normaliser: the xyz normalisation used for the targets.
        cfg: ``roi_out``.
        mask_thr: foreground threshold on the raw mask output.
        reproj_px: RANSAC inlier threshold, px.

    Returns:
        R (B, 3, 3) and t (B, 3) mm as float64 arrays, and ok (B,) bool; a ROI with fewer than
        6 foreground pixels or inliers, or where PnP fails, gets ok False, R = I and t = 0.
    """
    uv = roi_grid_to_image(centre, side, cfg.roi_out)
    xyz = normaliser.denormalise(out["xyz"].permute(0, 2, 3, 1))
    fg = mask_probability(out["mask"][:, 0], cfg) > mask_thr
    uv_np = uv.detach().cpu().double().numpy()
    xyz_np = xyz.detach().cpu().double().numpy()
    fg_np = fg.cpu().numpy()
    K_np = K.detach().cpu().double().numpy()

    n = uv_np.shape[0]
    R = np.tile(np.eye(3), (n, 1, 1))
    t = np.zeros((n, 3))
    ok = np.zeros(n, dtype=bool)
    for b in range(n):  # OpenCV solves one ROI at a time
        obj = np.ascontiguousarray(xyz_np[b][fg_np[b]])
        img = np.ascontiguousarray(uv_np[b][fg_np[b]])
        if len(obj) < MIN_PNP_POINTS:
            continue
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj,
            img,
            K_np[b],
            None,
            reprojectionError=reproj_px,
            confidence=0.99,
            flags=cv2.SOLVEPNP_EPNP,
        )
        if not found or inliers is None or len(inliers) < MIN_PNP_POINTS:
            continue
        inl = inliers[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K_np[b], None, rvec, tvec)
        R[b] = cv2.Rodrigues(rvec)[0]
        t[b] = tvec[:, 0]
        ok[b] = True
    return R, t, ok
