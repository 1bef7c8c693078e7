"""Stage 1: the YOLOX-like detector's boxes of the objects in one image."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from bopsurg.errors import BopsurgError
from bopsurg.estimation import Detections
from bopsurg.models.checkpoint import load_checkpoint, load_weights
from bopsurg.models.detector import DetectorConfig, YoloxDetector
from bopsurg.models.detector.letterbox import letterbox
from bopsurg.models.inference import for_inference
from bopsurg.models.predict_config import DetectSettings


class DetectStage:
    """A loaded detector, its class → object id table and the stage's settings.

    Args:
        path: The detector checkpoint.
        settings: Score threshold, boxes per object, input size.
        device: Where it runs.
    """

    def __init__(self, path: str | Path, settings: DetectSettings, device: torch.device) -> None:
        state, info = load_checkpoint(path, "detector")
        try:
            cfg = DetectorConfig.from_dict(info["config"])
            self.classes = [int(c) for c in info["meta"]["classes"]]
            if settings.input_hw is not None:
                cfg = dataclasses.replace(cfg, input_hw=tuple(settings.input_hw))
        except (KeyError, TypeError, ValueError) as err:
            raise BopsurgError(
                f"{Path(path).with_suffix('.json')}: bad detector config ({err})"
            ) from err
        self.cfg, self.settings, self.device = cfg, settings, device
        self.net = YoloxDetector(cfg)
        load_weights(self.net, state, path)
        for_inference(self.net, device)

    def __call__(self, rgb: np.ndarray) -> Detections:
        """Boxes in one (H, W, 3) uint8 image (BOP xywh, px) scoring at least ``conf``."""
        return self.batch([rgb])[0]

    @torch.inference_mode()
    def batch(self, rgbs: Sequence[np.ndarray]) -> list[Detections]:
        """Boxes in each of several (H, W, 3) uint8 images (BOP xywh, px) scoring at least
        ``conf``: the letterboxed images in one forward."""
        if not rgbs:
            return []
        boxed = [letterbox(rgb, self.cfg.input_hw) for rgb in rgbs]
        x = torch.from_numpy(np.stack([im for im, _ in boxed])).to(self.device)
        x = x.permute(0, 3, 1, 2).float().div_(255)
        found = self.net.detect(x, conf_thr=self.settings.conf)
        return [self._boxes(d, scale) for d, (_, scale) in zip(found, boxed, strict=True)]

    def _boxes(self, det_t: torch.Tensor, scale: float) -> Detections:
        """One image's detections (k, 6) in input px -> BOP boxes in image px."""
        det = det_t.cpu().numpy().astype(np.float64)
        xyxy = det[:, :4] / scale
        xywh = np.concatenate([xyxy[:, :2], xyxy[:, 2:] - xyxy[:, :2]], axis=1)
        obj = np.array([self.classes[int(c)] for c in det[:, 5]], np.int64)
        return Detections(obj, det[:, 4], xywh)


def best_boxes(boxes: Detections, obj_ids: tuple[int, ...], per_object: int) -> Detections:
    """The ``per_object`` best-scoring boxes of each object in ``obj_ids`` (stable order)."""
    keep = []
    for o in obj_ids:
        rows = np.flatnonzero(boxes.obj_id == o)
        rows = rows[np.argsort(-boxes.score[rows], kind="stable")][:per_object]
        keep.extend(rows.tolist())
    return boxes.subset(np.array(keep, dtype=np.int64))
