"""What BOP19 scores: the valid GT instances and the candidate pairs of the kept estimates.

The reference's rules (``eval_calc_errors.py``, ``eval_calc_scores.py``, ``visib_gt_min = -1``,
``n_top = -1``): only (scene, image, object) triples listed as targets are evaluated (the last
entry of a triple wins); per triple the ``inst_count`` best-scored estimates are kept (stable
score order) and the ``inst_count`` most visible GT instances are valid. Plain numpy, so that
``bopsurg eval`` can start VSD on these pairs before it loads the rest of the evaluation.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.results import PoseEstimates
from bopsurg.bop.targets import Target
from bopsurg.evaluation.matching import valid_gts_localization
from bopsurg.evaluation.tables import GtTable, rank_in_groups

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class PairTable:
    """Candidate (estimate, GT) pairs of the kept estimates, ordered by estimate then gt_id.

    Attributes:
        est_rank: (P,) score rank of the estimate within its (scene, image, object) target.
        est_index: (P,) row of the estimate in the results.
        gt_index: (P,) row of the GT in the :class:`~bopsurg.evaluation.tables.GtTable`.
    """

    est_rank: I64
    est_index: I64
    gt_index: I64


@dataclass(frozen=True)
class KeptPairs:
    """What BOP19 scores.

    Attributes:
        valid: (G,) valid GT instances (:func:`valid_gts`).
        pairs: The candidate pairs of the kept estimates (:func:`kept_pairs`).
        diameter: (P,) object diameter of each pair, mm.
    """

    valid: NDArray[np.bool_]
    pairs: PairTable
    diameter: F64


@dataclass(frozen=True)
class TargetTable:
    """The targets, one row per (scene, image, object); the last entry of a triple wins.

    Attributes:
        keys: (T, 3) scene_id, im_id, obj_id.
        inst_count: (T,) instances of the object in the image.
    """

    keys: I64
    inst_count: I64

    @classmethod
    def of(cls, targets: Sequence[Target]) -> TargetTable:
        """The table of a targets list."""
        last = {(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in targets}
        keys = np.array(list(last), dtype=np.int64).reshape(-1, 3)
        return cls(keys, np.fromiter(last.values(), dtype=np.int64, count=len(last)))


def _triple_codes(*keys: I64) -> list[I64]:
    """One int64 code per (scene, image, object) row of each (n, 3) table, equal across the
    tables exactly for equal triples."""
    joined = np.concatenate(keys)
    _, codes = np.unique(joined, axis=0, return_inverse=True)
    codes = codes.reshape(-1).astype(np.int64)
    ends = np.cumsum([k.shape[0] for k in keys])[:-1]
    return list(np.split(codes, ends))


def _gt_keys(gt: GtTable) -> I64:
    return np.stack([gt.scene_id, gt.im_id, gt.obj_id], axis=1).astype(np.int64).reshape(-1, 3)


def _est_keys(est: PoseEstimates) -> I64:
    return np.stack([est.scene_id, est.im_id, est.obj_id], axis=1).astype(np.int64).reshape(-1, 3)


def valid_gts(gt: GtTable, targets: TargetTable) -> NDArray[np.bool_]:
    """(G,) the valid GT instances: in target images, of target objects, the ``inst_count``
    most visible per (scene, image, object)."""
    g_code, t_code = _triple_codes(_gt_keys(gt), targets.keys)
    inst = np.zeros(len(g_code) + len(t_code), dtype=np.int64)
    inst[t_code] = targets.inst_count
    return valid_gts_localization(g_code, gt.visib_fract, inst[g_code])


def kept_pairs(est: PoseEstimates, gt: GtTable, targets: TargetTable) -> PairTable:
    """Candidate pairs of the kept estimates: targets only, the ``inst_count`` best-scored per
    (scene, image, object), each with every GT instance of its object in its image."""
    e_code, g_code, t_code = _triple_codes(_est_keys(est), _gt_keys(gt), targets.keys)
    inst = np.zeros(len(e_code) + len(g_code) + len(t_code), dtype=np.int64)
    is_target = np.zeros(inst.shape[0], dtype=bool)
    inst[t_code] = targets.inst_count
    is_target[t_code] = True
    e_idx = np.flatnonzero(is_target[e_code])
    rank, _ = rank_in_groups(e_code[e_idx], np.asarray(est.score, dtype=np.float64)[e_idx])
    keep = rank < inst[e_code[e_idx]]
    e_idx, rank = e_idx[keep], rank[keep]
    # each kept estimate's GT instances: a run of the GTs sorted by (triple, gt_id)
    g_order = np.lexsort((gt.gt_id, g_code))
    sorted_codes = g_code[g_order]
    lo = np.searchsorted(sorted_codes, e_code[e_idx], side="left")
    counts = np.searchsorted(sorted_codes, e_code[e_idx], side="right") - lo
    run_start = np.repeat(lo - (np.cumsum(counts) - counts), counts)
    at = np.arange(int(counts.sum()), dtype=np.int64) + run_start
    return PairTable(
        est_rank=np.repeat(rank, counts).astype(np.int64),
        est_index=np.repeat(e_idx, counts).astype(np.int64),
        gt_index=g_order[at].astype(np.int64),
    )


def kept_pairs_of_targets(
    est: PoseEstimates,
    gt: GtTable,
    targets: Sequence[Target],
    diameters: Callable[[I64], F64],
) -> KeptPairs:
    """:class:`KeptPairs` of the BOP19 targets.

    Args:
        est: The estimates.
        gt: The GT table.
        targets: The BOP19 targets.
        diameters: Object diameter (mm) of each object id of an array
            (:meth:`~bopsurg.evaluation.pair_errors.ModelCache.diameters`).
    """
    table = TargetTable.of(targets)
    pairs = kept_pairs(est, gt, table)
    return KeptPairs(valid_gts(gt, table), pairs, diameters(gt.obj_id[pairs.gt_index]))
