"""Training data from a BOP split, decoded once into memory.

Two views of the same split:

- :class:`DetectionSet` (detector): each image letterboxed to the network input
  (uint8), with its ``bbox_visib`` boxes.
- :class:`PoseSet` (pose head): per GT instance, a square *context crop* around its visible
  box (2.5 × the box's longer side, resampled to ``context`` px) holding RGB, the visible
  mask and the object-frame coordinates of every visible pixel. The coordinates are computed
  here from the rendered depth and the GT pose (``X = R^T (z K^-1 [u, v, 1] - t)``), so
  nothing beyond the BOP files is stored on disk, and the crop is large enough for every
  dynamic zoom-in (DZI) jitter to be cut from it later.

Whole scenes are held out for validation (every ``val_every``-th scene, deterministic), so
validation frames never share a trajectory replay with training frames.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from tqdm import tqdm

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import load_depth, load_mask, load_rgb
from bopsurg.errors import DatasetError
from bopsurg.models.detector.letterbox import letterbox

log = logging.getLogger(__name__)

#: Context crop side relative to the visible box's longer side: covers the largest DZI crop
#: (1.5 pad x 1.25 scale) with its largest centre shift (0.25 of the box).
CONTEXT_RATIO = 2.5


def split_scenes(
    dataset: BopDataset, val_every: int = 10, val: BopDataset | None = None
) -> tuple[list[int], list[int]]:
    """Train and validation scene ids of ``dataset``.

    With ``val`` (a separate split), all of ``dataset`` trains. Otherwise every
    ``val_every``-th scene (in id order, starting with the ``val_every``-th) is held out; with
    fewer than ``val_every`` scenes the last one is, and a single scene is used for both.
    """
    ids = dataset.scene_ids
    if not ids:
        raise DatasetError("the split has no scenes", path=dataset.split_dir)
    if val is not None or val_every <= 0:
        return ids, []
    held = ids[val_every - 1 :: val_every] or ids[-1:]
    train = [s for s in ids if s not in held] or ids
    return train, held


@dataclass(frozen=True)
class InstanceRecord:
    """One usable GT instance: where it is and what it looks like (full-image px, mm)."""

    scene_id: int
    im_id: int
    gt_id: int
    obj_id: int
    K: np.ndarray  # (3, 3)
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) mm
    bbox_visib: tuple[int, int, int, int]  # x, y, w, h (w = x_max - x_min, BOP)
    visib_fract: float


def list_instances(
    dataset: BopDataset,
    scene_ids: Sequence[int],
    obj_ids: Sequence[int] | None = None,
    min_visib: float = 0.1,
) -> dict[tuple[int, int], list[InstanceRecord]]:
    """GT instances per image with ``visib_fract >= min_visib`` (images without any kept too,
    as negatives, so the detector learns empty frames)."""
    out: dict[tuple[int, int], list[InstanceRecord]] = {}
    for sid in scene_ids:
        scene = dataset.scene(sid)
        infos = scene.gt_info
        if infos is None:
            raise DatasetError(
                "scene_gt_info.json is missing (run 'bopsurg annotate' first)",
                path=scene.scene_dir / "scene_gt_info.json",
            )
        for im_id in scene.im_ids:
            recs = []
            for gt_id, (gt, info) in enumerate(
                zip(scene.gt.get(im_id, []), infos.get(im_id, []), strict=False)
            ):
                if obj_ids is not None and gt.obj_id not in obj_ids:
                    continue
                if info.visib_fract < min_visib or info.bbox_visib[2] < 1:
                    continue
                recs.append(
                    InstanceRecord(
                        sid, im_id, gt_id, gt.obj_id, scene.camera[im_id].K, gt.R, gt.t,
                        info.bbox_visib, info.visib_fract,
                    )
                )  # fmt: skip
            out[(sid, im_id)] = recs
    return out


def _map(fn, items, desc: str, progress: bool, workers: int = 2) -> list:
    # Decoding is in OpenCV (releases the GIL): threads give a near-linear speed-up.
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(tqdm(pool.map(fn, items), total=len(items), desc=desc, disable=not progress))


# --------------------------------------------------------------------------- detector


def bbox_to_xyxy(bbox: Sequence[float], scale: float = 1.0) -> list[float]:
    """BOP ``(x, y, w, h)`` with ``w = x_max - x_min`` (pixel indices) to pixel-edge
    ``(x1, y1, x2, y2)`` (the box covers pixels x..x+w inclusive), times ``scale``."""
    x, y, w, h = bbox
    return [x * scale, y * scale, (x + w + 1) * scale, (y + h + 1) * scale]


@dataclass
class DetectionSet:
    """Letterboxed images and their boxes.

    Attributes:
        images: (N, 3, h, w) uint8 RGB at the network input size.
        targets: per image (n, 5) float32 ``[class, x1, y1, x2, y2]`` in input px.
        keys: (scene_id, im_id) per image.
        scales: (N,) input px per image px.
        classes: object id of each class index.
    """

    images: torch.Tensor
    targets: list[torch.Tensor]
    keys: list[tuple[int, int]]
    scales: np.ndarray
    classes: tuple[int, ...]

    def __len__(self) -> int:
        return len(self.keys)


def load_detection_set(
    dataset: BopDataset,
    scene_ids: Sequence[int],
    input_hw: tuple[int, int],
    classes: Sequence[int],
    *,
    min_visib: float = 0.1,
    progress: bool = True,
) -> DetectionSet:
    """Letterbox every image of ``scene_ids`` and collect its ``bbox_visib`` boxes."""
    per_image = list_instances(dataset, scene_ids, classes, min_visib)
    keys = list(per_image)
    cls_index = {o: k for k, o in enumerate(classes)}

    def load(key: tuple[int, int]) -> tuple[np.ndarray, float]:
        rgb = load_rgb(dataset.scene(key[0]).rgb_path(key[1]))
        return letterbox(rgb, input_hw)

    loaded = _map(load, keys, "load images", progress)
    images = torch.from_numpy(np.stack([im for im, _ in loaded])).permute(0, 3, 1, 2).contiguous()
    scales = np.array([s for _, s in loaded])
    targets = []
    for key, scale in zip(keys, scales, strict=True):
        rows = [[cls_index[r.obj_id], *bbox_to_xyxy(r.bbox_visib, scale)] for r in per_image[key]]
        targets.append(torch.tensor(rows, dtype=torch.float32).reshape(-1, 5))
    return DetectionSet(images, targets, keys, scales, tuple(classes))


# --------------------------------------------------------------------------- pose head


@dataclass
class PoseSet:
    """Context crops of GT instances, with everything the pose losses need.

    Attributes:
        rgb: (N, 3, C, C) uint8 context crops.
        mask: (N, C, C) bool visible masks.
        xyz: (N, 3, C, C) float16 object-frame coordinates (mm) of visible pixels, 0 elsewhere.
        ctx: (N, 3) float32 ``(a, cx, cy)``: context px = (image px - (cx, cy)) * a + C/2.
        K: (N, 3, 3) float32 camera matrices (image px).
        R: (N, 3, 3) float32 GT rotations; t: (N, 3) float32 GT translations (mm).
        bbox: (N, 4) float32 visible boxes ``(x, y, w, h)`` in image px (pixel edges:
            w = x_max - x_min + 1).
        image_hw: (N, 2) int64 full-image size.
        records: the source instances.
    """

    rgb: torch.Tensor
    mask: torch.Tensor
    xyz: torch.Tensor
    ctx: torch.Tensor
    K: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    bbox: torch.Tensor
    image_hw: torch.Tensor
    records: list[InstanceRecord]

    def __len__(self) -> int:
        return len(self.records)


def object_coordinates(
    depth_mm: np.ndarray, mask: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """(H, W, 3) float32 model-frame coordinates (mm) of the pixels in ``mask``, 0 elsewhere:
    ``X = R^T (z K^-1 [u, v, 1]^T - t)`` with z the rendered depth (mm) at pixel (u, v)."""
    v, u = np.nonzero(mask)
    z = depth_mm[v, u].astype(np.float64)
    rays = np.linalg.solve(K, np.stack([u, v, np.ones_like(u)]).astype(np.float64))
    pts_cam = rays * z
    pts = (R.T @ (pts_cam - t.reshape(3, 1))).T
    out = np.zeros((*mask.shape, 3), np.float32)
    out[v, u] = pts
    return out


def context_affine(bbox: Sequence[int], context: int) -> tuple[float, float, float]:
    """``(a, cx, cy)`` of the context crop around a BOP visible box (see :class:`PoseSet`)."""
    x, y, w, h = bbox
    cx, cy = x + w / 2.0, y + h / 2.0  # pixel-index centre of pixels x..x+w
    side = CONTEXT_RATIO * (max(w, h) + 1)
    return context / side, cx, cy


def _warp(img: np.ndarray, a: float, cx: float, cy: float, context: int, interp: int) -> np.ndarray:
    affine = np.array([[a, 0, context / 2 - a * cx], [0, a, context / 2 - a * cy]], np.float64)
    return cv2.warpAffine(img, affine, (context, context), flags=interp, borderValue=0)


def load_pose_set(
    dataset: BopDataset,
    scene_ids: Sequence[int],
    obj_id: int,
    *,
    context: int = 256,
    min_visib: float = 0.1,
    min_pixels: int = 16,
    progress: bool = True,
) -> PoseSet:
    """Context crops of every instance of ``obj_id`` with ``visib_fract >= min_visib`` and at
    least ``min_pixels`` visible pixels."""
    per_image = list_instances(dataset, scene_ids, [obj_id], min_visib)
    items = [(key, recs) for key, recs in per_image.items() if recs]

    def load(item):
        (sid, im_id), recs = item
        scene = dataset.scene(sid)
        rgb = load_rgb(scene.rgb_path(im_id))
        cam = scene.camera[im_id]
        if cam.depth_scale is None:
            raise DatasetError("depth_scale missing", path=scene.scene_dir / "scene_camera.json")
        depth = load_depth(scene.depth_path(im_id)) * cam.depth_scale
        out = []
        for r in recs:
            mask = load_mask(scene.mask_visib_path(im_id, r.gt_id)) & (depth > 0)
            if mask.sum() < min_pixels:
                continue
            xyz = object_coordinates(depth, mask, r.K, r.R, r.t)
            a, cx, cy = context_affine(r.bbox_visib, context)
            c_rgb = _warp(rgb, a, cx, cy, context, cv2.INTER_LINEAR)
            c_mask = _warp(mask.astype(np.uint8), a, cx, cy, context, cv2.INTER_NEAREST) > 0
            c_xyz = _warp(xyz, a, cx, cy, context, cv2.INTER_NEAREST)
            out.append((r, c_rgb, c_mask, c_xyz, (a, cx, cy), rgb.shape[:2]))
        return out

    loaded = [x for group in _map(load, items, "load instances", progress) for x in group]
    if not loaded:
        raise DatasetError(
            f"no instance of obj_id {obj_id} with visib_fract >= {min_visib} in scenes "
            f"{list(scene_ids)[:5]}...",
            path=dataset.split_dir,
        )
    recs = [x[0] for x in loaded]

    def f32(a) -> torch.Tensor:
        return torch.from_numpy(np.asarray(a, dtype=np.float32))

    return PoseSet(
        rgb=torch.from_numpy(np.stack([x[1] for x in loaded])).permute(0, 3, 1, 2).contiguous(),
        mask=torch.from_numpy(np.stack([x[2] for x in loaded])),
        xyz=torch.from_numpy(np.stack([x[3] for x in loaded])).permute(0, 3, 1, 2).half(),
        ctx=f32([x[4] for x in loaded]),
        K=f32([r.K for r in recs]),
        R=f32([r.R for r in recs]),
        t=f32([r.t for r in recs]),
        bbox=f32([[b[0], b[1], b[2] + 1, b[3] + 1] for b in (r.bbox_visib for r in recs)]),
        image_hw=torch.tensor([x[5] for x in loaded], dtype=torch.int64),
        records=recs,
    )
