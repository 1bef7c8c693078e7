"""Flat, columnar views of a dataset's ground truth and of estimate–GT pairs.

Evaluation works on whole columns (numpy arrays) instead of nested dicts, so every metric is
computed in one batched call per object.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import PoseEstimates
from bopsurg.errors import DatasetError

if TYPE_CHECKING:  # pandas on use: the GT table and the ranks are plain numpy
    import pandas as pd

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GtTable:
    """All GT instances of the evaluated images, one row each (G rows).

    Attributes:
        scene_id, im_id, gt_id, obj_id: (G,) int64 identifiers (gt_id = index in scene_gt).
        R: (G, 3, 3) rotations; t: (G, 3) translations, mm.
        K: (G, 3, 3) camera matrix of the instance's image.
        visib_fract: (G,) visible fraction from scene_gt_info (NaN where absent).
        im_width: (G,) image width in px (MSPD normalisation).
        images: set of (scene_id, im_id) of every image in the split, with or without GT.
    """

    scene_id: I64
    im_id: I64
    gt_id: I64
    obj_id: I64
    R: F64
    t: F64
    K: F64
    visib_fract: F64
    im_width: I64
    images: frozenset[tuple[int, int]]

    def __len__(self) -> int:
        return int(self.scene_id.shape[0])

    def frame(self) -> pd.DataFrame:
        """Identifier columns as a DataFrame with a ``g`` column = row index."""
        import pandas as pd

        return pd.DataFrame(
            {
                "scene_id": self.scene_id,
                "im_id": self.im_id,
                "gt_id": self.gt_id,
                "obj_id": self.obj_id,
                "g": np.arange(len(self), dtype=np.int64),
            }
        )


def load_gt_table(
    dataset: BopDataset, scene_ids: Iterable[int] | None = None, *, need_gt_info: bool = True
) -> GtTable:
    """Gather the GT of the given scenes (all scenes by default) into a :class:`GtTable`.

    Raises:
        DatasetError: A scene lacks scene_gt_info.json while ``need_gt_info`` is set, or a GT
            image has no camera entry.
    """
    cols: dict[str, list[Any]] = {
        k: [] for k in ("scene", "im", "gt", "obj", "R", "t", "K", "vf", "w")
    }
    images: set[tuple[int, int]] = set()
    ids = dataset.scene_ids if scene_ids is None else sorted(set(scene_ids))
    for scene_id in ids:
        scene = dataset.scene(scene_id)
        gt_info = scene.gt_info
        if gt_info is None and need_gt_info:
            raise DatasetError(
                "scene_gt_info.json is missing (visibility is needed for evaluation)",
                path=scene.scene_dir / "scene_gt_info.json",
            )
        width = dataset.image_size(scene_id)[0]
        images.update((scene_id, im_id) for im_id in scene.camera)
        for im_id, gts in scene.gt.items():
            images.add((scene_id, im_id))
            if not gts:
                continue
            cam = scene.camera.get(im_id)
            if cam is None:
                raise DatasetError(
                    f"image {im_id} has GT but no camera entry",
                    path=scene.scene_dir / "scene_camera.json",
                    field=str(im_id),
                )
            infos = gt_info.get(im_id) if gt_info is not None else None
            for gt_id, gt in enumerate(gts):
                cols["scene"].append(scene_id)
                cols["im"].append(im_id)
                cols["gt"].append(gt_id)
                cols["obj"].append(gt.obj_id)
                cols["R"].append(gt.R)
                cols["t"].append(gt.t)
                cols["K"].append(cam.K)
                vf = (
                    infos[gt_id].visib_fract if infos is not None and gt_id < len(infos) else np.nan
                )
                cols["vf"].append(vf)
                cols["w"].append(width)
    n = len(cols["scene"])
    return GtTable(
        scene_id=np.asarray(cols["scene"], dtype=np.int64),
        im_id=np.asarray(cols["im"], dtype=np.int64),
        gt_id=np.asarray(cols["gt"], dtype=np.int64),
        obj_id=np.asarray(cols["obj"], dtype=np.int64),
        R=np.asarray(cols["R"], dtype=np.float64).reshape(n, 3, 3),
        t=np.asarray(cols["t"], dtype=np.float64).reshape(n, 3),
        K=np.asarray(cols["K"], dtype=np.float64).reshape(n, 3, 3),
        visib_fract=np.asarray(cols["vf"], dtype=np.float64),
        im_width=np.asarray(cols["w"], dtype=np.int64),
        images=frozenset(images),
    )


def estimates_frame(est: PoseEstimates) -> pd.DataFrame:
    """Identifier columns of the estimates with ``e`` = row index and ``score``."""
    import pandas as pd

    return pd.DataFrame(
        {
            "scene_id": est.scene_id,
            "im_id": est.im_id,
            "obj_id": est.obj_id,
            "score": est.score,
            "e": np.arange(len(est), dtype=np.int64),
        }
    )


def rank_within_groups(keys: pd.DataFrame, score: F64) -> tuple[I64, I64]:
    """Score rank and file-order index of each row within its group of equal ``keys``.

    The rank orders by score descending, ties in file order (Python's stable ``sorted(...,
    reverse=True)`` as the reference toolkit uses); the file-order index is the reference's
    ``est_id`` (position among the estimates of that image and object in the CSV).

    Returns:
        (rank, est_id), each (N,) int64.
    """
    group = keys.groupby(list(keys.columns), sort=False).ngroup().to_numpy()
    return rank_in_groups(group, score)


def rank_in_groups(group: I64, score: F64) -> tuple[I64, I64]:
    """:func:`rank_within_groups` with the groups given as labels: ``(N,)`` int64, equal for
    rows of the same group (only equality matters)."""
    n = group.shape[0]
    order_idx = np.arange(n)
    # lexsort: last key is primary -> group, then score descending, then file order.
    order = np.lexsort((order_idx, -score, group))
    rank = np.empty(n, dtype=np.int64)
    sorted_groups = group[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_groups)) + 1]
    counts = np.diff(np.r_[starts, n])
    rank[order] = np.arange(n) - np.repeat(starts, counts)
    file_order = np.lexsort((order_idx, group))
    est_id = np.empty(n, dtype=np.int64)
    est_id[file_order] = np.arange(n) - np.repeat(starts, counts)
    return rank, est_id
