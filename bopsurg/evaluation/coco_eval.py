"""BOP 2D detection and segmentation scores (COCO AP/AR) through pycocotools.

Restates ``scripts/eval_bop22_coco.py`` of the reference toolkit around pycocotools' own
``COCOeval`` (the library everyone reports COCO AP with), so the numbers are pycocotools':

- ground truth: each target scene's ``scene_gt_coco.json`` (:mod:`bopsurg.bop.coco`), only
  the target images; scenes merged in target order with the reference's image-id offsets
  (``max id so far + 1``), which fixes the image order and so how tied scores rank;
- results: the BOP COCO results JSON, ``[{"scene_id", "image_id", "category_id", "score",
  "bbox": [x, y, w, h], "segmentation": RLE, "time"}]``; results of other images are dropped;
- ``bbox`` is evaluated against amodal boxes (the reference's default) and against modal
  boxes (of the visible mask; what a detector trained on visible boxes predicts), ``segm``
  against the visible masks;
- keys ``bop22_coco_{bbox|bbox_modal|segm}_{AP, AP50, AP75, AP_small, AP_medium, AP_large,
  AR1, AR10, AR100, AR_small, AR_medium, AR_large}``; all -1 without results, as the
  reference.

pycocotools is an optional dependency (``pip install bopsurg[coco]``), imported on use.
"""

from __future__ import annotations

import contextlib
import copy
import gzip
import io
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bopsurg.bop._validate import Issues, get_dict, get_float, get_int, get_list
from bopsurg.bop.coco import SCENE_GT_COCO, load_scene_gt_coco, rle_bbox
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.jsonio import load_json
from bopsurg.bop.targets import ImageTarget
from bopsurg.errors import BopsurgError, DatasetError, ResultsError

if TYPE_CHECKING:  # (its bootstrap imports pandas: recognising a results file stays light)
    from bopsurg.evaluation.coco_bootstrap import CocoSamples

#: ``COCOeval.stats`` in order, under the reference's names.
STATS = (
    "AP", "AP50", "AP75", "AP_small", "AP_medium", "AP_large",
    "AR1", "AR10", "AR100", "AR_small", "AR_medium", "AR_large",
)  # fmt: skip
#: Evaluations of each task: (key prefix, pycocotools iouType, box kind).
EVALUATIONS: dict[str, tuple[tuple[str, str, str | None], ...]] = {
    "coco-bbox": (("bbox", "bbox", "amodal"), ("bbox_modal", "bbox", "modal")),
    "coco-segm": (("segm", "segm", None),),
}
_GZIP_MAGIC = b"\x1f\x8b"
_UTF8_BOM = b"\xef\xbb\xbf"  # spreadsheets and some editors write one; load_json drops it


def is_coco_results(path: str | Path) -> bool:
    """Whether a results file is a BOP COCO results JSON (by content: a JSON array, plain or
    gzip-compressed as ``.json.gz``, how BOP challenge submissions ship), not a pose CSV."""
    try:
        with open(path, "rb") as f:
            compressed = f.read(2) == _GZIP_MAGIC
            f.seek(0)
            with gzip.open(f) if compressed else contextlib.nullcontext(f) as raw:
                head = raw.read(256)
    except (OSError, EOFError, zlib.error):
        return False  # the results loader reports the unreadable file
    return head.removeprefix(_UTF8_BOM).lstrip().startswith(b"[")


def load_coco_results(path: str | Path) -> list[dict[str, Any]]:
    """Load and validate BOP COCO results.

    Raises:
        ResultsError: Not a list of ``{"scene_id", "image_id", "category_id", "score"}``
            entries with a ``bbox`` of 4 numbers (w, h ≥ 0) and/or a ``segmentation`` RLE;
            the field is ``"index/key"``.
    """
    issues = Issues(path, error=ResultsError)
    content = load_json(path)
    out = []
    for i, entry in enumerate(get_list(content, None, issues, "a list of results") or []):
        d = get_dict(entry, str(i), issues, "a result object")
        if d is None:
            continue
        for key in ("scene_id", "image_id", "category_id"):
            if key not in d:
                issues("missing", f"{i}/{key}")
            get_int(d[key], f"{i}/{key}", issues, minimum=0)
        if "score" not in d:
            issues("missing", f"{i}/score")
        get_float(d["score"], f"{i}/score", issues)
        if "bbox" not in d and "segmentation" not in d:
            issues("needs a bbox or a segmentation", str(i))
        box = d.get("bbox")
        if box is not None and (
            not isinstance(box, list)
            or len(box) != 4
            or not all(isinstance(v, (int, float)) for v in box)
            or box[2] < 0
            or box[3] < 0
        ):
            issues("expected [x, y, w, h] with w, h >= 0", f"{i}/bbox")
        seg = d.get("segmentation")
        if seg is not None and not (isinstance(seg, dict) and "counts" in seg and "size" in seg):
            issues("expected an RLE {counts, size}", f"{i}/segmentation")
        out.append(d)
    return out


def _coco() -> tuple[Any, Any, Any]:  # (COCO, COCOeval, mask module); pycocotools is untyped
    try:
        from pycocotools import mask as mask_utils
        from pycocotools.coco import COCO
        from pycocotools.cocoeval import COCOeval
    except ImportError:
        raise BopsurgError(
            "COCO evaluation needs pycocotools: pip install 'bopsurg[coco]'"
        ) from None
    return COCO, COCOeval, mask_utils


def merged_ground_truth(
    dataset: BopDataset, targets: Sequence[ImageTarget], box: str | None
) -> tuple[dict[str, Any], dict[tuple[int, int], int]]:
    """The reference's merged COCO ground truth of the target images, and the COCO image id
    of each ``(scene_id, im_id)``.

    Raises:
        DatasetError: A target scene has no ``scene_gt_coco.json``.
    """
    by_scene: dict[int, set[int]] = {}
    for t in targets:
        by_scene.setdefault(t.scene_id, set()).add(t.im_id)
    merged: dict[str, Any] | None = None
    ids: dict[tuple[int, int], int] = {}
    for scene_id, im_ids in by_scene.items():
        path = dataset.split_dir / f"{scene_id:06d}" / SCENE_GT_COCO
        if not path.exists():
            raise DatasetError(
                "missing: write it with 'bopsurg annotate' (or 'bopsurg generate')", path=path
            )
        ann = copy.deepcopy(load_scene_gt_coco(path))
        ann["images"] = [im for im in ann["images"] if im["id"] in im_ids]
        ann["annotations"] = [a for a in ann["annotations"] if a["image_id"] in im_ids]
        if box == "modal":
            for a in ann["annotations"]:
                a["bbox"] = rle_bbox(a["segmentation"])
        offset = 0
        if merged is None:
            merged = ann
        else:
            offset = max(im["id"] for im in merged["images"]) + 1
            ann_offset = max((a["id"] for a in merged["annotations"]), default=-1) + 1
            for cat in ann["categories"]:
                if cat not in merged["categories"]:
                    merged["categories"].append(cat)
            for im in ann["images"]:
                im["id"] += offset
            for a in ann["annotations"]:
                a["id"] += ann_offset
                a["image_id"] += offset
            merged["images"].extend(ann["images"])
            merged["annotations"].extend(ann["annotations"])
        ids.update({(scene_id, i): i + offset for i in im_ids})
    if merged is None:
        raise BopsurgError("no target images to evaluate")
    return merged, ids


def evaluate_coco(
    dataset: BopDataset,
    results: Sequence[dict[str, Any]],
    tasks: Sequence[str],
    targets: Sequence[ImageTarget] | None = None,
) -> dict[str, float]:
    """COCO scores of 2D results for the tasks ``coco-bbox`` and/or ``coco-segm``.

    As :func:`evaluate_coco_samples`, without the bootstrap samples.
    """
    return evaluate_coco_samples(dataset, results, tasks, targets)[0]


def evaluate_coco_samples(
    dataset: BopDataset,
    results: Sequence[dict[str, Any]],
    tasks: Sequence[str],
    targets: Sequence[ImageTarget] | None = None,
) -> tuple[dict[str, float], CocoSamples | None]:
    """COCO scores of 2D results for the tasks ``coco-bbox`` and/or ``coco-segm``, and what
    their bootstrap intervals are computed from.

    Args:
        dataset: The split (its scenes need ``scene_gt_coco.json``).
        results: Loaded BOP COCO results (:func:`load_coco_results`).
        tasks: Subset of :data:`EVALUATIONS`.
        targets: Images to evaluate (default: ``test_targets_bop24.json`` or every image with
            GT).

    Returns:
        ``bop22_coco_<kind>_<stat>`` keys and ``bop22_coco_average_time_per_image``; the
        per-image matches (:class:`~bopsurg.evaluation.coco_bootstrap.CocoSamples`) of the
        evaluations that had results (None if none had).
    """
    coco_cls, cocoeval_cls, mask_utils = _coco()
    if targets is None:
        targets = dataset.image_targets()
    scores: dict[str, float] = {}
    evaluated: list[tuple[str, Any]] = []
    image_keys: list[tuple[int, int]] = []
    for task in tasks:
        for prefix, iou_type, box in EVALUATIONS[task]:
            gt, ids = merged_ground_truth(dataset, targets, box)
            field = "bbox" if iou_type == "bbox" else "segmentation"
            dets = []
            for r in results:
                key = (int(r["scene_id"]), int(r["image_id"]))
                if r.get(field) and key in ids:
                    # Both fields kept: with a bbox, pycocotools takes a detection's area
                    # (its COCO size class) from the box even in segm, as the reference.
                    keep = ("category_id", "score", "bbox", "segmentation")
                    d = {k: v for k, v in r.items() if k in keep}
                    d["image_id"] = ids[key]
                    seg = d.get("segmentation")
                    if isinstance(seg, dict) and isinstance(seg.get("counts"), list):
                        h, w = seg["size"]
                        d["segmentation"] = mask_utils.frPyObjects(seg, h, w)
                    dets.append(d)
            values = [-1.0] * len(STATS)
            if dets:
                with contextlib.redirect_stdout(io.StringIO()):
                    coco_gt = coco_cls()
                    coco_gt.dataset = gt
                    coco_gt.createIndex()
                    coco_dt = coco_gt.loadRes(dets)
                    ev = cocoeval_cls(coco_gt, coco_dt, iou_type)
                    ev.params.imgIds = sorted(coco_gt.getImgIds())
                    ev.evaluate()
                    ev.accumulate()
                    ev.summarize()
                values = [float(v) for v in ev.stats]
                evaluated.append((prefix, ev))
                key_of = {v: k for k, v in ids.items()}
                image_keys = [key_of[i] for i in ev.params.imgIds]
            scores.update(
                {f"bop22_coco_{prefix}_{s}": v for s, v in zip(STATS, values, strict=True)}
            )
    scores["bop22_coco_average_time_per_image"] = _average_time(results)
    from bopsurg.evaluation.coco_bootstrap import CocoSamples

    samples = CocoSamples.from_cocoevals(evaluated, image_keys) if evaluated else None
    return scores, samples


def _average_time(results: Sequence[dict[str, Any]]) -> float:
    """Mean per-image time of all results (-1 if any is missing or negative)."""
    times: dict[tuple[int, int], float] = {}
    for r in results:
        t = r.get("time")
        if t is None or t < 0:
            return -1.0
        times.setdefault((int(r["scene_id"]), int(r["image_id"])), float(t))
    return float(np.mean(list(times.values()))) if times else -1.0
