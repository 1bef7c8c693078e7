"""The built-in ``gdrnet`` estimator: the stages of :mod:`bopsurg.models.stages` composed.

Registered as ``gdrnet`` under ``bopsurg.estimators`` (:func:`create` is the factory). Per
image: detect (or take external boxes), keep the best boxes of each object, the pose head's
pose of each box, then for the needle the refinement (its segmenter masks, the arc fit, and
the depth points when ``bopsurg predict`` gives a depth image) and the end check. Every
setting is a field of :class:`bopsurg.models.predict_config.PredictConfig`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from bopsurg.errors import BopsurgError
from bopsurg.estimation import Detections, PosePredictions
from bopsurg.models import config_tree
from bopsurg.models.predict_config import PredictConfig, weight_file
from bopsurg.models.stages.detect import DetectStage, best_boxes
from bopsurg.models.stages.ends import EndStage
from bopsurg.models.stages.head import HeadPoses, HeadStage
from bopsurg.models.stages.refine import RefineStage
from bopsurg.models.training import resolve_device

#: The object the refinement's arc model describes (the needle).
NEEDLE_OBJ_ID = 1


class GdrNetEstimator:
    """Detector, pose head, needle refinement and end check; implements
    :class:`bopsurg.estimation.PoseEstimator`.

    Args:
        config: Every setting (default: :class:`PredictConfig`'s defaults, the shipped model).
    """

    def __init__(self, config: PredictConfig | None = None) -> None:
        cfg = config or PredictConfig()
        self.config = cfg
        self.device = resolve_device(cfg.device)
        dev = self.device
        self.detector = (
            None
            if cfg.detector is None
            else DetectStage(weight_file("detector", cfg.detector), cfg.detect, dev)
        )
        self.head = HeadStage(weight_file("pose", cfg.pose), cfg.head, dev)
        self.obj_ids = (self.head.obj_id,)
        #: The models the poses refer to (see ``bopsurg.estimation.estimator_models``).
        self.object_models = {self.head.obj_id: self.head.model}
        seg = cfg.refine.segmenter
        self.refine = (
            None
            if seg is None
            else RefineStage.load(weight_file("segmenter", seg), cfg.refine, dev)
        )
        ends = cfg.ends.classifier
        self.ends = (
            None if ends is None else EndStage.load(weight_file("ends", ends), cfg.ends, dev)
        )
        #: ``bopsurg predict`` passes a depth image: the refinement is on and ``depth.mode=fit``.
        self.uses_depth = self.refine is not None and cfg.refine.depth.mode == "fit"
        self._check_arcs()

    def _check_arcs(self) -> None:
        """The end classifier and the segmenter must be for the same needle."""
        if self.ends is None or self.refine is None:
            return
        a, b = self.ends.judge.arc, self.refine.refiner.arc
        if not np.allclose([a.radius, a.arc_rad], [b.radius, b.arc_rad], rtol=1e-3):
            raise BopsurgError(
                f"gdrnet: the end classifier {self.config.ends.classifier} was trained for "
                f"another needle (radius {a.radius:.2f} mm, arc {np.rad2deg(a.arc_rad):.1f} "
                f"deg) than the segmenter (radius {b.radius:.2f} mm, arc "
                f"{np.rad2deg(b.arc_rad):.1f} deg)"
            )

    def resolved_config(self) -> dict[str, Any]:
        """Every setting this estimator runs with (written next to the results)."""
        resolved: dict[str, Any] = config_tree.to_dict(self.config)
        return resolved

    def detect(self, rgb: np.ndarray) -> Detections:
        """Boxes of our detector in one (H, W, 3) uint8 image (BOP xywh, px)."""
        if self.detector is None:
            raise BopsurgError("no detector loaded: set detector (a checkpoint) or pass --boxes")
        found: Detections = self.detector(rgb)
        return found

    def report(self) -> str | None:
        """What the stages did, for ``bopsurg predict``."""
        lines = [self.head.report()]
        lines += [s.report() for s in (self.refine, self.ends) if s is not None]
        return "; ".join(x for x in lines if x) or None

    @torch.inference_mode()
    def predict(
        self,
        rgb: np.ndarray,
        K: np.ndarray,
        *,
        obj_ids: tuple[int, ...] | None = None,
        boxes: Detections | None = None,
        depth: np.ndarray | None = None,
    ) -> PosePredictions:
        """Poses of the objects in one image (see :class:`bopsurg.estimation.PoseEstimator`);
        ``depth`` (H, W) mm, 0 where there is no reading, is used by the RGB-D fit."""
        wanted = tuple(o for o in (obj_ids or self.obj_ids) if o in self.obj_ids)
        if not wanted:
            return PosePredictions.empty()
        found = best_boxes(
            self.detect(rgb) if boxes is None else boxes,
            wanted,
            self.config.detect.max_per_object,
        )
        if len(found) == 0:
            return PosePredictions.empty()
        image = torch.from_numpy(rgb).to(self.device).permute(2, 0, 1)[None].float() / 255
        K_t = torch.as_tensor(K, dtype=torch.float32, device=self.device)
        b = torch.as_tensor(found.bbox, dtype=torch.float32, device=self.device)
        box_xywh = torch.cat([b[:, :2] - 0.5, b[:, 2:]], dim=1)  # pixel-centre convention
        R, t = self.head(image, K_t, box_xywh)
        bbox_out = np.array(found.bbox, dtype=np.float64, copy=True)
        if self.head.obj_id == NEEDLE_OBJ_ID:
            R, t = self._needle_stages(image, K, K_t, box_xywh, HeadPoses(R, t), depth, bbox_out)
        return PosePredictions(found.obj_id, found.score, R, t, bbox_out)

    def _needle_stages(
        self,
        image: torch.Tensor,
        K: np.ndarray,
        K_t: torch.Tensor,
        box_xywh: torch.Tensor,
        poses: HeadPoses,
        depth: np.ndarray | None,
        bbox: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Refinement and end check of needle poses: R, t mm; the BOP boxes ``bbox`` (n, 4) of
        re-cropped ROIs are set to the grown boxes in place."""
        R, t = poses
        unheld = np.zeros(len(R), dtype=bool)
        if self.refine is not None:
            ref = self.refine(
                image,
                K,
                box_xywh,
                poses,
                head=lambda g: self.head(image, K_t, g),
                depth=depth if self.uses_depth else None,
            )
            R, t, unheld = ref.R, ref.t, ref.unheld
            bbox[ref.grown] = ref.boxes[ref.grown] + np.array([0.5, 0.5, 0.0, 0.0])  # BOP
        if self.ends is not None:
            R = self.ends(image, K, R, t, unheld)
        return R, t


def create(options: Mapping[str, Any]) -> GdrNetEstimator:
    """The ``gdrnet`` factory for ``bopsurg predict``.

    ``options``: a (nested) mapping laid over :class:`PredictConfig`'s defaults, from
    ``--config FILE`` and ``--option KEY=VALUE`` (dotted keys: ``refine.depth.weight=8``).

    Raises:
        BopsurgError: An unknown key or a bad value (one line naming the key), or a missing
            weight file.
    """
    config = config_tree.from_mapping(PredictConfig, options, "gdrnet")
    return GdrNetEstimator(config)
