"""``scene_gt_coco.json``: BOP's 2D annotations (boxes, RLE masks) in the COCO layout.

One file per scene, as ``scripts/calc_gt_coco.py`` of the reference toolkit writes it with
``--use_all_gt`` (every image, not only target images):

- ``images``: ``{"id": im_id, "file_name": rgb path relative to the scene, "width",
  "height"}``;
- ``annotations``: per GT instance whose visible mask has at least one pixel (and whose full
  mask too): ``{"id"`` (1, 2, … per scene), ``"image_id", "category_id": obj_id,
  "iscrowd": 0, "area"`` (visible px), ``"bbox"`` (amodal, ``[x, y, w, h]`` of the full mask,
  whole pixels: ``w = x_max − x_min + 1``), ``"segmentation"`` (the visible mask as
  uncompressed COCO RLE: column-major run lengths starting with a background run),
  ``"width", "height", "ignore"`` (``visib_fract < 0.1``)``}``;
- ``categories``: one per object id of the dataset.

The modal box (of the visible mask) follows from the segmentation
(:func:`rle_bbox`), so the reference's separate ``scene_gt_coco_modal.json`` is not needed.
Only numpy is used; evaluation goes through pycocotools (:mod:`bopsurg.evaluation.coco_eval`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from tqdm import tqdm

from bopsurg.bop._validate import Issues, get_dict, get_int, get_list
from bopsurg.bop.dataset import BopDataset, BopScene
from bopsurg.bop.images import load_mask
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.bop.targets import (
    TARGETS_BOP24_FILENAME,
    enumerate_image_targets,
    save_image_targets,
)
from bopsurg.errors import DatasetError

logger = logging.getLogger(__name__)

SCENE_GT_COCO = "scene_gt_coco.json"
#: Instances less visible than this are flagged ``ignore`` (as the reference does).
IGNORE_BELOW_VISIB = 0.1


def mask_to_rle(mask: ArrayLike) -> dict[str, Any]:
    """Uncompressed COCO RLE of a binary mask (H, W): ``{"counts": [...], "size": [H, W]}``.

    Runs are counted in column-major order and alternate background/foreground, starting
    with background (a leading 0 when the first pixel is set).
    """
    m = np.asarray(mask, dtype=bool)
    flat = m.ravel(order="F")
    if flat.size == 0:
        return {"counts": [], "size": list(m.shape)}
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.r_[0, change, flat.size]
    counts = np.diff(bounds).tolist()
    if flat[0]:
        counts = [0, *counts]
    return {"counts": [int(c) for c in counts], "size": [int(m.shape[0]), int(m.shape[1])]}


def rle_to_mask(rle: dict[str, Any]) -> NDArray[np.bool_]:
    """The binary mask (H, W) of an uncompressed RLE."""
    h, w = (int(v) for v in rle["size"])
    counts = np.asarray(rle["counts"], dtype=np.int64)
    values = np.arange(counts.size) % 2 == 1
    flat = np.repeat(values, counts)
    if flat.size != h * w:
        raise ValueError(f"RLE counts sum to {flat.size}, expected {h} x {w} = {h * w}")
    return flat.reshape((w, h)).T


def mask_bbox(mask: NDArray[np.bool_]) -> list[int]:
    """``[x, y, w, h]`` of the set pixels, whole pixels (``w = x_max − x_min + 1``)."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return [int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)]


def rle_bbox(rle: dict[str, Any]) -> list[int]:
    """Modal box ``[x, y, w, h]`` of an uncompressed RLE (whole pixels)."""
    return mask_bbox(rle_to_mask(rle))


def scene_gt_coco(
    scene: BopScene, obj_ids: Sequence[int], image_size: tuple[int, int], dataset_name: str
) -> dict[str, Any]:
    """The ``scene_gt_coco.json`` content of one scene, from its masks and gt_info.

    Args:
        scene: The scene (needs ``mask/``, ``mask_visib/`` and ``scene_gt_info.json``).
        obj_ids: Object ids of the dataset (the categories).
        image_size: (width, height) px.
        dataset_name: The categories' ``supercategory``.

    Raises:
        DatasetError: A mask or the gt_info is missing or unreadable.
    """
    infos = scene.gt_info
    if infos is None:
        raise DatasetError(
            "missing (run bopsurg annotate)", path=scene.scene_dir / "scene_gt_info.json"
        )
    width, height = image_size
    images, annotations = [], []
    ann_id = 1
    for im_id, gts in sorted(scene.gt.items()):
        rel = scene.rgb_path(im_id).relative_to(scene.scene_dir).as_posix()
        images.append({"id": int(im_id), "file_name": rel, "width": width, "height": height})
        for gt_id, gt in enumerate(gts):
            visib = load_mask(scene.mask_visib_path(im_id, gt_id))
            area = int(np.count_nonzero(visib))
            if area < 1:
                continue
            full = load_mask(scene.mask_path(im_id, gt_id))
            if not full.any():
                continue
            annotations.append(
                {
                    "id": ann_id,
                    "image_id": int(im_id),
                    "category_id": int(gt.obj_id),
                    "iscrowd": 0,
                    "area": area,
                    "bbox": mask_bbox(full),
                    "segmentation": mask_to_rle(visib),
                    "width": int(visib.shape[1]),
                    "height": int(visib.shape[0]),
                    "ignore": bool(infos[im_id][gt_id].visib_fract < IGNORE_BELOW_VISIB),
                }
            )
            ann_id += 1
    return {
        "info": {"description": f"{dataset_name} 2D annotations", "version": "1.0"},
        "licenses": [],
        "categories": [
            {"id": int(o), "name": str(o), "supercategory": dataset_name} for o in obj_ids
        ],
        "images": images,
        "annotations": annotations,
    }


def write_detection_annotations(
    dataset: BopDataset,
    *,
    keep_targets: bool = False,
    write_targets: bool = True,
    progress: bool = False,
) -> int:
    """Write the files of the detection tasks for a split: ``scene_gt_coco.json`` in every
    scene that has masks, and ``test_targets_bop24.json`` (every image with GT) at the root
    (an existing one is kept with ``keep_targets``; none is written without ``write_targets``, as
    for a training split: the root's targets file belongs to the test split).

    Returns:
        The number of scenes given a ``scene_gt_coco.json``.
    """
    written = 0
    name = "bopsurg"  # not the folder name: the same data give the same bytes anywhere
    for scene in tqdm(dataset.iter_scenes(), desc="2D annotations", disable=not progress):
        if not (scene.scene_dir / "mask_visib").is_dir() or scene.gt_info is None:
            logger.info("%s: no masks, no %s", scene.scene_dir, SCENE_GT_COCO)
            continue
        content = scene_gt_coco(scene, dataset.obj_ids, dataset.image_size(scene.scene_id), name)
        save_json(scene.scene_dir / SCENE_GT_COCO, content)
        written += 1
    path = dataset.root / TARGETS_BOP24_FILENAME
    if write_targets and not (keep_targets and path.exists()):
        targets = enumerate_image_targets({s.scene_id: s.gt for s in dataset.iter_scenes()})
        save_image_targets(path, targets)
    return written


def parse_scene_gt_coco(content: Any, issues: Issues) -> dict[str, Any]:
    """Validate decoded ``scene_gt_coco.json`` content (schema, RLE sizes); returns it."""
    d = get_dict(content, None, issues, "a COCO annotation object") or {}
    for key in ("images", "annotations", "categories"):
        if key not in d:
            issues("missing", key)
    images = {}
    for i, im in enumerate(get_list(d.get("images", []), "images", issues, "a list") or []):
        e = get_dict(im, f"images/{i}", issues, "an image {id, width, height}")
        if e is None:
            continue
        vals = [
            get_int(e.get(k), f"images/{i}/{k}", issues, minimum=0)
            for k in ("id", "width", "height")
        ]
        if None not in vals:
            images[vals[0]] = (vals[1], vals[2])
    anns = get_list(d.get("annotations", []), "annotations", issues, "a list") or []
    for i, ann in enumerate(anns):
        a = get_dict(ann, f"annotations/{i}", issues, "an annotation")
        if a is None:
            continue
        for k in ("id", "image_id", "category_id", "area", "bbox", "segmentation"):
            if k not in a:
                issues("missing", f"annotations/{i}/{k}")
        im_id = a.get("image_id")
        if isinstance(im_id, int) and images and im_id not in images:
            issues(f"image {im_id} is not in images", f"annotations/{i}/image_id")
        seg = a.get("segmentation")
        if isinstance(seg, dict) and isinstance(seg.get("counts"), list):
            size = seg.get("size")
            total = sum(int(c) for c in seg["counts"] if isinstance(c, int))
            if not (isinstance(size, list) and len(size) == 2 and total == size[0] * size[1]):
                issues(
                    f"RLE counts sum to {total}, not size {size}", f"annotations/{i}/segmentation"
                )
    return d


def load_scene_gt_coco(path: str | Path) -> dict[str, Any]:
    """Load and validate a ``scene_gt_coco.json``.

    Raises:
        DatasetError: Missing, malformed or inconsistent file (names the field).
    """
    return parse_scene_gt_coco(load_json(path), Issues(path))
