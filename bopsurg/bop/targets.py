"""Evaluation targets (``test_targets_bop19.json``): which object instances are evaluated.

The file is a list of ``{"im_id", "inst_count", "obj_id", "scene_id"}``: in image ``im_id`` of
scene ``scene_id``, the ``inst_count`` most visible instances of object ``obj_id`` are
targets. The reference ``scripts/enumerate_test_targets.py`` counts, per image and object, the
GT instances with ``visib_fract >= 0.1``; objects with no such instance are not targets.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bopsurg.bop._validate import Issues, get_dict, get_int, get_list
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.bop.scene import GtInfo, GtPose
from bopsurg.errors import DatasetError

#: Default visibility threshold of the BOP19 targets.
MIN_VISIB = 0.1
_TARGET_KEYS = ("scene_id", "im_id", "obj_id", "inst_count")


@dataclass(frozen=True, order=True)
class Target:
    """``inst_count`` instances of object ``obj_id`` in image ``im_id`` of ``scene_id``."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


def parse_targets(content: Any, issues: Issues) -> list[Target]:
    """Validate decoded targets content; bad entries are left out (collect mode)."""
    items = get_list(content, None, issues, "a list of targets")
    out = []
    for i, entry in enumerate(items or []):
        d = get_dict(entry, str(i), issues, "a target {scene_id, im_id, obj_id, inst_count}")
        if d is None:
            continue
        vals: list[int | None] = []
        for key in _TARGET_KEYS:
            if key not in d:
                issues("missing", f"{i}/{key}")
                vals.append(None)
            else:
                minimum = 1 if key == "inst_count" else 0
                vals.append(get_int(d[key], f"{i}/{key}", issues, minimum=minimum))
        if all(v is not None for v in vals):
            out.append(Target(*vals))  # type: ignore[arg-type]
    return out


def load_targets(path: str | Path) -> list[Target]:
    """Load a targets file (``test_targets_bop19.json``).

    Args:
        path: The file.

    Returns:
        The targets in file order.

    Raises:
        DatasetError: Missing or malformed file; an entry without integer ``scene_id``,
            ``im_id``, ``obj_id`` (>= 0) and ``inst_count`` (>= 1); ``field`` is
            ``"index/key"``.
    """
    return parse_targets(load_json(path), Issues(path))


def save_targets(path: str | Path, targets: Iterable[Target]) -> None:
    """Write targets in the reference layout (one JSON object per line), atomically."""
    save_json(
        path,
        [
            {
                "im_id": int(t.im_id),
                "inst_count": int(t.inst_count),
                "obj_id": int(t.obj_id),
                "scene_id": int(t.scene_id),
            }
            for t in targets
        ],
    )


def enumerate_targets(
    scene_gts: Mapping[int, Mapping[int, Sequence[GtPose]]],
    scene_gt_infos: Mapping[int, Mapping[int, Sequence[GtInfo]]],
    min_visib: float = MIN_VISIB,
) -> list[Target]:
    """Targets as ``scripts/enumerate_test_targets.py`` makes them.

    Args:
        scene_gts: scene_id → image id → GT instances.
        scene_gt_infos: scene_id → image id → GT meta information (same order).
        min_visib: An instance counts when its ``visib_fract >= min_visib``.

    Returns:
        One target per (scene, image, object) with at least one such instance, sorted by
        scene_id, im_id, obj_id.

    Raises:
        DatasetError: A scene or image lacks gt_info, or its list length differs from the GT's.
    """
    out: list[Target] = []
    for scene_id, gts in scene_gts.items():
        infos = scene_gt_infos.get(scene_id)
        if infos is None:
            raise DatasetError(f"no scene_gt_info for scene {scene_id}", field=str(scene_id))
        for im_id, im_gts in gts.items():
            im_infos = infos.get(im_id)
            if im_infos is None or len(im_infos) != len(im_gts):
                got = "none" if im_infos is None else f"{len(im_infos)} entries"
                raise DatasetError(
                    f"scene {scene_id} image {im_id}: scene_gt_info has {got} for "
                    f"{len(im_gts)} GT instances",
                    field=f"{scene_id}/{im_id}",
                )
            counts = Counter(
                gt.obj_id
                for gt, info in zip(im_gts, im_infos, strict=True)
                if info.visib_fract >= min_visib
            )
            out.extend(Target(int(scene_id), int(im_id), int(o), c) for o, c in counts.items())
    return sorted(out)


# --------------------------------------------------------------------------- BOP24 targets
#: File name of the 6D-detection targets (BOP 2023-2025): the images to evaluate.
TARGETS_BOP24_FILENAME = "test_targets_bop24.json"


@dataclass(frozen=True, order=True)
class ImageTarget:
    """Image ``im_id`` of scene ``scene_id`` is evaluated (BOP24 6D detection, COCO 2D)."""

    scene_id: int
    im_id: int


def parse_image_targets(content: Any, issues: Issues) -> list[ImageTarget]:
    """Validate decoded ``test_targets_bop24.json`` content (``[{"scene_id", "im_id"}]``;
    other keys are allowed and ignored, as the reference does)."""
    items = get_list(content, None, issues, "a list of image targets")
    out = []
    for i, entry in enumerate(items or []):
        d = get_dict(entry, str(i), issues, "an image target {scene_id, im_id}")
        if d is None:
            continue
        vals: list[int | None] = []
        for key in ("scene_id", "im_id"):
            if key not in d:
                issues("missing", f"{i}/{key}")
                vals.append(None)
            else:
                vals.append(get_int(d[key], f"{i}/{key}", issues, minimum=0))
        if vals[0] is not None and vals[1] is not None:
            out.append(ImageTarget(vals[0], vals[1]))
    return out


def load_image_targets(path: str | Path) -> list[ImageTarget]:
    """Load ``test_targets_bop24.json``; the order of the file is kept (it decides the order
    of tied scores in the reference's precision-recall curves).

    Raises:
        DatasetError: Missing or malformed file; ``field`` is ``"index/key"``.
    """
    return parse_image_targets(load_json(path), Issues(path))


def save_image_targets(path: str | Path, targets: Iterable[ImageTarget]) -> None:
    """Write ``test_targets_bop24.json`` in the reference layout, atomically."""
    save_json(path, [{"im_id": int(t.im_id), "scene_id": int(t.scene_id)} for t in targets])


def enumerate_image_targets(
    scene_gts: Mapping[int, Mapping[int, Sequence[GtPose]]],
) -> list[ImageTarget]:
    """Every image with at least one GT instance, sorted by scene and image id.

    The 6D-detection evaluation decides itself which instances count (``visib_fract >= 0.1``)
    and ignores estimates matched to the others, so the file only lists images.
    """
    return sorted(
        ImageTarget(int(s), int(i)) for s, ims in scene_gts.items() for i, gts in ims.items() if gts
    )
