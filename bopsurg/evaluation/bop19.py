"""BOP19 6D-localization scores: recall per threshold and average recall (AR).

Reproduces ``scripts/eval_bop19_pose.py`` → ``eval_calc_errors.py`` → ``eval_calc_scores.py``
of the reference toolkit (``visib_gt_min = -1``, ``n_top = -1``, targets from
``test_targets_bop19.json``):

- only (scene, image, object) triples listed as targets are evaluated; per triple the
  ``inst_count`` best-scored estimates are kept (stable score order);
- per image, the ``inst_count`` most visible GT instances of each target object are valid;
- errors are normalised before thresholding: MSSD by the object diameter, MSPD by
  ``640 / image width``; MSSD is +inf where ``‖t_est − t_gt‖ ≥ diameter`` (the reference's
  sphere pre-check), VSD is 1 where the bounding-sphere projections do not overlap;
- greedy matching (:mod:`bopsurg.evaluation.matching`) with strict thresholds, redone per
  threshold; recall = matched valid GTs / valid GTs, micro-averaged over the dataset;
- AR_MSSD, AR_MSPD = mean of 10 recalls; AR_VSD = mean of 10 τ × 10 θ recalls;
  AR = (AR_VSD + AR_MSSD + AR_MSPD) / 3 when VSD is available.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.results import PoseEstimates
from bopsurg.bop.targets import Target
from bopsurg.evaluation.bop19_pairs import KeptPairs, PairTable, kept_pairs_of_targets
from bopsurg.evaluation.columns import Columns, match_rows, pick
from bopsurg.evaluation.matching import greedy_match
from bopsurg.evaluation.pair_errors import ModelCache, pair_errors
from bopsurg.evaluation.tables import GtTable
from bopsurg.evaluation.vsd_images import VSD_TAUS
from bopsurg.evaluation.vsd_pairs import PendingVsd, VsdInputs, start_vsd

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Correctness thresholds exactly as the reference builds them (floats included).
MSSD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
MSPD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(5, 51, 5))
VSD_THRESHOLDS: tuple[float, ...] = MSSD_THRESHOLDS
VSD_DELTA_MM = 15.0


@dataclass
class RecallCurve:
    """Recall at each threshold of one error type, and its mean (the AR)."""

    error_type: str
    thresholds: list[float]
    recalls: list[float]
    tp_counts: list[int]
    targets_count: int
    taus: list[float] | None = None
    extra: dict[str, object] = field(default_factory=dict)
    #: Per image with valid GTs, what the bootstrap intervals resample: (M, 2) scene_id,
    #: im_id; (M,) valid GTs; (T, M) matched valid GTs at each threshold (recall order).
    image_ids: NDArray[np.int64] | None = None
    image_targets: NDArray[np.int64] | None = None
    image_hits: NDArray[np.int64] | None = None

    @property
    def average_recall(self) -> float:
        """Mean of the recalls (0 when there are no thresholds)."""
        return float(np.mean(self.recalls)) if self.recalls else 0.0


def recall_curve(
    pairs: PairTable,
    errors: F64,
    valid_gt: NDArray[np.bool_],
    thresholds: tuple[float, ...],
    error_type: str,
    gt_images: NDArray[np.int64] | None = None,
) -> RecallCurve:
    """Recall at each threshold for normalised pair errors.

    Args:
        pairs: The candidate pairs.
        errors: (P,) normalised errors of the pairs, or (T, P) for VSD (one row per τ, the
            recall list is then τ-major, θ-minor like the reference's folders).
        valid_gt: (G,) valid GT instances.
        thresholds: Correctness thresholds θ.
        error_type: Name, e.g. ``"mssd"``.
        gt_images: (G, 2) scene_id, im_id of each GT: also count hits per image (for the
            bootstrap intervals of the AR).
    """
    errs = np.atleast_2d(np.asarray(errors, dtype=np.float64))
    targets = int(np.count_nonzero(valid_gt))
    recalls: list[float] = []
    tps: list[int] = []
    hit_rows: list[NDArray[np.bool_]] = []
    for row in errs:
        for th in thresholds:
            matched = greedy_match(
                pairs.est_rank, pairs.est_index, pairs.gt_index, row, th, valid_gt
            )
            tp = int(np.count_nonzero(matched[valid_gt] >= 0))
            tps.append(tp)
            recalls.append(tp / float(targets) if targets > 0 else 0.0)
            hit_rows.append(matched[valid_gt] >= 0)
    curve = RecallCurve(error_type, list(thresholds), recalls, tps, targets)
    if gt_images is not None:
        ids, inv = np.unique(gt_images[valid_gt], axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        curve.image_ids = ids.astype(np.int64).reshape(-1, 2)
        curve.image_targets = np.bincount(inv, minlength=len(ids)).astype(np.int64)
        curve.image_hits = np.array(
            [np.bincount(inv, weights=h, minlength=len(ids)) for h in hit_rows], dtype=np.int64
        ).reshape(len(hit_rows), len(ids))
    return curve


def merge_image_counts(merged: RecallCurve, parts: Sequence[RecallCurve]) -> None:
    """Give ``merged`` the per-image counts of ``parts`` (curves of disjoint scenes), in image
    order, so that the bootstrap draws the same replicates however the scenes were split."""
    if not parts or any(p.image_ids is None for p in parts):
        return
    ids = np.concatenate([p.image_ids for p in parts if p.image_ids is not None])
    order = np.lexsort((ids[:, 1], ids[:, 0]))
    merged.image_ids = ids[order]
    merged.image_targets = np.concatenate(
        [p.image_targets for p in parts if p.image_targets is not None]
    )[order]
    merged.image_hits = np.concatenate(
        [p.image_hits for p in parts if p.image_hits is not None], axis=1
    )[:, order]


def normalise_mssd(mssd: F64, te: F64, diameter: F64) -> F64:
    """MSSD / diameter with the reference's +inf where ``‖t_est − t_gt‖ ≥ diameter``."""
    out = mssd / diameter
    return np.where(te < diameter, out, np.inf)


def normalise_mspd(mspd: F64, im_width: NDArray[np.int64]) -> F64:
    """MSPD scaled to a 640 px wide image, as the reference (``640 / W × e``)."""
    factor = 640.0 / im_width.astype(np.float64)
    return factor * mspd


def recall_curves(
    est: PoseEstimates,
    gt: GtTable,
    targets: Sequence[Target],
    models: ModelCache,
    *,
    pair_mssd: Columns,
    vsd_inputs: VsdInputs | None = None,
    kept: KeptPairs | None = None,
    vsd: PendingVsd | None = None,
) -> dict[str, RecallCurve]:
    """BOP19 recall curves (MSSD, MSPD, and VSD with ``vsd_inputs``) under the reference's rules.

    Args:
        est: The estimates.
        gt: The GT table.
        targets: The BOP19 targets.
        models: Model points, symmetries and diameters.
        pair_mssd: MSSD (mm) of candidate pairs already computed (columns ``e``, ``g``,
            ``mssd``, or a DataFrame of them); every kept pair must be among them.
        vsd_inputs: Depth renderer and dataset for VSD; None: no VSD curve.
        kept: The targets' kept pairs, when already computed
            (:func:`~bopsurg.evaluation.bop19_pairs.kept_pairs_of_targets`).
        vsd: VSD of those pairs, already started
            (:func:`~bopsurg.evaluation.vsd_pairs.start_vsd`).
    """
    if kept is None:
        kept = kept_pairs_of_targets(est, gt, targets, models.diameters)
    pairs, valid, diam = kept.pairs, kept.valid, kept.diameter
    e_idx, g_idx = pairs.est_index, pairs.gt_index
    errs = pair_errors(est, gt, e_idx, g_idx, models, ("te", "mspd"))
    known = match_rows((e_idx, g_idx), (np.asarray(pair_mssd["e"]), np.asarray(pair_mssd["g"])))
    errs["mssd"] = pick(np.asarray(pair_mssd["mssd"], dtype=np.float64), known)
    ims = np.stack([gt.scene_id, gt.im_id], axis=1).astype(np.int64)
    mssd = normalise_mssd(errs["mssd"], errs["te"], diam)
    mspd = normalise_mspd(errs["mspd"], gt.im_width[g_idx])
    curves = {
        "mssd": recall_curve(pairs, mssd, valid, MSSD_THRESHOLDS, "mssd", ims),
        "mspd": recall_curve(pairs, mspd, valid, MSPD_THRESHOLDS, "mspd", ims),
    }
    if vsd_inputs is not None:
        if vsd is None:
            vsd = start_vsd(est, gt, kept, vsd_inputs)
        curve = recall_curve(pairs, vsd.result(), valid, VSD_THRESHOLDS, "vsd", ims)
        curve.taus = list(VSD_TAUS)
        curve.extra["delta_mm"] = vsd_inputs.delta
        curves["vsd"] = curve
    return curves
