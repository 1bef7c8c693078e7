"""Greedy matching of estimates to GT instances, vectorised over all images at once.

Rule (``bop_toolkit_lib.pose_matching.match_poses``): within each image and object, the
estimates are visited in order of decreasing score (ties in file order); each takes, among
the GT instances that are valid and not yet matched, the one with the smallest error, and only
if that error is strictly below the threshold (ties between GTs go to the lower gt_id, as the
reference's strict ``<`` update keeps the first). Every GT is matched at most once. Matching
is redone independently for every threshold.

Instead of a Python loop per image, round ``r`` lets the ``r``-th best estimate of every group
choose at once; groups never share GT instances, so the rounds reproduce the sequential rule.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

I64 = NDArray[np.int64]


def greedy_match(
    est_rank: ArrayLike,
    est_index: ArrayLike,
    gt_index: ArrayLike,
    errors: ArrayLike,
    threshold: float,
    valid_gt: ArrayLike,
) -> I64:
    """Match estimates to GTs for one threshold.

    The inputs describe P candidate pairs (an estimate and a GT of the same object in the same
    image). Pairs of one estimate must be ordered by gt_id (the tie-break).

    Args:
        est_rank: (P,) rank of the pair's estimate within its image/object group (0 = best).
        est_index: (P,) global index of the pair's estimate.
        gt_index: (P,) global index of the pair's GT, in ``range(len(valid_gt))``.
        errors: (P,) error of the pair (NaN never matches).
        threshold: Correctness threshold (strict: ``error < threshold``).
        valid_gt: (G,) bool, GT instances that may be matched.

    Returns:
        (G,) int64: for each GT the pair index that matched it, or -1.
    """
    rank = np.asarray(est_rank, dtype=np.int64)
    est = np.asarray(est_index, dtype=np.int64)
    gt = np.asarray(gt_index, dtype=np.int64)
    err = np.asarray(errors, dtype=np.float64)
    valid = np.asarray(valid_gt, dtype=bool)
    matched_by = np.full(valid.shape[0], -1, dtype=np.int64)
    ok = valid[gt] & (err < threshold)  # NaN compares False
    if not ok.any():
        return matched_by
    cand = np.flatnonzero(ok)
    max_rank = int(rank[cand].max())
    pair_pos = np.arange(err.shape[0])
    for r in range(max_rank + 1):
        c = cand[rank[cand] == r]
        if c.size == 0:
            continue
        c = c[matched_by[gt[c]] < 0]
        if c.size == 0:
            continue
        # Per estimate: smallest error, then lowest pair position (= lowest gt_id).
        order = np.lexsort((pair_pos[c], err[c], est[c]))
        c = c[order]
        first = np.r_[True, est[c][1:] != est[c][:-1]]
        chosen = c[first]
        matched_by[gt[chosen]] = chosen
    return matched_by


def valid_gts_localization(
    group_of_gt: ArrayLike, visib_fract: ArrayLike, inst_count: ArrayLike
) -> NDArray[np.bool_]:
    """Valid GT instances for BOP19 localization with ``visib_gt_min = -1``.

    Per image, GT instances are sorted by visib_fract descending (stable, gt_id order on ties);
    for each target object the first ``inst_count`` instances are valid, all others invalid.

    Args:
        group_of_gt: (G,) id of the (image, object) group of each GT, in gt_id order per image.
        visib_fract: (G,) visible fractions.
        inst_count: (G,) inst_count of the GT's (image, object) target; 0 if not a target.

    Returns:
        (G,) bool.
    """
    grp = np.asarray(group_of_gt, dtype=np.int64)
    vf = np.asarray(visib_fract, dtype=np.float64)
    cnt = np.asarray(inst_count, dtype=np.int64)
    n = grp.shape[0]
    if n == 0:
        return np.zeros(0, dtype=bool)
    order = np.lexsort((np.arange(n), -vf, grp))
    sorted_grp = grp[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_grp)) + 1]
    counts = np.diff(np.r_[starts, n])
    pos = np.empty(n, dtype=np.int64)
    pos[order] = np.arange(n) - np.repeat(starts, counts)
    return pos < cnt
