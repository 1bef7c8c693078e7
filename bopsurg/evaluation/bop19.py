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

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from bopsurg.evaluation.matching import greedy_match

F64 = NDArray[np.float64]

#: Correctness thresholds exactly as the reference builds them (floats included).
MSSD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
MSPD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(5, 51, 5))
VSD_THRESHOLDS: tuple[float, ...] = MSSD_THRESHOLDS
VSD_TAUS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
VSD_DELTA_MM = 15.0


@dataclass(frozen=True)
class PairTable:
    """Candidate (estimate, GT) pairs of the kept estimates, ordered by estimate then gt_id.

    Attributes:
        est_rank: (P,) score rank of the estimate within its (scene, image, object) target.
        est_index: (P,) row of the estimate in the results.
        gt_index: (P,) row of the GT in the :class:`~bopsurg.evaluation.tables.GtTable`.
    """

    est_rank: NDArray[np.int64]
    est_index: NDArray[np.int64]
    gt_index: NDArray[np.int64]


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
) -> RecallCurve:
    """Recall at each threshold for normalised pair errors.

    Args:
        pairs: The candidate pairs.
        errors: (P,) normalised errors of the pairs, or (T, P) for VSD (one row per τ, the
            recall list is then τ-major, θ-minor like the reference's folders).
        valid_gt: (G,) valid GT instances.
        thresholds: Correctness thresholds θ.
        error_type: Name, e.g. ``"mssd"``.
    """
    errs = np.atleast_2d(np.asarray(errors, dtype=np.float64))
    targets = int(np.count_nonzero(valid_gt))
    recalls: list[float] = []
    tps: list[int] = []
    for row in errs:
        for th in thresholds:
            matched = greedy_match(
                pairs.est_rank, pairs.est_index, pairs.gt_index, row, th, valid_gt
            )
            tp = int(np.count_nonzero(matched[valid_gt] >= 0))
            tps.append(tp)
            recalls.append(tp / float(targets) if targets > 0 else 0.0)
    return RecallCurve(error_type, list(thresholds), recalls, tps, targets)


def normalise_mssd(mssd: F64, te: F64, diameter: F64) -> F64:
    """MSSD / diameter with the reference's +inf where ``‖t_est − t_gt‖ ≥ diameter``."""
    out = mssd / diameter
    return np.where(te < diameter, out, np.inf)


def normalise_mspd(mspd: F64, im_width: NDArray[np.int64]) -> F64:
    """MSPD scaled to a 640 px wide image, as the reference (``640 / W × e``)."""
    factor = 640.0 / im_width.astype(np.float64)
    return factor * mspd


def sphere_projections_overlap(t_est: F64, t_gt: F64, radius: F64) -> NDArray[np.bool_]:
    """The reference's approximate overlap test of the bounding-sphere projections (VSD).

    Args:
        t_est, t_gt: (P, 3) translations, mm.
        radius: (P,) sphere radius (diameter / 2), mm.
    """
    ze, zg = t_est[:, 2], t_gt[:, 2]
    nonzero = (ze != 0) & (zg != 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        pe = t_est[:, :2] / ze[:, None]
        pg = t_gt[:, :2] / zg[:, None]
        dist = np.linalg.norm(pe - pg, axis=1)
        thresh = radius * (1.0 / ze + 1.0 / zg)
    return nonzero & (dist < thresh)
