"""Registered metrics on (estimate, GT) pairs: the candidate pairs and their batched errors.

Both matchings of ``bopsurg eval`` (the per-instance one of the runner and BOP19's) pair
estimates with GT instances of the same object in the same image and evaluate metrics of
:data:`bopsurg.metrics.registry.METRICS` on them, one batched call per object.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import PoseEstimates
from bopsurg.evaluation import device
from bopsurg.evaluation.columns import join_pairs
from bopsurg.evaluation.tables import GtTable
from bopsurg.metrics.registry import Need, PairBatch, metric
from bopsurg.metrics.symmetry import Symmetries, symmetry_transforms

if TYPE_CHECKING:  # pandas on use (candidate_pairs): the model cache and the errors are numpy
    import pandas as pd

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class ModelCache:
    """Model points, symmetry sets and diameters per object, loaded once."""

    def __init__(self, dataset: BopDataset, max_sym_disc_step: float) -> None:
        self.dataset = dataset
        self.step = max_sym_disc_step
        self._syms: dict[int, Symmetries] = {}

    def pts(self, obj_id: int) -> F64:
        """(V, 3) model vertices, mm."""
        return self.dataset.model(obj_id).pts

    def syms(self, obj_id: int) -> Symmetries:
        """Symmetry transformations, discretised with ``max_sym_disc_step``."""
        if obj_id not in self._syms:
            self._syms[obj_id] = symmetry_transforms(self.dataset.models_info[obj_id], self.step)
        return self._syms[obj_id]

    def diameter(self, obj_id: int) -> float:
        """Object diameter, mm."""
        return float(self.dataset.models_info[obj_id]["diameter"])

    def diameters(self, obj_ids: I64) -> F64:
        """Diameter (mm) of each object id in ``obj_ids``, looked up once per distinct id."""
        ids, inverse = np.unique(obj_ids, return_inverse=True)
        return np.array([self.diameter(int(o)) for o in ids], dtype=np.float64)[inverse]


def candidate_pairs(est_df: pd.DataFrame, gt: GtTable) -> pd.DataFrame:
    """All (estimate, GT) pairs of the same object in the same image, by estimate then gt_id.

    Args:
        est_df: Estimates with columns ``e`` (row in the results), ``scene_id``, ``im_id``,
            ``obj_id`` and any others to carry along.
        gt: The GT table.
    """
    pairs = est_df.merge(gt.frame(), on=["scene_id", "im_id", "obj_id"], how="inner")
    return pairs.sort_values(["e", "gt_id"], kind="stable").reset_index(drop=True)


def candidate_pair_indices(est: PoseEstimates, gt: GtTable) -> tuple[I64, I64]:
    """:func:`candidate_pairs` as (P,) estimate rows and (P,) GT rows, in numpy: all pairs of
    the same object in the same image, by estimate then gt_id."""
    return join_pairs(
        (est.scene_id, est.im_id, est.obj_id), (gt.scene_id, gt.im_id, gt.obj_id), gt.gt_id
    )


def pair_errors(
    est: PoseEstimates,
    gt: GtTable,
    e_idx: I64,
    g_idx: I64,
    models: ModelCache,
    which: Sequence[str],
) -> dict[str, F64]:
    """Registered metrics ``which`` of pairs (estimate e_idx[i], GT g_idx[i]), batched per object
    (MSSD, MSPD and ADD on the device of :func:`bopsurg.evaluation.device.metric_device`).

    Returns:
        Per metric name a (P,) array in pair order (NaN only when P is 0).
    """
    chosen = [metric(name) for name in which]
    needs = frozenset().union(*(m.needs for m in chosen))
    out = {m.name: np.full(e_idx.shape[0], np.nan) for m in chosen}
    obj = gt.obj_id[g_idx]
    for obj_id in np.unique(obj):
        sel = np.flatnonzero(obj == obj_id)
        oid = int(obj_id)
        batch = PairBatch(
            R_est=est.R[e_idx[sel]],
            t_est=est.t[e_idx[sel]],
            R_gt=gt.R[g_idx[sel]],
            t_gt=gt.t[g_idx[sel]],
            pts=models.pts(oid) if Need.MODEL_POINTS in needs else None,
            syms=models.syms(oid) if Need.SYMMETRIES in needs else None,
            K=gt.K[g_idx[sel]] if Need.CAMERA in needs else None,
        )
        for m in chosen:
            out[m.name][sel] = (device.batched(m.name) or m.function)(batch)
    return out
