"""Stage 3: the needle's pose fitted to full-resolution evidence (RGB, and RGB-D with depth).

Per needle ROI: the segmenter's masks around the box; where the visible mask runs past the
box (:class:`RecropSettings`), the pose head and the segmenter run again on the union of the
box and the mask's box; then the arc fit (:func:`bopsurg.models.refine.fit.refine_pose`) from
the pose head's pose, with the mask's depth points when there is a depth image.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from bopsurg.models.inference import for_inference
from bopsurg.models.predict_config import RecropSettings, RefineSettings
from bopsurg.models.refine import workers
from bopsurg.models.refine.refiner import NeedleRefiner, RoiMasks, Segmenter
from bopsurg.models.refine.workers import cpu_workers
from bopsurg.models.stages.head import HeadPoses

#: Re-runs the pose head on grown boxes (m, 4) (x, y, w, h), pixel-centre px, of the ROIs
#: ``rows`` ((m,) indices into the stage's ROIs: their images and cameras).
HeadFn = Callable[[torch.Tensor, np.ndarray], HeadPoses]

#: Depth for the fit: None (RGB), one (H, W) image for all ROIs, or one entry per ROI (an
#: (H, W) image, mm, 0 where there is no reading, or None).
Depth = np.ndarray | Sequence[np.ndarray | None] | None


class Refinement(NamedTuple):
    """The refined poses of n needle ROIs.

    Attributes:
        R: (n, 3, 3) rotations.
        t: (n, 3) translations, mm.
        boxes: (n, 4) the boxes the poses come from (x, y, w, h), pixel-centre px.
        grown: (n,) bool: the box grew to the needle's visible mask (a re-crop).
    """

    R: np.ndarray
    t: np.ndarray
    boxes: np.ndarray
    grown: np.ndarray


@dataclass
class RefineStats:
    """Needle poses the fit changed or left as the pose head gave them, and re-cropped ROIs."""

    refined: int = 0
    kept: int = 0
    recropped: int = 0


def grown_boxes(
    boxes: np.ndarray, seen: np.ndarray, min_growth: float
) -> tuple[np.ndarray, np.ndarray]:
    """Boxes grown to hold what the segmenter saw of each object.

    Args:
        boxes: (n, 4) boxes (x, y, w, h), px (one convention for both arguments).
        seen: (n, 4) boxes of the segmenter's visible masks, NaN rows where it saw nothing.
        min_growth: grow a box only where the union's longer side is at least this multiple
            of the box's.

    Returns:
        The boxes (n, 4), the union where it grew enough, and which did (n,) bool.
    """
    boxes, seen = np.asarray(boxes, float), np.asarray(seen, float)
    lo = np.minimum(boxes[:, :2], seen[:, :2])
    hi = np.maximum(boxes[:, :2] + boxes[:, 2:], seen[:, :2] + seen[:, 2:])
    union = np.concatenate([lo, hi - lo], axis=1)
    grow = np.isfinite(seen).all(axis=1)
    grow &= union[:, 2:].max(axis=1) >= min_growth * boxes[:, 2:].max(axis=1)
    return np.where(grow[:, None], union, boxes), grow


class RefineStage:
    """Segment, re-crop and fit the needle ROIs of a batch of images.

    Args:
        refiner: The segmenter and the fits (:class:`NeedleRefiner`).
        recrop: When to run a ROI again on its grown box.
    """

    def __init__(self, refiner: NeedleRefiner, recrop: RecropSettings) -> None:
        self.refiner, self.recrop = refiner, recrop
        self.stats = RefineStats()

    @classmethod
    def load(cls, path: str | Path, settings: RefineSettings, device: torch.device) -> RefineStage:
        """The stage on the segmenter checkpoint ``path``."""
        seg = Segmenter(path, device, settings.mask)
        for_inference(seg.net, device)
        return cls(NeedleRefiner.for_segmenter(seg, settings.fit, settings.depth), settings.recrop)

    def __call__(
        self,
        image: torch.Tensor,
        K: np.ndarray,
        box_xywh: torch.Tensor,
        poses: HeadPoses,
        head: HeadFn | None = None,
        depth: Depth = None,
        index: np.ndarray | None = None,
    ) -> Refinement:
        """The refined poses of needle boxes (n, 4) (x, y, w, h), pixel-centre px, of a batch
        of images; the fits of all n ROIs in one :meth:`NeedleRefiner.fit`.

        Args:
            image: (B, 3, H, W) float RGB in [0, 1].
            K: (3, 3) intrinsics, px, or (n, 3, 3) one per ROI.
            box_xywh: The boxes.
            poses: The pose head's poses of the boxes.
            head: Re-runs the pose head on grown boxes (None: no re-crops).
            depth: None (RGB only), one (H, W) depth image, mm (0: no reading), or one per
                ROI (:data:`Depth`).
            index: (n,) the image of each ROI (None: all in image 0).
        """
        n = len(box_xywh)
        K = np.broadcast_to(np.asarray(K, float), (n, 3, 3)).copy()  # writable, per ROI
        index = np.zeros(n, dtype=np.int64) if index is None else np.asarray(index)
        masks = self._observe(image, K, box_xywh, poses.R, poses.t, index)
        boxes = box_xywh.detach().cpu().double().numpy()
        R, t = poses.R.copy(), poses.t.copy()  # the re-crops write into these
        grew = np.zeros(n, dtype=bool)
        todo = np.ones(n, dtype=bool)  # ROIs whose box may still grow
        passes = self.recrop.passes if self.recrop.growth > 0 and head is not None else 0
        for _ in range(passes):
            grown, redo = grown_boxes(boxes, self.refiner.visible_boxes(masks), self.recrop.growth)
            redo &= todo
            if not redo.any() or head is None:
                break
            # the needle runs past its box: pose head and segmenter again on all that was seen
            g = torch.as_tensor(grown[redo], dtype=box_xywh.dtype, device=box_xywh.device)
            R[redo], t[redo] = head(g, np.flatnonzero(redo))
            again = self._observe(image, K[redo], g, R[redo], t[redo], index[redo])
            masks = masks.replaced(redo, again)
            boxes, todo, grew = np.where(redo[:, None], grown, boxes), redo, grew | redo
        out = self.refiner.fit(masks, K, R, t, depth)
        self._count(out.changed, grew)
        return Refinement(out.R, out.t, boxes, grew)

    def _observe(
        self,
        image: torch.Tensor,
        K: np.ndarray,
        box_xywh: torch.Tensor,
        R: np.ndarray,
        t: np.ndarray,
        index: np.ndarray,
    ) -> RoiMasks:
        """The segmenter's masks of the ROIs (:meth:`NeedleRefiner.observe`), image by image
        of the batch; K (m, 3, 3) and ``index`` (m,) per ROI."""

        images = np.unique(index)
        order = [np.flatnonzero(index == b) for b in images]  # each image's ROIs, once

        def observe(which: np.ndarray) -> list[RoiMasks]:
            out = []
            for j in which.tolist():
                b, rows = int(images[j]), order[j]
                sel = torch.as_tensor(rows, device=box_xywh.device)
                m = self.refiner.observe(
                    image[b : b + 1], K[rows[0]], box_xywh[sel], R[rows], t[rows]
                )
                out.append(m)
            return out

        # the images side by side, a thread each (the segmenter's small convolutions gain
        # less from a second intra-op thread than from a second image)
        with cpu_workers(image.device) as count:
            groups = workers.split(np.arange(images.size), count)
            parts = [m for g in workers.run(observe, groups) for m in g]
        inv = np.argsort(np.concatenate(order), kind="stable")
        return RoiMasks(
            np.concatenate([m.prob for m in parts])[inv],
            np.concatenate([m.origin for m in parts])[inv],
            np.concatenate([m.step for m in parts])[inv],
        )

    def _count(self, changed: np.ndarray, grew: np.ndarray) -> None:
        st = self.stats
        st.refined += int(changed.sum())
        st.kept += int((~changed).sum())
        st.recropped += int(grew.sum())

    def report(self) -> str:
        """What the refinement did, for ``bopsurg predict``."""
        st = self.stats
        text = f"refinement improved {st.refined} needle poses, {st.kept} kept the network's"
        if self.recrop.growth > 0:
            text += f", {st.recropped} re-cropped to their whole mask"
        return text
