"""The refinement stage of the ``gdrnet`` estimator: evidence at full resolution, then the fit.

Per ROI: the segmenter (:mod:`.seghead`) predicts the needle's masks on a square grid of
about one image px around the detection (the visible one, and the full, amodal one when it
predicts it), and :func:`.fit.refine_poses` fits the exact arc to them (the wire explains the
visible pixels, the arc lies on the full mask), starting from the pose head's estimate; a fit
that does not lower its own cost keeps the pose head's pose. The masks' evidence is prepared
per ROI (cv2), then every ROI of a call is fitted at once, on the refiner's device.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
from numpy.typing import NDArray

from bopsurg.errors import BopsurgError
from bopsurg.geometry import transform_pts
from bopsurg.models.checkpoint import load_checkpoint, load_weights
from bopsurg.models.pose.roi import crop
from bopsurg.models.predict_config import DepthSettings, FitSettings
from bopsurg.models.refine.arc import ArcModel
from bopsurg.models.refine.depth_fit import fit_depths
from bopsurg.models.refine.fit import Evidence, Starts, refine_poses
from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig
from bopsurg.models.refine.wire3d import depth_points, strided_points

#: The fit's evidence from a segmenter: ``full`` (the default when the segmenter predicts the
#: full, amodal mask: the arc may lie on the full mask, the pixels it must explain are the
#: visible ones) or ``visible`` (the visible mask for both). Fitting the full mask alone was
#: worse on both validation sets (MODEL_CARD.md).
MASK_KINDS = ("full", "visible")

#: Evidence source: (image (1, 3, H, W) float in [0, 1], centres (n, 2) px, sides (n,) px,
#: grid side S) → foreground probabilities on the ROI grids: (n, S, S) of one mask, or
#: (n, 2, S, S) of the visible and the full mask.
EvidenceFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, int], np.ndarray]


class Segmenter:
    """A loaded segmenter checkpoint (kind ``needle_seg``) and the arc it was trained for.

    Args:
        path: The checkpoint.
        device: Where it runs.
        mask: The mask it returns (:data:`MASK_KINDS`); ``auto``: ``full`` when the checkpoint
            predicts it, else ``visible``.
    """

    def __init__(self, path: str | Path, device: torch.device, mask: str = "auto") -> None:
        state, info = load_checkpoint(path, "needle_seg")
        try:
            self.cfg = SegConfig.from_dict(info["config"])
            arc = info["meta"]["arc"]
            self.arc = ArcModel(radius=float(arc["radius"]), arc_rad=float(arc["arc_rad"]))
        except (KeyError, TypeError, ValueError) as err:
            raise BopsurgError(
                f"{Path(path).with_suffix('.json')}: bad segmenter config ({err})"
            ) from err
        if mask == "auto":
            mask = "full" if self.cfg.amodal else "visible"
        if mask not in MASK_KINDS:
            raise BopsurgError(f"segmenter mask must be one of {MASK_KINDS}, got {mask!r}")
        if mask == "full" and not self.cfg.amodal:
            raise BopsurgError(f"{path}: this segmenter predicts no full (amodal) mask")
        self.mask = mask
        self.outputs = [0, 1] if mask == "full" else [0]  # indices of the net's outputs used
        self.net = NeedleSegNet(self.cfg)
        load_weights(self.net, state, path)
        self.net.to(device).eval()
        self.device = device

    @torch.inference_mode()
    def __call__(
        self, image: torch.Tensor, centre: torch.Tensor, side: torch.Tensor, size: int
    ) -> np.ndarray:
        """Foreground probabilities of the ROIs: (n, size, size) visible, or (n, 2, size,
        size) visible and full with ``mask="full"`` (see :data:`EvidenceFn`)."""
        index = torch.zeros(len(centre), dtype=torch.long, device=image.device)
        roi = crop(image, centre, side, size, "bilinear", index=index)
        prob = torch.sigmoid(self.net(roi))[:, self.outputs].float().cpu().numpy()
        return prob if len(self.outputs) > 1 else prob[:, 0]


def arc_boxes(
    box_xywh: torch.Tensor,
    arc: ArcModel,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    max_growth: float = 3.0,
) -> torch.Tensor:
    """Boxes (n, 4) (x, y, w, h), px, grown to hold the arc projected at the poses ``R``
    (n, 3, 3), ``t`` (n, 3) mm. A pose that puts the arc behind the camera, or whose arc would
    grow the box's longer side more than ``max_growth`` times (a start far off, where the
    grown crop would shrink the needle out of the segmenter's reach), keeps its box."""
    X = transform_pts(arc.points(32), R, t)
    z = X[..., 2:]
    uv = (X @ K.T)[..., :2] / np.where(z > 1e-6, z, 1.0)
    ok = (z[..., 0] > 1e-6).all(axis=1) & np.isfinite(uv).all(axis=(1, 2))
    b = box_xywh.detach().cpu().double().numpy()
    lo = np.minimum(b[:, :2], uv.min(axis=1))
    hi = np.maximum(b[:, :2] + b[:, 2:], uv.max(axis=1))
    ok &= (hi - lo).max(axis=1) <= max_growth * np.maximum(b[:, 2:].max(axis=1), 1.0)
    grown = np.where(ok[:, None], np.concatenate([lo, hi - lo], axis=1), b)
    return torch.as_tensor(grown, dtype=box_xywh.dtype, device=box_xywh.device)


def upsampled(
    prob: np.ndarray, factor: int, origin: np.ndarray, step: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """Probabilities (S, S) or (C, S, S) on a grid whose pixel (0, 0) sits at image
    ``origin`` (2,) px, ``step`` image px apart, resampled ``factor`` times finer (bilinear):
    the fine probabilities, and the fine grid's origin and step. Fine pixel (i, j) sits at
    coarse ``((j + 0.5) / factor - 0.5, (i + 0.5) / factor - 0.5)`` (OpenCV pixel centres)."""
    if factor <= 1:
        return prob, origin, step
    p = np.asarray(prob, np.float32)
    flat = p.reshape(-1, *p.shape[-2:])
    n = p.shape[-1] * factor
    out = np.stack([cv2.resize(c, (n, n), interpolation=cv2.INTER_LINEAR) for c in flat])
    fine_origin = np.asarray(origin, float) + step * (0.5 / factor - 0.5)
    return out.reshape(*p.shape[:-2], n, n), fine_origin, step / factor


@dataclass(frozen=True)
class RoiMasks:
    """The segmenter's foreground probabilities on the square grids of n ROIs.

    Attributes:
        prob: (n, S, S) visible mask, or (n, 2, S, S) visible and full (amodal) masks.
        origin: (n, 2) image px of each grid's pixel (0, 0) (OpenCV pixel centres).
        step: (n,) image px per grid pixel.
    """

    prob: np.ndarray
    origin: np.ndarray
    step: np.ndarray

    def visible_boxes(self, threshold: float) -> np.ndarray:
        """(n, 4) boxes (x, y, w, h) of each ROI's visible mask (probability above
        ``threshold``), pixel-centre px like the estimator's boxes (x, y: the left and
        top edges of the first pixel); NaN where the mask is empty."""
        prob = np.asarray(self.prob[:, 0] if self.prob.ndim == 4 else self.prob, np.float64)
        vis: NDArray[np.bool_] = np.asarray(prob > threshold, dtype=bool).reshape(prob.shape)
        out = np.full((len(vis), 4), np.nan)
        rows, cols = vis.any(axis=2), vis.any(axis=1)  # (n, S): rows / columns with foreground
        some = np.any(rows, axis=1)
        idx = np.arange(vis.shape[-1])
        lo = np.stack([np.where(cols, idx, np.inf).min(1), np.where(rows, idx, np.inf).min(1)], 1)
        hi = np.stack([np.where(cols, idx, -np.inf).max(1), np.where(rows, idx, -np.inf).max(1)], 1)
        s = self.step[:, None]
        out[some, :2] = (self.origin + (lo - 0.5) * s)[some]
        out[some, 2:] = ((hi - lo + 1.0) * s)[some]
        return out

    def subset(self, rows: np.ndarray) -> RoiMasks:
        """The masks of the ROIs ``rows`` (a bool (n,) mask or indices)."""
        return RoiMasks(self.prob[rows], self.origin[rows], self.step[rows])

    def replaced(self, rows: np.ndarray, other: RoiMasks) -> RoiMasks:
        """These masks with the ROIs ``rows`` (bool (n,)) taken from ``other`` (their count)."""
        prob, origin, step = self.prob.copy(), self.origin.copy(), self.step.copy()
        prob[rows], origin[rows], step[rows] = other.prob, other.origin, other.step
        return RoiMasks(prob, origin, step)


class Refined(NamedTuple):
    """What :meth:`NeedleRefiner.fit` gives for n ROIs."""

    #: (n, 3, 3) rotations and (n, 3) translations, mm.
    R: np.ndarray
    t: np.ndarray
    #: (n,) bool: the fit changed the pose head's pose.
    changed: np.ndarray


class NeedleRefiner:
    """Refines pose-head estimates of the needle against full-resolution evidence.

    Args:
        evidence: where the foreground comes from (a :class:`Segmenter`, or e.g. GT masks in
            a bench).
        arc: the needle's centre line.
        grid: evidence grid side S, px (the segmenter's ROI side).
        pad: grid side = pad · max(w, h) of the detection box.
        fit: the image fit's settings.
        depth: the RGB-D fit's settings (used when :meth:`fit` gets a depth image).
        whole: frame the box grown to hold the start pose's whole projected arc (a segmenter
            trained with :attr:`SegConfig.frame` ``"whole"``), so that the evidence covers
            the part of a needle hidden in tissue.
        device: where the fits run (the segmenter's, from :meth:`for_segmenter`).
    """

    def __init__(
        self,
        evidence: EvidenceFn,
        arc: ArcModel,
        grid: int,
        pad: float = 1.5,
        fit: FitSettings | None = None,
        depth: DepthSettings | None = None,
        whole: bool = False,
        device: torch.device | str = "cpu",
    ) -> None:
        self.evidence, self.arc, self.grid, self.pad = evidence, arc, grid, pad
        self.whole = whole
        self.device = torch.device(device)
        self.settings = fit or FitSettings()
        self.depth = depth or DepthSettings()

    @classmethod
    def for_segmenter(
        cls, seg: Segmenter, fit: FitSettings | None = None, depth: DepthSettings | None = None
    ) -> NeedleRefiner:
        """A refiner on a loaded segmenter: its arc, ROI size, padding, framing and device."""
        whole = seg.cfg.frame == "whole"
        return cls(seg, seg.arc, seg.cfg.roi, seg.cfg.pad, fit, depth, whole, seg.device)

    def grids(self, box_xywh: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Grid centre (n, 2) px and side (n,) px of boxes (x, y, w, h) in pixel-centre px."""
        centre = box_xywh[:, :2] + 0.5 * box_xywh[:, 2:]
        return centre, self.pad * box_xywh[:, 2:].max(dim=1).values.clamp(min=1.0)

    def observe(
        self,
        image: torch.Tensor,
        K: np.ndarray,
        box_xywh: torch.Tensor,
        R: np.ndarray,
        t: np.ndarray,
    ) -> RoiMasks:
        """The segmenter's masks on the ROI grids of boxes (x, y, w, h), pixel-centre px (the
        poses ``R`` (n, 3, 3), ``t`` (n, 3) mm only frame a ``whole`` segmenter's ROI)."""
        if self.whole:
            box_xywh = arc_boxes(box_xywh, self.arc, np.asarray(K, float), R, t)
        centre, side = self.grids(box_xywh)
        prob = self.evidence(image, centre, side, self.grid)
        c_np = centre.detach().cpu().double().numpy()
        step = side.detach().cpu().double().numpy() / self.grid
        return RoiMasks(np.asarray(prob), c_np - 0.5 * self.grid * step[:, None], step)

    def visible_boxes(self, masks: RoiMasks) -> np.ndarray:
        """(n, 4) boxes of the ROIs' visible masks (see :meth:`RoiMasks.visible_boxes`)."""
        return masks.visible_boxes(self.settings.mask_threshold)

    def fit(
        self,
        masks: RoiMasks,
        K: np.ndarray,
        R: np.ndarray,
        t: np.ndarray,
        depth: np.ndarray | Sequence[np.ndarray | None] | None = None,
    ) -> Refined:
        """Poses (R (n, 3, 3), t (n, 3) mm) fitted to ``masks`` from the pose head's and which
        ROIs changed (:class:`Refined`), all ROIs at once on the refiner's device.

        ``K``: (3, 3) intrinsics, px, or (n, 3, 3) one per ROI. ``depth``: None (RGB), one depth
        image (H, W) mm (0: no reading) for all ROIs, or a sequence of n entries, each a depth
        image or None (RGB for that ROI). RGB-D: the visible mask's pixels back-projected are
        the fit's points (its depth term), and the arc fitted to those points alone
        (:func:`.depth_fit.fit_depths`) is one more start."""
        n, s = len(R), self.settings
        Ks = np.broadcast_to(np.asarray(K, float), (n, 3, 3))
        depths = _per_roi(depth, n)

        evidence: list[Evidence] = []
        points: list[np.ndarray | None] = []
        for i in range(n):  # once per ROI: distance transforms, back-projection
            ev, visible = self._evidence(masks, i)
            d = depths[i]
            evidence.append(ev)
            points.append(None if d is None else self.roi_points(ev, visible, d, Ks[i]))
        with_depth = np.array([p is not None for p in points], bool)
        has = np.flatnonzero(with_depth)
        alone = fit_depths(
            R[has], t[has], [points[i] for i in has], self.arc, self.depth.points, self.device
        )
        starts = Starts(alone.R[alone.used], alone.t[alone.used], has[alone.used])
        fitted = [p if p is not None and len(p) >= s.min_evidence else None for p in points]
        res = refine_poses(
            R, t, Ks, evidence, self.arc, s, fitted, starts, depth=self.depth, device=self.device
        )
        return Refined(res.R, res.t, res.improved)

    def roi_points(
        self, ev: Evidence, visible: np.ndarray, depth: np.ndarray, K: np.ndarray
    ) -> np.ndarray:
        """The RGB-D fit's points of one ROI: its visible mask's pixels (on the evidence's
        grid) back-projected with ``depth`` (H, W) mm and ``K`` (3, 3), at most
        ``depth.max_points`` of them, evenly strided (N, 3) mm."""
        rows, cols = np.nonzero(visible)
        uv = ev.origin + ev.step * np.stack([cols, rows], 1)
        points: np.ndarray = strided_points(depth_points(uv, depth, K), self.depth.max_points)
        return points

    def _evidence(self, masks: RoiMasks, i: int) -> tuple[Evidence, np.ndarray]:
        """ROI ``i``'s evidence for the fit, and its visible mask (on the evidence's grid)."""
        up = max(1, int(self.settings.evidence_upsample))
        p_i, origin, step = upsampled(masks.prob[i], up, masks.origin[i], masks.step[i])
        fg = p_i > self.settings.mask_threshold
        # (2, S, S): visible and full; the full mask bounds the arc, the visible one is
        # what it must explain
        if fg.ndim == 3:
            return Evidence.from_mask(fg[1], origin, step, explain=fg[0]), fg[0]
        return Evidence.from_mask(fg, origin, step), fg

    def __call__(
        self,
        image: torch.Tensor,
        K: np.ndarray,
        box_xywh: torch.Tensor,
        R: np.ndarray,
        t: np.ndarray,
        depth: np.ndarray | None = None,
    ) -> Refined:
        """The refined poses (:class:`Refined`): :meth:`observe`, then :meth:`fit` (no re-crops:
        those are the stage's, :class:`bopsurg.models.stages.refine.RefineStage`).

        Args:
            image: (1, 3, H, W) float RGB in [0, 1].
            K: (3, 3) intrinsics, px.
            box_xywh: (n, 4) boxes (x, y, w, h), pixel-centre px.
            R, t: the pose head's estimates, float64.
            depth: (H, W) depth image, mm, or None (RGB only).
        """
        return self.fit(self.observe(image, K, box_xywh, R, t), K, R, t, depth)


def _per_roi(
    depth: np.ndarray | Sequence[np.ndarray | None] | None, n: int
) -> list[np.ndarray | None]:
    """The depth image of each of n ROIs (None: RGB) from :meth:`NeedleRefiner.fit`'s
    ``depth`` (one (H, W) image for all, or one entry per ROI, e.g. an (n, H, W) stack)."""
    if depth is None:
        return [None] * n
    if isinstance(depth, np.ndarray) and depth.ndim == 2:
        return [depth] * n
    if len(depth) != n:
        raise ValueError(f"depth: {len(depth)} entries for {n} ROIs")
    return list(depth)
