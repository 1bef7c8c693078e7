"""Stage 2: the GDR-Net-like pose head's pose of each box.

Per box: a square crop of side 1.5 x the box's longer side around its centre (test-time
dynamic zoom-in), the pose head, and the pose decoded directly from its rotation and SITE
outputs, averaged over the crops of :attr:`HeadSettings.zoom` (``decode=direct``), or by
PnP-RANSAC on its dense 2D-3D correspondences (``decode=pnp``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from bopsurg.bop.meshes import ObjectModel, load_ply
from bopsurg.errors import BopsurgError
from bopsurg.models.checkpoint import load_checkpoint, load_weights
from bopsurg.models.inference import for_inference
from bopsurg.models.pose.config import PoseConfig
from bopsurg.models.pose.decode import (
    mean_pose,
    nearest_rotation,
    pnp_ransac_from_output,
    pose_from_output,
)
from bopsurg.models.pose.network import GdrPoseNet
from bopsurg.models.pose.roi import crop, dzi_boxes, roi_coord_2d
from bopsurg.models.pose.targets import XyzNormaliser
from bopsurg.models.predict_config import HeadSettings
from bopsurg.needle import needle_mesh

log = logging.getLogger(__name__)


class HeadPoses(NamedTuple):
    """The pose head's poses of n boxes: R (n, 3, 3), t (n, 3) mm, float64."""

    R: np.ndarray
    t: np.ndarray


@dataclass
class HeadStats:
    """With ``decode=pnp``: ROIs solved by PnP-RANSAC, and those that kept the direct pose."""

    pnp_solved: int = 0
    pnp_fallback: int = 0


class HeadStage:
    """A loaded pose head for one object, and how its output is decoded.

    Args:
        path: The pose-head checkpoint.
        settings: Decoding and test-time zoom.
        device: Where it runs.
    """

    def __init__(self, path: str | Path, settings: HeadSettings, device: torch.device) -> None:
        state, info = load_checkpoint(path, "pose")
        try:
            self.cfg = PoseConfig.from_dict(info["config"])
            meta = info["meta"]
            self.obj_id = int(meta["obj_id"])
            self.normaliser = XyzNormaliser(
                torch.tensor(meta["xyz_centre"], dtype=torch.float32), float(meta["xyz_scale"])
            )
        except (KeyError, TypeError, ValueError) as err:
            raise BopsurgError(
                f"{Path(path).with_suffix('.json')}: bad pose config ({err})"
            ) from err
        self.net = GdrPoseNet(self.cfg)
        load_weights(self.net, state, path)
        for_inference(self.net, device)
        self.settings, self.device, self.meta = settings, device, meta
        self.stats = HeadStats()
        #: The mesh the poses refer to: ``meta["model_ply"]`` (beside the checkpoint) when the
        #: training recorded it, else bopsurg's default needle.
        ply = meta.get("model_ply")
        self.model: ObjectModel = load_ply(Path(path).parent / ply) if ply else needle_mesh()

    @torch.inference_mode()
    def __call__(
        self,
        image: torch.Tensor,
        K: torch.Tensor,
        box_xywh: torch.Tensor,
        index: torch.Tensor | None = None,
    ) -> HeadPoses:
        """Poses of boxes (n, 4) (x, y, w, h), pixel-centre px, in ``image`` (B, 3, H, W)
        float RGB in [0, 1]: box i in image ``index[i]`` ((n,) long; None: all in image 0),
        with intrinsics ``K`` (3, 3) px, or (n, 3, 3) one per box."""
        n = len(box_xywh)
        K_b = K[None].expand(n, 3, 3) if K.dim() == 2 else K
        if index is None:
            index = torch.zeros(n, dtype=torch.long, device=image.device)
        centre, side = dzi_boxes(box_xywh, None, self.cfg, tuple(image.shape[-2:]))
        if self.settings.decode == "direct":
            return self._zoomed_direct(image, K_b, centre, side, box_xywh[:, 2:], index)
        out = self._run(image, centre, side, index)
        R, t, ok = pnp_ransac_from_output(out, K_b, centre, side, self.normaliser, self.cfg)
        R_d, t_d = pose_from_output(out, K_b, centre, box_xywh[:, 2:], side, self.cfg)
        # float64 rotations (the network's float32 Gram-Schmidt is off by ~1e-7)
        R_d = nearest_rotation(R_d.double()).cpu().numpy()
        R = np.where(ok[:, None, None], R, R_d)
        t = np.where(ok[:, None], t, t_d.double().cpu().numpy())
        self.stats.pnp_solved += int(ok.sum())
        self.stats.pnp_fallback += int((~ok).sum())
        if not ok.all():
            log.debug("pnp: %d of %d ROIs fell back to direct decoding", (~ok).sum(), len(ok))
        return HeadPoses(R, t)

    def report(self) -> str | None:
        """What PnP did (``decode=pnp``), for ``bopsurg predict``."""
        if self.settings.decode != "pnp":
            return None
        st = self.stats
        return (
            f"PnP-RANSAC solved {st.pnp_solved} ROIs, {st.pnp_fallback} fell back to "
            "the direct decoding"
        )

    def _run(
        self, image: torch.Tensor, centre: torch.Tensor, side: torch.Tensor, index: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """The network's outputs on the square crops (centre (m, 2), side (m,) px) of the
        images ``index`` (m,)."""
        cfg, hw = self.cfg, tuple(image.shape[-2:])
        roi = crop(image, centre, side, cfg.roi_in, "bilinear", index=index)
        out: dict[str, torch.Tensor] = self.net(roi, roi_coord_2d(centre, side, cfg.roi_out, hw))
        return out

    def _zoomed_direct(
        self,
        image: torch.Tensor,
        K: torch.Tensor,
        centre: torch.Tensor,
        side: torch.Tensor,
        wh: torch.Tensor,
        index: torch.Tensor,
    ) -> HeadPoses:
        """Direct decoding averaged over the ``zoom`` crops of each ROI, in one batch of n·k
        crops."""
        n, k = len(centre), len(self.settings.zoom)
        zoom = torch.tensor(self.settings.zoom, dtype=side.dtype, device=side.device)
        sides = (side[:, None] * zoom).clamp(1.0, float(max(image.shape[-2:]))).reshape(-1)
        centres = centre.repeat_interleave(k, dim=0)
        out = self._run(image, centres, sides, index.repeat_interleave(k, dim=0))
        R, t = pose_from_output(
            out, K.repeat_interleave(k, dim=0), centres, wh.repeat_interleave(k, dim=0), sides,
            self.cfg,
        )  # fmt: skip
        R_m, t_m = mean_pose(R.double().reshape(n, k, 3, 3), t.double().reshape(n, k, 3))
        return HeadPoses(R_m.cpu().numpy(), t_m.cpu().numpy())
