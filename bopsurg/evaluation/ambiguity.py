"""Pose ambiguities of thin instruments, from the GT pose, the visible mask and the model.

The paper explains its worst needle errors by two ambiguities: both the tip and the tail are
hidden (nothing tells the needle's direction along its arc), and the needle seen edge-on (its
silhouette degenerates to a line). For every GT instance this module computes:

- ``tip_visible``, ``tail_visible``: whether the projection of the model's tip (tail) falls
  on the instance's visible mask (any pixel of the 3×3 neighbourhood of the rounded
  projection: the wire is only a few pixels wide); NaN when the mask is not available.
  The keypoints come from ``models_info.json`` (``"keypoints": {"tip": [x, y, z], "tail":
  [x, y, z]}`` in mm, written by bopsurg's generator); without them, the two vertices that
  define the model's diameter stand in (tail = the one with the lower vertex index).
- ``view_angle_deg``: the angle between the viewing ray to the model origin and the model's
  plane, 0 = edge-on, 90 = seen face-on. The plane normal is ``"plane_normal"`` of
  models_info, else the model's least-variance principal axis (z for the needle).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_mask_window
from bopsurg.evaluation.columns import Columns, as_columns, n_rows, take
from bopsurg.evaluation.summary import describe
from bopsurg.metrics.registry import table_metrics

if TYPE_CHECKING:
    import pandas as pd

F64 = NDArray[np.float64]

#: Columns :func:`instance_ambiguity` adds to each GT row (and errors.csv), in order.
AMBIGUITY_COLUMNS: tuple[str, ...] = ("tip_visible", "tail_visible", "view_angle_deg")

#: Bins of the split tables.
VIEW_ANGLE_BINS = (
    (0.0, 15.0, "edge-on <15°"),
    (15.0, 45.0, "oblique 15-45°"),
    (45.0, 90.01, "face-on >45°"),
)
VISIB_BINS = ((0.0, 0.5, "visib <0.5"), (0.5, 0.8, "visib 0.5-0.8"), (0.8, 1.01, "visib >=0.8"))


def model_keypoints(model_info: Mapping[str, Any], pts: F64) -> tuple[F64, F64]:
    """(tip, tail) in the model frame, mm (see the module docstring)."""
    kp = model_info.get("keypoints")
    if isinstance(kp, Mapping) and "tip" in kp and "tail" in kp:
        return np.asarray(kp["tip"], dtype=np.float64), np.asarray(kp["tail"], dtype=np.float64)
    from scipy.spatial import ConvexHull, QhullError

    try:
        cand = np.sort(ConvexHull(pts).vertices)
    except QhullError:
        cand = np.arange(pts.shape[0])
    c = pts[cand]
    diff = c[:, None, :] - c[None, :, :]
    d = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))  # pairwise distances, as pdist's
    i, j = np.unravel_index(np.argmax(d), d.shape)
    a, b = sorted((int(cand[i]), int(cand[j])))
    return pts[b].copy(), pts[a].copy()


def model_plane_normal(model_info: Mapping[str, Any], pts: F64) -> F64:
    """Unit normal of the model's plane (models_info ``plane_normal`` or least-variance axis)."""
    n = model_info.get("plane_normal")
    if n is None:
        centred = pts - pts.mean(axis=0)
        _, vecs = np.linalg.eigh(centred.T @ centred)
        n = vecs[:, 0]
        n = n if n[np.argmax(np.abs(n))] > 0 else -n  # deterministic sign
    n = np.asarray(n, dtype=np.float64)
    result: F64 = n / np.linalg.norm(n)
    return result


def view_angle_deg(R: F64, t: F64, normal: F64) -> F64:
    """Angle (deg) between the viewing rays to ``t`` (N, 3) and the planes with normal
    ``R @ normal``: 0 = edge-on, 90 = face-on."""
    n_cam = np.einsum("nij,j->ni", R, normal)
    ray = t / np.linalg.norm(t, axis=1, keepdims=True)
    s = np.abs(np.einsum("ni,ni->n", n_cam, ray))
    result: F64 = np.degrees(np.arcsin(np.clip(s, 0.0, 1.0)))
    return result


def _ends_on_mask(path: Path, uv: F64) -> tuple[bool, bool]:
    """Whether each of the (2, 2) projections ``uv`` (px) falls on the mask in ``path``: any
    pixel of the 3×3 neighbourhood of the rounded projection; only that window is decoded."""
    finite = np.all(np.isfinite(uv), axis=1)
    # Far off the image either way; clipping keeps the rounding in int64's range.
    px = np.rint(np.clip(np.where(finite[:, None], uv, 0.0), -8.0, 1e7)).astype(np.int64)
    lo = np.maximum(px[finite].min(axis=0, initial=0) - 1, 0)
    hi = px[finite].max(axis=0, initial=-2) + 2
    mask = load_mask_window(path, (int(lo[1]), int(hi[1])), (int(lo[0]), int(hi[0])))
    ends = []
    for (u, v), ok in zip(px.tolist(), finite.tolist(), strict=True):  # the two ends
        r0, r1 = max(v - 1 - int(lo[1]), 0), min(v + 2 - int(lo[1]), mask.shape[0])
        c0, c1 = max(u - 1 - int(lo[0]), 0), min(u + 2 - int(lo[0]), mask.shape[1])
        ends.append(ok and r0 < r1 and c0 < c1 and bool(mask[r0:r1, c0:c1].any()))
    return ends[0], ends[1]


def instance_ambiguity(
    dataset: BopDataset, gt_rows: Columns, gt_R: F64, gt_t: F64, gt_K: F64
) -> Columns:
    """``tip_visible``, ``tail_visible``, ``view_angle_deg`` for each GT row.

    Args:
        dataset: The dataset (models, models_info, mask_visib files).
        gt_rows: Rows with ``scene_id``, ``im_id``, ``gt_id``, ``obj_id``; masks are read only
            for the rows given.
        gt_R, gt_t, gt_K: (G, 3, 3), (G, 3) mm and (G, 3, 3) of the same rows.

    Returns:
        The three (G,) float columns (NaN where unknown).
    """
    n = n_rows(gt_rows)
    out: Columns = {c: np.full(n, np.nan) for c in AMBIGUITY_COLUMNS}
    obj = gt_rows["obj_id"]
    for obj_id in np.unique(obj):
        sel = np.flatnonzero(obj == obj_id)
        info = dataset.models_info[int(obj_id)]
        pts = dataset.model(int(obj_id)).pts
        tip, tail = model_keypoints(info, pts)
        normal = model_plane_normal(info, pts)
        out["view_angle_deg"][sel] = view_angle_deg(gt_R[sel], gt_t[sel], normal)
        cam_pts = np.einsum("nij,kj->nki", gt_R[sel], np.stack([tip, tail])) + gt_t[sel][:, None, :]
        uvw = np.einsum("nij,nkj->nki", gt_K[sel], cam_pts)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[..., :2] / uvw[..., 2:3]
        uv[uvw[..., 2] <= 0] = np.nan  # behind the camera: not visible
        rows = take(gt_rows, sel)
        scene_ids = rows["scene_id"]
        # Only scenes with masks cost a file read per instance; decide that once per scene.
        with_masks = {
            int(sid): (dataset.scene(int(sid)).scene_dir / "mask_visib").is_dir()
            for sid in np.unique(scene_ids)
        }
        masked = [sid for sid, has in with_masks.items() if has]
        im_ids, gt_ids = rows["im_id"], rows["gt_id"]
        ends = np.full((sel.size, 2), np.nan)
        for k in np.flatnonzero(np.isin(scene_ids, masked)):
            scene = dataset.scene(int(scene_ids[k]))
            path = scene.mask_visib_path(int(im_ids[k]), int(gt_ids[k]))
            if not path.exists():
                continue
            ends[k] = _ends_on_mask(path, uv[k])
        out["tip_visible"][sel] = ends[:, 0]
        out["tail_visible"][sel] = ends[:, 1]
    return out


def ambiguity_splits(rows: Columns | pd.DataFrame) -> dict[str, dict[str, dict[str, float]]]:
    """The paper's statistics of its table's metrics split by ends visible, view angle,
    visibility.

    Args:
        rows: GT rows of the table population (visib ≥ min_visib) with the columns of the
            table's metrics (:func:`~bopsurg.metrics.registry.table_metrics`: ``re``, ``te``,
            ``mssd``), ``tip_visible``, ``tail_visible``, ``view_angle_deg``, ``visib_fract``.

    Returns:
        ``{split: {group: {"n", "re_median", "te_median", "mssd_median", "mssd_mean"}}}``.
    """
    cols = as_columns(rows)
    r = take(cols, ~np.isnan(cols["re"]))
    tip, tail = r["tip_visible"], r["tail_visible"]
    groups: dict[str, dict[str, NDArray[np.bool_]]] = {
        "ends_visible": {},
        "view_angle": {},
        "visibility": {},
    }
    ends = np.where(np.isnan(tip), -1, tip) + np.where(np.isnan(tail), -1, tail)
    known = ~np.isnan(tip) & ~np.isnan(tail)
    for label, cond in (("both", ends == 2), ("one", ends == 1), ("none", ends == 0)):
        groups["ends_visible"][label] = known & cond
    angle, visib = r["view_angle_deg"], r["visib_fract"]
    for lo, hi, label in VIEW_ANGLE_BINS:
        groups["view_angle"][label] = (angle >= lo) & (angle < hi)
    for lo, hi, label in VISIB_BINS:
        groups["visibility"][label] = (visib >= lo) & (visib < hi)
    out: dict[str, dict[str, dict[str, float]]] = {}
    for split, parts in groups.items():
        out[split] = {}
        for label, mask in parts.items():
            g = take(r, mask)
            stats: dict[str, float] = {"n": int(mask.sum())}
            for metric in table_metrics():
                stats[f"{metric.name}_median"] = describe(g[metric.name])["median"]
            stats["mssd_mean"] = describe(g["mssd"])["mean"]
            out[split][label] = stats
    return out
