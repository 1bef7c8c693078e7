"""Helpers shared by tests."""

from __future__ import annotations

import numpy as np

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import PoseEstimates


def estimates_from_gt(
    dataset: BopDataset, *, t_offset_mm: float = 0.0, time: float = 0.05
) -> PoseEstimates:
    """One estimate per GT instance at its GT pose (translation shifted by ``t_offset_mm``)."""
    rows = [
        (s, i, g) for s in dataset.scene_ids for i, gl in dataset.scene(s).gt.items() for g in gl
    ]
    n = len(rows)
    return PoseEstimates.from_arrays(
        scene_id=np.array([r[0] for r in rows], dtype=np.int64),
        im_id=np.array([r[1] for r in rows], dtype=np.int64),
        obj_id=np.array([r[2].obj_id for r in rows], dtype=np.int64),
        score=np.ones(n),
        R=np.stack([r[2].R for r in rows]),
        t=np.stack([r[2].t for r in rows]) + t_offset_mm,
        time=np.full(n, time),
    )
