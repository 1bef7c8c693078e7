"""2D detection results in the BOP format (the JSON of the BOP 2D detection tasks).

The file is a list of ``{"scene_id", "image_id", "category_id", "score", "bbox", "time"}``
with ``bbox = [x, y, w, h]`` in px (COCO convention), ``category_id`` the object id and
``time`` the detector's run time for the whole image in s (-1 = unknown). GDRNPP's test
pipeline reads boxes in this shape, so boxes from any detector plug into ``bopsurg predict
--boxes``; ``bopsurg predict --detections-out`` writes the boxes our detector found.

:class:`Detections` (the boxes of one image) lives here, with its file format; the estimator
protocol (:mod:`bopsurg.estimation`) takes and re-exports it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.bop._validate import Issues, get_dict, get_float, get_floats, get_int, get_list
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.errors import BopsurgError, ResultsError
from bopsurg.geometry import as_column

if TYPE_CHECKING:
    from bopsurg.bop.dataset import BopDataset

_KEYS = ("scene_id", "image_id", "category_id", "score", "bbox")

ImageKey = tuple[int, int]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class Detections:
    """2D detections in one image.

    Attributes:
        obj_id: (N,) int64 object ids.
        score: (N,) float64 confidences (higher = more confident).
        bbox: (N, 4) float64 boxes ``(x, y, w, h)`` in px, BOP/COCO convention: (x, y) is the
            top-left corner of the top-left pixel.
    """

    obj_id: I64
    score: F64
    bbox: F64

    def __post_init__(self) -> None:
        n = len(np.atleast_1d(np.asarray(self.obj_id)))
        object.__setattr__(self, "obj_id", as_column(self.obj_id, (n,), "obj_id", np.int64))
        object.__setattr__(self, "score", as_column(self.score, (n,), "score", np.float64))
        object.__setattr__(self, "bbox", as_column(self.bbox, (n, 4), "bbox", np.float64))

    def __len__(self) -> int:
        return len(self.obj_id)

    @classmethod
    def empty(cls) -> Detections:
        """No detections."""
        return cls(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 4)))

    def subset(self, index: ArrayLike) -> Detections:
        """The rows selected by a boolean mask or an index array."""
        idx = np.asarray(index)
        return Detections(self.obj_id[idx], self.score[idx], self.bbox[idx])


def load_detections(path: str | Path) -> tuple[dict[ImageKey, Detections], dict[ImageKey, float]]:
    """Load BOP 2D detections, grouped by image.

    Args:
        path: The JSON file.

    Returns:
        ``(detections, times)``: per ``(scene_id, im_id)`` the boxes (score order kept as in
        the file) and the image's run time in s (-1 when absent).

    Raises:
        ResultsError: Missing file, bad JSON, or a bad entry (named by index and field).
    """
    issues = Issues(path, error=ResultsError)
    content = load_json(path)
    rows: dict[ImageKey, list[tuple[int, float, Any]]] = {}
    times: dict[ImageKey, float] = {}
    for i, entry in enumerate(get_list(content, None, issues, "a list of detections") or []):
        d = get_dict(entry, str(i), issues, "a detection")
        assert d is not None  # issues raises in non-collect mode
        for key in _KEYS:
            if key not in d:
                issues("missing", f"{i}/{key}")
        scene = get_int(d["scene_id"], f"{i}/scene_id", issues, minimum=0)
        im = get_int(d["image_id"], f"{i}/image_id", issues, minimum=0)
        obj = get_int(d["category_id"], f"{i}/category_id", issues, minimum=0)
        score = get_float(d["score"], f"{i}/score", issues)
        bbox = get_floats(d["bbox"], 4, f"{i}/bbox", issues, what=" [x, y, w, h]")
        assert scene is not None
        assert im is not None
        assert obj is not None
        assert score is not None
        assert bbox is not None
        if bbox[2] <= 0 or bbox[3] <= 0:
            issues(f"width and height must be positive, got {bbox[2:].tolist()}", f"{i}/bbox")
        image = (scene, im)
        rows.setdefault(image, []).append((obj, score, bbox))
        time = d.get("time", -1)
        times[image] = -1.0 if time is None else get_float(time, f"{i}/time", issues) or 0.0
    out = {
        key: Detections(
            np.array([r[0] for r in rs], np.int64),
            np.array([r[1] for r in rs]),
            np.array([r[2] for r in rs]).reshape(-1, 4),
        )
        for key, rs in rows.items()
    }
    return out, times


def save_detections(
    path: str | Path,
    detections: Mapping[ImageKey, Detections],
    times: Mapping[ImageKey, float] | None = None,
) -> None:
    """Write BOP 2D detections (atomically), images in ``(scene_id, im_id)`` order.

    Args:
        path: Destination JSON.
        detections: Boxes per ``(scene_id, im_id)``.
        times: Run time per image, s; missing images get -1.
    """
    entries = []
    for scene, im in sorted(detections):
        det = detections[(scene, im)]
        time = -1.0 if times is None else float(times.get((scene, im), -1.0))
        for obj, score, bbox in zip(det.obj_id, det.score, det.bbox, strict=True):
            entries.append(
                {
                    "bbox": [round(float(v), 3) for v in bbox],
                    "category_id": int(obj),
                    "image_id": int(im),
                    "scene_id": int(scene),
                    "score": float(score),
                    "time": time,
                }
            )
    save_json(path, entries)


def gt_detections(dataset: BopDataset) -> dict[ImageKey, Detections]:
    """Oracle boxes: every GT instance's visible box as a detection with score 1.

    Running an estimator on these instead of its detector's boxes separates the detector's
    share of the pose error from the pose stage's. BOP's ``bbox_visib`` has
    ``w = x_max − x_min``; a detection box spans whole pixels, so its width is one more.
    Instances with nothing visible get no box.

    Raises:
        BopsurgError: A scene has no ``scene_gt_info.json`` (run ``bopsurg annotate``).
    """
    out: dict[ImageKey, Detections] = {}
    for scene_id in dataset.scene_ids:
        scene = dataset.scene(scene_id)
        infos = scene.gt_info
        if infos is None:
            raise BopsurgError(
                f"{scene.scene_dir / 'scene_gt_info.json'}: missing, needed for the GT boxes"
            )
        for im_id, gts in scene.gt.items():
            rows = [
                (gt.obj_id, info.bbox_visib)
                for gt, info in zip(gts, infos[im_id], strict=True)
                if info.bbox_visib[2] >= 0
            ]
            if rows:
                boxes = np.array([b for _, b in rows], np.float64) + np.array([0, 0, 1, 1])
                out[(scene_id, im_id)] = Detections(
                    np.array([o for o, _ in rows], np.int64), np.ones(len(rows)), boxes
                )
    return out
