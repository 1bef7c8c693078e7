"""BOP24/BOP25 6D-detection scores: average precision over MSSD and MSPD thresholds.

Reproduces ``scripts/eval_bop24_pose.py`` of the reference toolkit (``eval_calc_errors.py``
and ``eval_calc_scores.py`` in ``detection`` mode, ``n_top = 0``, ``visib_gt_min = 0.1``,
``score.calc_pose_detection_scores``, ``score.calc_ap``):

- per image only the 100 best-scored estimates are kept (score descending, ties in file
  order); only the images of ``test_targets_bop24.json`` are evaluated;
- an estimate is evaluated when its object has a GT instance in the image (any visibility);
  estimates of objects absent from the image are never false positives;
- errors: MSSD / diameter (θ = 0.05 … 0.5), MSSD in mm (θ = 2, 4, … 20 mm), MSPD × 640 / W
  (θ = 5 … 50 px); MSSD is +inf where ``‖t_est − t_gt‖ ≥ diameter`` (the reference's
  sphere pre-check);
- per threshold, greedy matching (:mod:`bopsurg.evaluation.matching`) against every GT
  instance; per object: GT instances with ``visib_fract ≥ 0.1`` are the targets, estimates
  matched to a less visible instance are ignored, the others are TP (matched) or FP;
- AP = COCO's 101-point interpolated precision; mAP = mean over objects with targets of the
  mean AP over thresholds; ``bop24_mAP = (mAP_mssd + mAP_mspd) / 2``, ``bop25_mAP =
  mAP_mssd``, ``bop25_mAP_mm = mAP_mssd_mm``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bopsurg import metrics
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import PoseEstimates, average_time_per_image
from bopsurg.bop.targets import ImageTarget
from bopsurg.errors import DatasetError
from bopsurg.evaluation import bop19, device
from bopsurg.evaluation.columns import Columns, group_labels, join_pairs, match_rows
from bopsurg.evaluation.matching import greedy_match
from bopsurg.evaluation.tables import GtTable, load_gt_table, rank_in_groups

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Thresholds exactly as the reference builds them (MSSD relative to the diameter, MSSD in
#: mm, MSPD in px at 640 px image width).
THRESHOLDS: dict[str, tuple[float, ...]] = {
    "mssd": bop19.MSSD_THRESHOLDS,
    "mssd_mm": tuple(float(x) for x in range(2, 21, 2)),
    "mspd": bop19.MSPD_THRESHOLDS,
}
#: GT instances less visible than this are not targets; estimates matched to them are ignored.
MIN_VISIB = 0.1
#: Estimates kept per image (the reference's ``max_num_estimates_per_image``).
MAX_ESTIMATES_PER_IMAGE = 100
#: Recall points of COCO's interpolated AP.
RECALL_POINTS: F64 = np.linspace(0.0, 1.0, 101, endpoint=True)


def interpolated_ap(recalls: F64, precisions: F64) -> float:
    """COCO 101-point average precision (``score.calc_ap`` of the reference).

    At each recall point r, the precision is the largest precision among the curve points with
    recall ≥ r (0 if none); AP is the mean over the 101 points.

    Args:
        recalls: (N,) non-decreasing recalls along the score-sorted detections.
        precisions: (N,) precisions at the same points.
    """
    rec = np.asarray(recalls, dtype=np.float64)
    pre = np.asarray(precisions, dtype=np.float64)
    if rec.size == 0:
        return 0.0
    best_after = np.maximum.accumulate(pre[::-1])[::-1]
    first = np.searchsorted(rec, RECALL_POINTS, side="left")
    interp = np.where(first < rec.size, best_after[np.minimum(first, rec.size - 1)], 0.0)
    return float(np.mean(interp))


@dataclass
class DetectionCurve:
    """Per-object APs of one error type.

    Attributes:
        error_type: ``"mssd"``, ``"mssd_mm"`` or ``"mspd"``.
        thresholds: The correctness thresholds θ.
        obj_ids: Objects with at least one target, ascending.
        ap: (O, T) AP per object and threshold.
        targets_count: (O,) targets (GT instances with ``visib_fract ≥ 0.1``) per object.
        ranked: Per object and threshold (row-major, O x T), the ranked estimates the AP
            is computed from: (target-image index, TP flag) of each non-ignored estimate in
            ranking order; what :mod:`bopsurg.evaluation.bootstrap` resamples.
    """

    error_type: str
    thresholds: list[float]
    obj_ids: list[int]
    ap: F64
    targets_count: list[int]
    ranked: list[tuple[I64, NDArray[np.bool_]]]

    @property
    def mean_ap(self) -> float:
        """Mean over objects of the mean AP over thresholds (NaN without targets)."""
        if not self.obj_ids:
            return float("nan")
        return float(np.mean([np.mean(row) for row in self.ap]))


@dataclass
class DetectionInputs:
    """Evaluated estimates and their candidate GT pairs, shared by all error types.

    Attributes:
        order: (E,) estimate rows (into the results) in the reference's ranking order
            (score descending; ties by target scene, target image, object order in the
            image's GT, file order).
        order_obj_id: (E,) object id of each estimate of ``order``.
        pair_rank, pair_est, pair_gt: (P,) candidate pairs (estimate, GT of its object in
            its image), ordered by estimate then gt_id; ``pair_rank`` is the estimate's score
            rank within its (image, object).
        gt: The GT table of the target images.
        is_target: (G,) GT instances that count (``visib_fract ≥ 0.1``).
        kept: The estimates after the per-image cap (for the time average).
        images: (I, 2) ``(scene_id, im_id)`` of the target images, in target order.
        order_im_pos: (E,) target-image index (into ``images``) of each estimate of ``order``.
        gt_im_pos: (G,) target-image index of each GT instance (-1 outside the targets).
    """

    order: I64
    order_obj_id: I64
    pair_rank: I64
    pair_est: I64
    pair_gt: I64
    gt: GtTable
    is_target: NDArray[np.bool_]
    kept: PoseEstimates
    images: I64
    order_im_pos: I64
    gt_im_pos: I64


def _target_images(dataset: BopDataset, gt: GtTable, targets: Sequence[ImageTarget]) -> Columns:
    """Target images (``scene_id``, ``im_id``, once each, in target order) with their
    position keys ``scene_pos`` (scene by first appearance) and ``im_pos`` (row)."""
    # The reference organises targets as {scene: {image: ...}} in insertion order.
    images = list(dict.fromkeys((int(t.scene_id), int(t.im_id)) for t in targets))
    scene_pos = {s: k for k, s in enumerate(dict.fromkeys(s for s, _ in images))}
    have = set(zip(gt.scene_id.tolist(), gt.im_id.tolist(), strict=True)) | set(gt.images)
    missing = [(s, i) for s, i in images if (s, i) not in have]
    if missing:
        s, i = missing[0]
        raise DatasetError(
            f"target image {i} of scene {s} is not in the split ({len(missing)} such targets)",
            path=dataset.root,
        )
    return {
        "scene_id": np.array([s for s, _ in images], dtype=np.int64),
        "im_id": np.array([i for _, i in images], dtype=np.int64),
        "scene_pos": np.array([scene_pos[s] for s, _ in images], dtype=np.int64),
        "im_pos": np.arange(len(images), dtype=np.int64),
    }


def prepare(
    dataset: BopDataset,
    estimates: PoseEstimates,
    targets: Sequence[ImageTarget],
    *,
    max_per_image: int = MAX_ESTIMATES_PER_IMAGE,
    gt: GtTable | None = None,
) -> DetectionInputs:
    """Cap the estimates per image, select the evaluated ones and their candidate pairs."""
    # 1. Per image, the max_per_image best (score descending, ties in file order).
    img_rank, _ = rank_in_groups(group_labels(estimates.scene_id, estimates.im_id), estimates.score)
    kept_rows = np.flatnonzero(img_rank < max_per_image)
    if gt is None:
        gt = load_gt_table(dataset, sorted({t.scene_id for t in targets}))
    tdf = _target_images(dataset, gt, targets)
    t_keys = (tdf["scene_id"], tdf["im_id"])

    # 2. GT of the target images (by row); object order of each image = its first gt_id.
    t_of_gt = match_rows((gt.scene_id, gt.im_id), t_keys)
    in_targets = np.flatnonzero(t_of_gt >= 0)
    g_keys = (gt.scene_id[in_targets], gt.im_id[in_targets], gt.obj_id[in_targets])
    g_group = group_labels(*g_keys)
    first_gt = np.full(int(g_group.max(initial=-1)) + 1, np.iinfo(np.int64).max)
    np.minimum.at(first_gt, g_group, gt.gt_id[in_targets])

    # 3. Estimates of target images whose object is in the image's GT, by row.
    e = kept_rows
    t_of_e = match_rows((estimates.scene_id[e], estimates.im_id[e]), t_keys)
    e = e[t_of_e >= 0]
    t_of_e = t_of_e[t_of_e >= 0]
    e_keys = (estimates.scene_id[e], estimates.im_id[e], estimates.obj_id[e])
    o_of_e = match_rows(e_keys, tuple(np.unique(np.stack(g_keys, 1), axis=0).T))
    e, t_of_e, o_of_e = e[o_of_e >= 0], t_of_e[o_of_e >= 0], o_of_e[o_of_e >= 0]
    score = estimates.score[e]
    obj_pos = first_gt[o_of_e]
    im_pos, scene_pos = tdf["im_pos"][t_of_e], tdf["scene_pos"][t_of_e]
    e_keys = (estimates.scene_id[e], estimates.im_id[e], estimates.obj_id[e])
    rank, _ = rank_in_groups(group_labels(*e_keys), score)
    # Reference order: the errors files list scene, image (target order), object (GT
    # order), then estimates by score; a stable sort by score then gives the AP ranking.
    order = np.lexsort((rank, obj_pos, im_pos, scene_pos, -score))
    pe, pg = join_pairs(e_keys, g_keys, gt.gt_id[in_targets])
    is_target = np.zeros(len(gt), dtype=bool)
    is_target[in_targets] = gt.visib_fract[in_targets] >= MIN_VISIB
    gt_im_pos = np.full(len(gt), -1, dtype=np.int64)
    gt_im_pos[in_targets] = tdf["im_pos"][t_of_gt[in_targets]]
    return DetectionInputs(
        order=e[order],
        order_obj_id=estimates.obj_id[e][order],
        pair_rank=rank[pe],
        pair_est=e[pe],
        pair_gt=in_targets[pg],
        gt=gt,
        is_target=is_target,
        kept=estimates.subset(kept_rows),
        # column-major, as a DataFrame's columns: the samples file keeps its bytes
        images=np.asfortranarray(np.stack([tdf["scene_id"], tdf["im_id"]], axis=1)),
        order_im_pos=im_pos[order],
        gt_im_pos=gt_im_pos,
    )


def pair_errors(
    dataset: BopDataset,
    estimates: PoseEstimates,
    inputs: DetectionInputs,
    max_sym_disc_step: float = 0.01,
) -> dict[str, F64]:
    """Thresholdable errors of every candidate pair: ``mssd`` (/ diameter), ``mssd_mm`` (mm)
    and ``mspd`` (px at 640 px width), one batched metric call per object."""
    gt, e_idx, g_idx = inputs.gt, inputs.pair_est, inputs.pair_gt
    mssd = np.full(e_idx.shape[0], np.nan)
    mspd = np.full(e_idx.shape[0], np.nan)
    diameter = np.full(e_idx.shape[0], np.nan)
    obj = gt.obj_id[g_idx]
    for obj_id in np.unique(obj):
        sel = np.flatnonzero(obj == obj_id)
        info = dataset.models_info[int(obj_id)]
        pts = dataset.model(int(obj_id)).pts
        syms = metrics.symmetry_transforms(info, max_sym_disc_step)
        Re, te = estimates.R[e_idx[sel]], estimates.t[e_idx[sel]]
        Rg, tg = gt.R[g_idx[sel]], gt.t[g_idx[sel]]
        mssd[sel] = device.mssd(Re, te, Rg, tg, pts, syms)
        mspd[sel] = device.mspd(Re, te, Rg, tg, gt.K[g_idx[sel]], pts, syms)
        diameter[sel] = float(info["diameter"])
    te_dist = metrics.te(estimates.t[e_idx], gt.t[g_idx])
    mssd_mm = np.where(te_dist < diameter, mssd, np.inf)
    return {
        "mssd": bop19.normalise_mssd(mssd, te_dist, diameter),
        "mssd_mm": mssd_mm,
        "mspd": bop19.normalise_mspd(mspd, gt.im_width[g_idx]),
    }


def detection_flags(
    inputs: DetectionInputs, errors: F64, threshold: float
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Match at one threshold; (TP, ignored) flags of the estimates in ``inputs.order``."""
    n_est = int(inputs.order.max()) + 1 if inputs.order.size else 0
    matched_by = greedy_match(
        inputs.pair_rank,
        inputs.pair_est,
        inputs.pair_gt,
        errors,
        threshold,
        np.ones(len(inputs.gt), dtype=bool),
    )
    gt_of_est = np.full(n_est, -1, dtype=np.int64)
    hit = np.flatnonzero(matched_by >= 0)
    gt_of_est[inputs.pair_est[matched_by[hit]]] = hit
    g = gt_of_est[inputs.order]
    matched = g >= 0
    tp = matched & inputs.is_target[np.maximum(g, 0)]
    return tp, matched & ~tp


def detection_curve(
    inputs: DetectionInputs, errors: F64, error_type: str, obj_ids: Sequence[int]
) -> DetectionCurve:
    """AP per object and threshold of one error type."""
    thresholds = THRESHOLDS[error_type]
    target_obj = inputs.gt.obj_id[inputs.is_target]
    counts = {int(o): int(np.count_nonzero(target_obj == o)) for o in obj_ids}
    with_targets = [o for o in sorted(obj_ids) if counts[o] > 0]
    ap = np.zeros((len(with_targets), len(thresholds)))
    ranked: list[tuple[I64, NDArray[np.bool_]]] = [None] * ap.size  # type: ignore[list-item]
    for j, th in enumerate(thresholds):
        tp, ignored = detection_flags(inputs, errors, th)
        for k, obj_id in enumerate(with_targets):
            sel = (inputs.order_obj_id == obj_id) & ~ignored
            ranked[k * len(thresholds) + j] = (inputs.order_im_pos[sel], tp[sel])
            tp_cum = np.cumsum(tp[sel])
            n = np.arange(1, tp_cum.size + 1)
            ap[k, j] = interpolated_ap(tp_cum / float(counts[obj_id]), tp_cum / n)
    return DetectionCurve(
        error_type, list(thresholds), with_targets, ap, [counts[o] for o in with_targets], ranked
    )


@dataclass
class DetectionEvaluation:
    """BOP24/BOP25 scores under the reference's key names, and the curves behind them."""

    scores: dict[str, float]
    curves: dict[str, DetectionCurve]
    inputs: DetectionInputs


def evaluate_bop24(
    dataset: BopDataset,
    estimates: PoseEstimates,
    targets: Sequence[ImageTarget] | None = None,
    *,
    max_per_image: int = MAX_ESTIMATES_PER_IMAGE,
    max_sym_disc_step: float = 0.01,
    gt: GtTable | None = None,
) -> DetectionEvaluation:
    """6D-detection scores of pose estimates, as ``scripts/eval_bop24_pose.py``.

    Args:
        dataset: The dataset split holding the GT.
        estimates: Results checked against the dataset.
        targets: Images to evaluate; default: the dataset's ``test_targets_bop24.json``, or
            every image with GT when the file is absent.
        max_per_image: Estimates kept per image (reference: 100; 200 for xyzibd).
        max_sym_disc_step: Discretisation of continuous symmetries (BOP: 0.01).
        gt: The split's GT table, if already loaded.

    Returns:
        Scores ``bop24_mAP_mssd``, ``bop24_mAP_mssd_mm``, ``bop24_mAP_mspd``, ``bop24_mAP``,
        ``bop25_mAP``, ``bop25_mAP_mm``, ``bop24_average_time_per_image`` and per-object APs.
    """
    if targets is None:
        targets = dataset.image_targets()
    inputs = prepare(dataset, estimates, targets, max_per_image=max_per_image, gt=gt)
    errors = pair_errors(dataset, estimates, inputs, max_sym_disc_step)
    obj_ids = dataset.obj_ids
    curves = {name: detection_curve(inputs, errors[name], name, obj_ids) for name in THRESHOLDS}
    scores = {k: float(v) for k, v in score_keys({n: c.mean_ap for n, c in curves.items()}).items()}
    scores["bop24_average_time_per_image"] = average_time_per_image(inputs.kept)
    return DetectionEvaluation(scores, curves, inputs)


def score_keys(mean_ap: dict[str, Any]) -> dict[str, Any]:
    """The reference's keys from the mAP of each error type (floats, or arrays of bootstrap
    replicates)."""
    return {
        "bop24_mAP_mssd": mean_ap["mssd"],
        "bop24_mAP_mssd_mm": mean_ap["mssd_mm"],
        "bop24_mAP_mspd": mean_ap["mspd"],
        "bop24_mAP": (mean_ap["mssd"] + mean_ap["mspd"]) / 2,
        "bop25_mAP": mean_ap["mssd"],
        "bop25_mAP_mm": mean_ap["mssd_mm"],
    }
