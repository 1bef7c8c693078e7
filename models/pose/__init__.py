"""GDR-Net-like 6D pose head in plain PyTorch (no torchvision).

Modules, one concept each: :mod:`.config` (sizes and weights), :mod:`.encodings` (rot6d,
allocentric ↔ egocentric, SITE), :mod:`.roi` (DZI boxes, crops, 2D
coordinates), :mod:`.targets` (xyz maps, normalisation, regions), :mod:`.network`
(:class:`GdrPoseNet`), :mod:`.losses` (:func:`gdr_losses`) and :mod:`.decode` (poses from
outputs). Units follow BOP: mm, px, ``x_cam = R x_model + t``.
"""

from __future__ import annotations

from bopsurg.models.pose.config import PoseConfig
from bopsurg.models.pose.decode import (
    mean_pose,
    nearest_rotation,
    pnp_ransac_from_output,
    pose_from_output,
)
from bopsurg.models.pose.encodings import (
    SiteRoi,
    allo_to_ego,
    ego_to_allo,
    matrix_from_rot6d,
    ray_rotation,
    rot6d_from_matrix,
    site_decode,
    site_encode,
)
from bopsurg.models.pose.losses import gdr_losses, point_matching
from bopsurg.models.pose.network import GdrPoseNet, mask_probability
from bopsurg.models.pose.roi import crop, crop_theta, dzi_boxes, roi_coord_2d, roi_grid_to_image
from bopsurg.models.pose.targets import (
    XyzNormaliser,
    farthest_point_sampling,
    xyz_from_depth,
    xyz_to_region,
)

__all__ = [
    "GdrPoseNet",
    "PoseConfig",
    "SiteRoi",
    "XyzNormaliser",
    "allo_to_ego",
    "crop",
    "crop_theta",
    "dzi_boxes",
    "ego_to_allo",
    "farthest_point_sampling",
    "gdr_losses",
    "mask_probability",
    "matrix_from_rot6d",
    "mean_pose",
    "nearest_rotation",
    "pnp_ransac_from_output",
    "point_matching",
    "pose_from_output",
    "ray_rotation",
    "roi_coord_2d",
    "roi_grid_to_image",
    "rot6d_from_matrix",
    "site_decode",
    "site_encode",
    "xyz_from_depth",
    "xyz_to_region",
]
