"""The built-in ``gdrnet`` estimator: YOLOX-like boxes, then the GDR-Net-like pose head.

Registered as ``gdrnet`` under ``bopsurg.estimators`` (:func:`create` is the factory). Per
image: letterbox to the detector input, detect, keep the best ``max_per_object`` boxes of each
object above ``conf``, crop a square ROI of side 1.5 x the box's longer side around the box
centre (test-time dynamic zoom-in), run the pose head, and decode the pose directly from its
rotation and SITE outputs (``decode=direct``, the default) or by PnP-RANSAC on its dense
2D-3D correspondences (``decode=pnp``), then optionally refine the needle's pose against its
mask predicted at full image resolution (``refine=fit``; :mod:`bopsurg.models.refine`) and,
when ``bopsurg predict`` hands it the image's depth, to the 3D points of that mask too
(``depth=fit``; :mod:`bopsurg.models.refine.wire3d`). Boxes from another detector can replace
ours.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bopsurg.bop.meshes import load_ply
from bopsurg.errors import BopsurgError
from bopsurg.estimation import Detections, PosePredictions
from bopsurg.models.checkpoint import load_checkpoint, load_weights
from bopsurg.models.detector import DetectorConfig, YoloxDetector
from bopsurg.models.detector.letterbox import letterbox
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
from bopsurg.models.refine.ends import EndJudge, load_judge
from bopsurg.models.refine.fit import FitSettings
from bopsurg.models.refine.refiner import NeedleRefiner
from bopsurg.models.training import resolve_device
from bopsurg.needle import needle_mesh

log = logging.getLogger(__name__)

#: The small model shipped with bopsurg (see MODEL_CARD.md there).
SHIPPED = Path(__file__).parent / "weights"
#: The object the refinement's arc model describes (the needle).
NEEDLE_OBJ_ID = 1
REFINE_MODES = ("fit", "none")
#: What the refinement does with a depth image: ``fit`` the arc to the visible mask's 3D
#: points together with the image evidence (:mod:`bopsurg.models.refine.wire3d`), or
#: ``none`` (RGB only).
DEPTH_MODES = ("fit", "none")
#: The refinement's fit as the estimator runs it by default, set for the shipped pose head.
#: The fit's prior is the head's error model, and the shipped head's depth is off by less
#: than the generic 4 mm (median |dz| 1.58 mm on the model card's test split, network only),
#: so its depth σ is 2.5 mm; the segmenter's probabilities are resampled 2x finer before
#: the threshold (:attr:`FitSettings.evidence_upsample`). Chosen on the two validation sets
#: (other episodes; a harness on cached ROIs of the step-5 head), refined median TE / MSSD mm:
#: generic → depth σ 2.5 → and 2x evidence: VAL1 0.947 / 1.179 → 0.878 / 1.158 → 0.853 /
#: 1.140, VAL2 1.289 / 1.629 → 1.311 / 1.589 → 1.283 / 1.563 (σ 2.0 and 3.0 within 0.03 of
#: 2.5). The model card has the test split's numbers.
REFINE_FIT = FitSettings(prior_mm=(1.5, 1.5, 2.5), evidence_upsample=2)

#: Test-time zoom: the direct decoding averages the poses of crops whose sides are these
#: multiples of the test-time DZI crop (1.5 x the box: 1.25, 1.5 and 1.75 x the box). The
#: head's SITE depth is not scale-invariant: on the model card's 478 held-out needles the
#: median signed depth error of the first shipped head is +3.0 / +0.7 / -3.1 % at crops of
#: 1.2 / 1.5 / 1.8 x the box (commit e38f2a1's: +1.8 / +0.7 / -1.5 %), nearly linear in the
#: crop side, so a symmetric set of crops cancels that bias and averages the noise
#: (``bench/bench_refine.py --segmenter none --option zoom=0.8`` prints it). Same needles,
#: e38f2a1's head and the segmenter, one crop -> these three: network TE 3.12 -> 2.92 mm, MSSD
#: 3.77 -> 3.45 mm; refined TE 2.90 -> 2.67 mm, MSSD 3.34 -> 3.05 mm (five crops from 1.2 to
#: 1.8 x did no better on a scratch subset). ``zoom=1`` is one crop.
ZOOM_SCALES = (5 / 6, 1.0, 7 / 6)
#: The shipped needle segmenter (see MODEL_CARD.md); the refinement is on by default when
#: this file exists, ``refine=none`` turns it off.
SHIPPED_SEGMENTER = SHIPPED / "needle_seg.pt"
#: The end check's logit margin for a needle pose the RGB-D fit took without the pose head's
#: prior (:attr:`.refiner.Refined.unheld`): the points put the head's pose aside there, and
#: the tip and tail the fit kept from it (:func:`.fit.same_ends`) are a guess, so the
#: classifier decides alone.
UNHELD_ENDS_MARGIN = 0.0

#: The shipped needle-end classifier (:mod:`bopsurg.models.refine.ends`; MODEL_CARD.md): on
#: by default when this file exists, ``ends=none`` turns it off.
SHIPPED_ENDS = SHIPPED / "needle_ends.pt"
#: Re-crop: when the segmenter's visible mask grows the detection box's longer side by at
#: least this factor (the needle runs past its box), the pose head and the segmenter run again
#: on the union of the box and the mask's box. The detector boxes part of a needle that is
#: large in the image or split by an occluder, and a crop of part of a needle reads as a
#: whole needle farther away (on the model card's first test split, 49 of the 70 needles whose
#: refined TE was over 5 mm had a box whose longer side was under 0.8 of the GT visible box's;
#: on GT visible boxes 41 of the 70 came under 3 mm). Chosen on the validation sets, refined
#: median TE / MSSD mm without → 1.2 → 1.1: VAL1 0.917 / 1.178 → 0.910 / 1.180 → 0.881 /
#: 1.125, VAL2 1.312 / 1.612 → 1.301 / 1.560 → 1.311 / 1.591.
RECROP_GROWTH = 1.1
#: Most re-crops of one ROI (each grows the box by at most the segmenter's pad).
RECROP_PASSES = 3


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


class PoseHead:
    """A loaded pose head for one object."""

    def __init__(self, path: str | Path, device: torch.device) -> None:
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
        self.net.to(device).eval()
        self.meta = meta
        #: The mesh the poses refer to: ``meta["model_ply"]`` (beside the checkpoint) when the
        #: training recorded it, else bopsurg's default needle, which every generated dataset
        #: and the shipped model use.
        ply = meta.get("model_ply")
        self.model = load_ply(Path(path).parent / ply) if ply else needle_mesh()


class Detector:
    """A loaded detector and its class → object id table."""

    def __init__(self, path: str | Path, device: torch.device) -> None:
        state, info = load_checkpoint(path, "detector")
        try:
            self.cfg = DetectorConfig.from_dict(info["config"])
            self.classes = [int(c) for c in info["meta"]["classes"]]
        except (KeyError, TypeError, ValueError) as err:
            raise BopsurgError(
                f"{Path(path).with_suffix('.json')}: bad detector config ({err})"
            ) from err
        self.net = YoloxDetector(self.cfg)
        load_weights(self.net, state, path)
        self.net.to(device).eval()


class GdrNetEstimator:
    """Detector + pose heads; implements :class:`bopsurg.estimation.PoseEstimator`.

    Args:
        detector: Detector checkpoint, or None to require external boxes.
        poses: Pose-head checkpoints, one per object.
        device: Torch device name (``auto`` = CUDA when available).
        conf: Minimum detection score kept.
        max_per_object: Boxes (hence poses) kept per object and image, best first.
        decode: ``direct`` (rotation + SITE heads) or ``pnp`` (PnP-RANSAC on the coordinates;
            a ROI where PnP finds no solution keeps the direct pose, see ``pnp_fallback``).
        segmenter: Needle-segmenter checkpoint for the refinement, or None for none.
        mask: The segmenter's evidence the fit uses (``full``: the arc on the full mask, the
            wire explaining the visible one; ``visible``: the visible mask alone; None:
            ``full`` when the segmenter predicts the full mask).
        fit: The refinement's fit settings (default :data:`REFINE_FIT`).
        zoom: Crop sides of the direct decoding, as multiples of the test-time DZI crop
            (default :data:`ZOOM_SCALES`); the poses of the crops are averaged.
        recrop: With the refinement: run the needle's ROI again on the box grown to its
            visible mask when that grows the box's longer side this many times
            (:data:`RECROP_GROWTH`); 0 turns it off.
        ends: Needle-end classifier checkpoint, or None: after the refinement, a needle pose
            whose tip looks less like a tip than its tail is turned end for end
            (:mod:`bopsurg.models.refine.ends`).
        ends_margin: The logit margin the tail must win by; None: the one recorded with the
            classifier (its checkpoint's ``meta.margin``, else 0).
        det_input_hw: The detector's input (H, W), px, multiples of 32, instead of the one
            it was trained at (its checkpoint's ``input_hw``): the network is convolutional,
            and a larger input shows a thin needle with more pixels of wire.
        depth: With the refinement and a depth image: ``fit`` the needle's arc to the 3D points
            of its visible mask together with the image (:data:`DEPTH_MODES`), or ``none``.
    """

    def __init__(
        self,
        detector: str | Path | None,
        poses: list[str | Path],
        *,
        device: str = "auto",
        conf: float = 0.05,
        max_per_object: int = 1,
        decode: str = "direct",
        segmenter: str | Path | None = None,
        mask: str | None = None,
        fit: FitSettings | None = None,
        zoom: tuple[float, ...] = ZOOM_SCALES,
        recrop: float = RECROP_GROWTH,
        ends: str | Path | None = None,
        ends_margin: float | None = None,
        det_input_hw: tuple[int, int] | None = None,
        depth: str = "fit",
    ) -> None:
        if depth not in DEPTH_MODES:
            raise BopsurgError(f"gdrnet: depth must be one of {DEPTH_MODES}, got {depth!r}")
        if decode not in ("direct", "pnp"):
            raise BopsurgError(f"decode must be 'direct' or 'pnp', got {decode!r}")
        if not zoom or not all(np.isfinite(z) and z > 0 for z in zoom):
            raise BopsurgError(f"gdrnet: zoom must be positive crop-side multiples, got {zoom}")
        self.zoom = tuple(float(z) for z in zoom)
        if not (np.isfinite(recrop) and (recrop == 0 or recrop >= 1)):
            raise BopsurgError(f"gdrnet: recrop must be 0 (off) or a growth >= 1, got {recrop}")
        self.recrop = float(recrop)
        #: ROIs whose pose comes from a box grown to the segmenter's visible mask (``recrop``).
        self.recropped = 0
        self.device = resolve_device(device)
        self.detector = None if detector is None else Detector(detector, self.device)
        if self.detector is not None and det_input_hw is not None:
            try:
                cfg = dataclasses.replace(self.detector.cfg, input_hw=tuple(det_input_hw))
            except ValueError as err:
                raise BopsurgError(f"gdrnet: det_size: {err}") from err
            self.detector.cfg = cfg
        heads = [PoseHead(p, self.device) for p in poses]
        self.heads = {h.obj_id: h for h in heads}
        self.obj_ids = tuple(sorted(self.heads))
        #: The models the poses refer to (see ``bopsurg.estimation.estimator_models``).
        self.object_models = {o: h.model for o, h in self.heads.items()}
        self.conf, self.max_per_object, self.decode = conf, max_per_object, decode
        #: With ``decode="pnp"``: ROIs solved by PnP-RANSAC, and those that fell back to the
        #: direct decoding (too few mask pixels or inliers); a bench reports both.
        self.pnp_solved = 0
        self.pnp_fallback = 0
        #: The refinement stage (needle only), or None.
        self.refiner = (
            None
            if segmenter is None
            else NeedleRefiner.from_checkpoint(segmenter, self.device, fit or REFINE_FIT, mask)
        )
        #: Whether :meth:`predict` uses a depth image (``bopsurg predict`` then passes one):
        #: the refinement is on and ``depth=fit``.
        self.uses_depth = self.refiner is not None and depth == "fit"
        #: The needle-end check (needle only), or None.
        self.ends: EndJudge | None = (
            None if ends is None else load_judge(ends, self.device, ends_margin)
        )
        if self.ends is not None and self.refiner is not None:
            a, b = self.ends.arc, self.refiner.arc
            if not np.allclose([a.radius, a.arc_rad], [b.radius, b.arc_rad], rtol=1e-3):
                raise BopsurgError(
                    f"gdrnet: the end classifier {ends} was trained for another needle (radius "
                    f"{a.radius:.2f} mm, arc {np.rad2deg(a.arc_rad):.1f} deg) than the "
                    f"segmenter (radius {b.radius:.2f} mm, arc {np.rad2deg(b.arc_rad):.1f} deg)"
                )

    @torch.inference_mode()
    def detect(self, rgb: np.ndarray) -> Detections:
        """Boxes of our detector in one (H, W, 3) uint8 image (BOP xywh, px)."""
        if self.detector is None:
            raise BopsurgError("no detector loaded: pass a detector checkpoint or --boxes")
        image, scale = letterbox(rgb, self.detector.cfg.input_hw)
        x = torch.from_numpy(image).to(self.device).permute(2, 0, 1)[None].float() / 255
        det = self.detector.net.detect(x, conf_thr=self.conf)[0].cpu().numpy().astype(np.float64)
        xyxy = det[:, :4] / scale
        xywh = np.concatenate([xyxy[:, :2], xyxy[:, 2:] - xyxy[:, :2]], axis=1)
        obj = np.array([self.detector.classes[int(c)] for c in det[:, 5]], np.int64)
        return Detections(obj, det[:, 4], xywh)

    def report(self) -> str | None:
        """How PnP (``decode="pnp"``) and the refinement went, for ``bopsurg predict``."""
        lines = []
        if self.decode == "pnp":
            lines.append(
                f"PnP-RANSAC solved {self.pnp_solved} ROIs, {self.pnp_fallback} fell back to "
                "the direct decoding"
            )
        if self.refiner is not None:
            st = self.refiner.stats
            lines.append(
                f"refinement improved {st.refined} needle poses, {st.kept} kept the network's"
                + (f", {self.recropped} re-cropped to their whole mask" if self.recrop else "")
            )
        if self.refiner is not None and self.refiner.stats.unheld:
            lines.append(
                f"RGB-D fits without the head's prior: {self.refiner.stats.unheld}"
                + (f" (end check at margin {UNHELD_ENDS_MARGIN:g})" if self.ends else "")
            )
        if self.ends is not None:
            st_e = self.ends.stats
            lines.append(
                f"end check (margin {self.ends.margin:g}) turned {st_e.swapped} of "
                f"{st_e.checked} needles end for end"
            )
        return "; ".join(lines) or None

    def _select(self, boxes: Detections, obj_ids: tuple[int, ...]) -> Detections:
        keep = []
        for o in obj_ids:
            rows = np.flatnonzero(boxes.obj_id == o)
            rows = rows[np.argsort(-boxes.score[rows], kind="stable")][: self.max_per_object]
            keep.extend(rows.tolist())
        return boxes.subset(np.array(keep, dtype=np.int64))

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
        wanted = tuple(o for o in (obj_ids or self.obj_ids) if o in self.heads)
        if not wanted:
            return PosePredictions.empty()
        found = self._select(self.detect(rgb) if boxes is None else boxes, wanted)
        if len(found) == 0:
            return PosePredictions.empty()
        image = torch.from_numpy(rgb).to(self.device).permute(2, 0, 1)[None].float() / 255
        Ks = torch.as_tensor(K, dtype=torch.float32, device=self.device)
        R_out, t_out = np.zeros((len(found), 3, 3)), np.zeros((len(found), 3))
        bbox_out = np.array(found.bbox, dtype=np.float64, copy=True)
        for obj in np.unique(found.obj_id):
            rows = np.flatnonzero(found.obj_id == obj)
            head = self.heads[int(obj)]
            b = torch.as_tensor(found.bbox[rows], dtype=torch.float32, device=self.device)
            box_xywh = torch.cat([b[:, :2] - 0.5, b[:, 2:]], dim=1)  # pixel-centre convention
            K_b = Ks[None].expand(len(rows), 3, 3)
            R, t = self._head_poses(head, image, K_b, box_xywh)
            unheld = np.zeros(len(rows), dtype=bool)
            if self.refiner is not None and int(obj) == NEEDLE_OBJ_ID:
                R, t, fit_boxes, grown, unheld = self.refine_needles(
                    head, image, K, box_xywh, R, t, depth=depth
                )
                bbox_out[rows[grown]] = fit_boxes[grown] + np.array([0.5, 0.5, 0.0, 0.0])  # BOP
            if self.ends is not None and int(obj) == NEEDLE_OBJ_ID:
                # The margin is the head's say on which end is the tip; where the points put
                # its pose aside (the RGB-D fit without its prior was kept), it has none.
                margin = np.where(unheld, UNHELD_ENDS_MARGIN, self.ends.margin)
                R, _ = self.ends(image, K, R, t, margin)
            R_out[rows], t_out[rows] = R, t
        return PosePredictions(found.obj_id, found.score, R_out, t_out, bbox_out)

    @torch.inference_mode()
    def refine_needles(
        self,
        head: PoseHead,
        image: torch.Tensor,
        K: np.ndarray,
        box_xywh: torch.Tensor,
        R: np.ndarray,
        t: np.ndarray,
        refiner: NeedleRefiner | None = None,
        recrop: float | None = None,
        depth: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The refinement stage of needle ROIs: the segmenter's masks around each box, the ROI
        run again (pose head and segmenter) on a box grown to its visible mask while that
        grows the box by ``recrop`` (:data:`RECROP_GROWTH`, at most :data:`RECROP_PASSES`
        times), then the fit from the pose head's pose; a re-cropped ROI whose fit the fit's
        out-of-domain guard refuses gets the fit on its first box instead. With a ``depth``
        image (and ``depth=fit``) the fit also weighs its visible mask's 3D points.

        Args:
            head: The needle's pose head.
            image: (1, 3, H, W) float RGB in [0, 1].
            K: (3, 3) intrinsics, px.
            box_xywh: (n, 4) boxes (x, y, w, h), pixel-centre px.
            R, t: The pose head's poses on those boxes (n, 3, 3), (n, 3) mm, float64.
            refiner: The stage's segmenter and fit (default: the estimator's; a bench may
                pass one on other evidence).
            recrop: Default: the estimator's; 0 turns re-cropping off.
            depth: (H, W) depth image, mm (0: no reading), or None.

        Returns:
            R (n, 3, 3), t (n, 3) mm, the boxes the poses come from (n, 4) (pixel-centre px),
            which of them grew (n,) bool, and which poses the RGB-D fit took without the pose
            head's prior (n,) bool (:attr:`.refiner.Refined.unheld`).
        """
        refiner = refiner or self.refiner
        if refiner is None:
            raise BopsurgError("gdrnet: no refinement stage (no segmenter loaded)")
        recrop = self.recrop if recrop is None else recrop
        K = np.asarray(K, float)
        K_b = torch.as_tensor(K, dtype=torch.float32, device=self.device)[None]
        masks = refiner.observe(image, K, box_xywh, R, t)
        boxes = box_xywh.detach().cpu().double().numpy()
        first = (R, t, masks, boxes)  # what a refused re-crop falls back to
        R, t = R.copy(), t.copy()  # the re-crops write into these
        grew = np.zeros(len(R), dtype=bool)
        todo = np.ones(len(R), dtype=bool)  # ROIs whose box may still grow
        for _ in range(RECROP_PASSES if recrop > 0 else 0):
            grown, redo = grown_boxes(boxes, masks.visible_boxes(), recrop)
            redo &= todo
            if not redo.any():
                break
            # the needle runs past its box: pose head and segmenter again on all that was seen
            g = torch.as_tensor(grown[redo], dtype=box_xywh.dtype, device=box_xywh.device)
            R[redo], t[redo] = self._head_poses(head, image, K_b.expand(len(g), 3, 3), g)
            masks = masks.replaced(redo, refiner.observe(image, K, g, R[redo], t[redo]))
            boxes, todo, grew = np.where(redo[:, None], grown, boxes), redo, grew | redo
        depth = depth if self.uses_depth else None
        R, t, fitted, unheld = refiner.fit(masks, K, R, t, depth)
        # A re-crop whose fit the out-of-domain guard refused (the grown mask holds what the
        # wire cannot explain: an instrument, a groove) is undone: the first box's fit.
        back = grew & ~fitted
        if back.any():
            R0, t0, masks0, boxes0 = first
            refiner.stats.kept -= int(back.sum())  # counted again by the fit below
            redo = refiner.fit(masks0.subset(back), K, R0[back], t0[back], depth)
            R[back], t[back], unheld[back] = redo.R, redo.t, redo.unheld
            boxes[back], grew[back] = boxes0[back], False
        self.recropped += int(grew.sum())
        return R, t, boxes, grew, unheld

    def _head_poses(
        self, head: PoseHead, image: torch.Tensor, K_b: torch.Tensor, box_xywh: torch.Tensor
    ) -> tuple[np.ndarray, np.ndarray]:
        """The pose head's poses (R (n, 3, 3), t (n, 3) mm, float64) of boxes (n, 4) (x, y, w,
        h), pixel-centre px, by the estimator's ``decode``."""
        centre, side = dzi_boxes(box_xywh, None, head.cfg, tuple(image.shape[-2:]))
        if self.decode != "pnp":  # the mean pose is a float64 rotation already
            return self._zoomed_direct(head, image, K_b, centre, side, box_xywh[:, 2:])
        out = self._run_head(head, image, centre, side)
        R, t, ok = pnp_ransac_from_output(out, K_b, centre, side, head.normaliser, head.cfg)
        R_d, t_d = pose_from_output(out, K_b, centre, box_xywh[:, 2:], side, head.cfg)
        # float64 rotations (the network's float32 Gram-Schmidt is off by ~1e-7)
        R_d = nearest_rotation(R_d.double()).cpu().numpy()
        R = np.where(ok[:, None, None], R, R_d)
        t = np.where(ok[:, None], t, t_d.double().cpu().numpy())
        self.pnp_solved += int(ok.sum())
        self.pnp_fallback += int((~ok).sum())
        if not ok.all():
            log.debug("pnp: %d of %d ROIs fell back to direct decoding", (~ok).sum(), len(ok))
        return R, t

    def _run_head(
        self, head: PoseHead, image: torch.Tensor, centre: torch.Tensor, side: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """The pose head's outputs on the square crops (centre (m, 2), side (m,) px)."""
        cfg, hw = head.cfg, tuple(image.shape[-2:])
        index = torch.zeros(len(centre), dtype=torch.long, device=self.device)
        roi = crop(image, centre, side, cfg.roi_in, "bilinear", index=index)
        out: dict[str, torch.Tensor] = head.net(roi, roi_coord_2d(centre, side, cfg.roi_out, hw))
        return out

    def _zoomed_direct(
        self,
        head: PoseHead,
        image: torch.Tensor,
        K: torch.Tensor,
        centre: torch.Tensor,
        side: torch.Tensor,
        wh: torch.Tensor,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Direct decoding averaged over the :attr:`zoom` crops of each ROI, in one batch of
        n·k crops: R (n, 3, 3) and t (n, 3) mm, float64."""
        n, k = len(centre), len(self.zoom)
        zoom = torch.tensor(self.zoom, dtype=side.dtype, device=side.device)
        sides = (side[:, None] * zoom).clamp(1.0, float(max(image.shape[-2:]))).reshape(-1)
        centres = centre.repeat_interleave(k, dim=0)
        out = self._run_head(head, image, centres, sides)
        R, t = pose_from_output(
            out, K.repeat_interleave(k, dim=0), centres, wh.repeat_interleave(k, dim=0), sides,
            head.cfg,
        )  # fmt: skip
        R_m, t_m = mean_pose(R.double().reshape(n, k, 3, 3), t.double().reshape(n, k, 3))
        return R_m.cpu().numpy(), t_m.cpu().numpy()


def create(options: Mapping[str, Any]) -> GdrNetEstimator:
    """The ``gdrnet`` factory for ``bopsurg predict``.

    Options (strings from ``--option``): ``detector`` and ``pose`` (checkpoint paths; default:
    the shipped model), ``device`` (``auto``), ``conf`` (0.05), ``max_per_object`` (1),
    ``decode`` (``direct`` or ``pnp``), ``no_detector`` (``1``: external boxes only),
    ``refine`` (``fit``: fit the needle arc to its full-resolution mask; ``none``: the network's
    pose as it is; default ``fit`` when a segmenter is shipped, else ``none``),
    ``segmenter`` (its checkpoint; default: the shipped one), ``mask`` (the segmenter's
    evidence the fit uses: ``full``, its full and visible masks, the default when it predicts
    the full mask, or ``visible`` alone), ``min_explained`` (the fit's out-of-domain guard: the
    share of the visible mask its wire must explain, else the network's pose is kept; default
    :attr:`FitSettings.min_explained`; the rest of the fit is :data:`REFINE_FIT`) and
    ``zoom`` (comma-separated crop-side multiples whose direct poses are averaged; default
    :data:`ZOOM_SCALES`, ``1`` for one crop) and ``recrop`` (with the refinement: the growth
    of the box's longer side by the segmenter's visible mask that runs the needle's ROI again
    on the grown box; default :data:`RECROP_GROWTH`, ``0`` off), ``ends`` (the needle-end
    classifier's checkpoint, or ``none``; default: the shipped one when it exists) and
    ``ends_margin`` (the logit margin a swap needs; default: the one recorded with the
    classifier, chosen on validation splits), ``det_size`` (the detector's input ``HxW``,
    multiples of 32; default: the one it was trained at) and ``depth`` (with the refinement:
    ``fit`` the arc to the visible mask's 3D points when ``bopsurg predict`` passes a depth
    image, the default; ``none``: RGB only).
    """
    known = {"detector", "pose", "device", "conf", "max_per_object", "decode", "no_detector"}
    known |= {"refine", "segmenter", "mask", "min_explained", "zoom", "recrop", "ends"}
    known |= {"ends_margin", "det_size", "depth"}
    unknown = sorted(set(options) - known)
    if unknown:
        raise BopsurgError(f"gdrnet: unknown option(s) {unknown}; known: {sorted(known)}")
    detector = options.get("detector") or SHIPPED / "detector.pt"
    pose = options.get("pose") or SHIPPED / "pose.pt"
    if str(options.get("no_detector", "0")) in ("1", "true", "yes"):
        detector = None
    try:
        conf = float(options.get("conf", 0.05))
        max_per = int(options.get("max_per_object", 1))
        min_explained = float(options.get("min_explained", FitSettings.min_explained))
        recrop = float(options.get("recrop", RECROP_GROWTH))
        ends_margin = float(options["ends_margin"]) if "ends_margin" in options else None
    except ValueError as err:
        raise BopsurgError(f"gdrnet: bad option value ({err})") from err
    if ends_margin is not None and not np.isfinite(ends_margin):
        raise BopsurgError(f"gdrnet: ends_margin must be a finite logit margin, got {ends_margin}")
    try:
        zoom = tuple(map(float, str(options["zoom"]).split(","))) if "zoom" in options else ()
    except ValueError as err:
        raise BopsurgError(f"gdrnet: zoom must be numbers, e.g. zoom=0.9,1,1.1 ({err})") from err
    det_size = None
    if "det_size" in options:
        try:
            h, w = (int(v) for v in str(options["det_size"]).lower().split("x"))
        except ValueError as err:
            raise BopsurgError(
                f"gdrnet: det_size must be HxW in px, e.g. det_size=384x512 ({err})"
            ) from err
        det_size = (h, w)
    segmenter = Path(options.get("segmenter") or SHIPPED_SEGMENTER)
    default_refine = "fit" if "segmenter" in options or SHIPPED_SEGMENTER.exists() else "none"
    refine = str(options.get("refine", default_refine))
    if refine not in REFINE_MODES:
        raise BopsurgError(f"gdrnet: refine must be one of {REFINE_MODES}, got {refine!r}")
    if refine == "fit" and not segmenter.exists():
        raise BopsurgError(
            f"gdrnet: refine=fit needs a needle segmenter, {segmenter} does not exist "
            "(train one with python -m bopsurg.models.refine.train_seg, pass segmenter=PATH)"
        )
    ends_opt = str(options.get("ends", "")).strip()
    if ends_opt == "none":
        ends = None
    elif ends_opt:
        ends = Path(ends_opt)
        if not ends.exists():
            raise BopsurgError(f"gdrnet: ends={ends} does not exist")
    else:
        ends = SHIPPED_ENDS if SHIPPED_ENDS.exists() else None
    return GdrNetEstimator(
        detector,
        [pose],
        device=str(options.get("device", "auto")),
        conf=conf,
        max_per_object=max_per,
        decode=str(options.get("decode", "direct")),
        segmenter=None if refine == "none" else segmenter,
        mask=str(options["mask"]) if "mask" in options else None,
        fit=dataclasses.replace(REFINE_FIT, min_explained=min_explained),
        zoom=zoom or ZOOM_SCALES,
        recrop=recrop,
        ends=ends,
        ends_margin=ends_margin,
        det_input_hw=det_size,
        depth=str(options.get("depth", "fit")),
    )
