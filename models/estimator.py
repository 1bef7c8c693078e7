"""The built-in ``gdrnet`` estimator: the stages of :mod:`bopsurg.models.stages` composed.

Registered as ``gdrnet`` under ``bopsurg.estimators`` (:func:`create` is the factory). Per
image: detect (or take external boxes), keep the best boxes of each object, the pose head's
pose of each box, then for the needle the refinement (its segmenter masks, the arc fit, and
the depth points when ``bopsurg predict`` gives a depth image) and the end check. Every
setting is a field of :class:`bopsurg.models.predict_config.PredictConfig`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch

from bopsurg.errors import BopsurgError
from bopsurg.estimation import Detections, ImageInput, PosePredictions
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
        return self.predict_batch([ImageInput(rgb, K, obj_ids, boxes, depth)])[0]

    @torch.inference_mode()
    def predict_batch(self, images: Sequence[ImageInput]) -> list[PosePredictions]:
        """Poses of the objects in each of several images, the same as :meth:`predict` of each:
        the detector on all images at once, the pose head on all their boxes, the needle
        stages (one fit) on all their needles. Images of different sizes go in one batch per
        size."""
        out: list[PosePredictions] = [PosePredictions.empty() for _ in images]
        found = self._boxes(images)
        sizes: dict[tuple[int, ...], list[int]] = {}
        for i, im in enumerate(images):
            if len(found[i]):
                sizes.setdefault(tuple(im.rgb.shape), []).append(i)
        for rows in sizes.values():
            preds = self._predict_same_size([images[i] for i in rows], [found[i] for i in rows])
            for i, pred in zip(rows, preds, strict=True):
                out[i] = pred
        return out

    def _boxes(self, images: Sequence[ImageInput]) -> list[Detections]:
        """The best boxes of the wanted objects in each image (our detector's, in one batch,
        where an image brings none)."""
        wanted = [
            tuple(o for o in (im.obj_ids or self.obj_ids) if o in self.obj_ids) for im in images
        ]
        detect = [i for i, im in enumerate(images) if im.boxes is None and wanted[i]]
        ours: dict[int, Detections] = {}
        if detect:
            if self.detector is None:
                raise BopsurgError(
                    "no detector loaded: set detector (a checkpoint) or pass --boxes"
                )
            found = self.detector.batch([images[i].rgb for i in detect])
            ours = dict(zip(detect, found, strict=True))
        per = self.config.detect.max_per_object
        return [
            best_boxes(ours.get(i, im.boxes), wanted[i], per) if wanted[i] else Detections.empty()
            for i, im in enumerate(images)
        ]

    def _predict_same_size(
        self, images: Sequence[ImageInput], found: Sequence[Detections]
    ) -> list[PosePredictions]:
        """The poses of the boxes ``found`` in images of one size (each with a box)."""
        dev = self.device
        counts = [len(f) for f in found]
        index = np.repeat(np.arange(len(images)), counts)
        stack = np.stack([im.rgb for im in images])
        image = torch.from_numpy(stack).to(dev).permute(0, 3, 1, 2).float() / 255
        K = np.stack([np.asarray(images[i].K, np.float64) for i in index.tolist()])
        bbox = np.concatenate([f.bbox for f in found]).astype(np.float64)
        b = torch.as_tensor(bbox, dtype=torch.float32, device=dev)
        box_xywh = torch.cat([b[:, :2] - 0.5, b[:, 2:]], dim=1)  # pixel-centre convention
        K_t = torch.as_tensor(K, dtype=torch.float32, device=dev)
        index_t = torch.as_tensor(index, device=dev)
        R, t = self.head(image, K_t, box_xywh, index_t)
        if self.head.obj_id == NEEDLE_OBJ_ID:
            depth = [images[i].depth for i in index.tolist()] if self.uses_depth else None
            batch = _Batch(image, K, K_t, index, index_t, box_xywh)
            R, t = self._needle_stages(batch, HeadPoses(R, t), depth, bbox)
        ends = np.cumsum(counts)[:-1]
        return [
            PosePredictions(f.obj_id, f.score, R_i, t_i, b_i)
            for f, R_i, t_i, b_i in zip(
                found, np.split(R, ends), np.split(t, ends), np.split(bbox, ends), strict=True
            )
        ]

    def _needle_stages(
        self,
        batch: _Batch,
        poses: HeadPoses,
        depth: list[np.ndarray | None] | None,
        bbox: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Refinement and end check of needle poses: R, t mm; the BOP boxes ``bbox`` (n, 4) of
        re-cropped ROIs are set to the grown boxes in place."""
        R, t = poses
        if self.refine is not None:
            ref = self.refine(
                batch.image,
                batch.K,
                batch.box_xywh,
                poses,
                head=lambda g, rows: self.head(
                    batch.image, batch.K_t[rows], g, batch.index_t[rows]
                ),
                depth=depth,
                index=batch.roi_image,
            )
            R, t = ref.R, ref.t
            bbox[ref.grown] = ref.boxes[ref.grown] + np.array([0.5, 0.5, 0.0, 0.0])  # BOP
        if self.ends is not None:
            R = self.ends(batch.image, batch.K, R, t, batch.roi_image)
        return R, t


class _Batch(NamedTuple):
    """The ROIs of a batch of images of one size, as the needle stages take them."""

    #: (B, 3, H, W) float RGB in [0, 1].
    image: torch.Tensor
    #: (n, 3, 3) each ROI's intrinsics, px (float64, and float32 on the device).
    K: np.ndarray
    K_t: torch.Tensor
    #: (n,) each ROI's image in ``image`` (and on the device).
    roi_image: np.ndarray
    index_t: torch.Tensor
    #: (n, 4) boxes (x, y, w, h), pixel-centre px.
    box_xywh: torch.Tensor


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
