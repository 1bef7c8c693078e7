"""Check a BOP dataset folder and report every problem found, one line each.

:func:`check_dataset` never stops at the first problem and never raises for bad data: it
reports each file's problems and goes on with the other files, so one run lists everything a
user has to fix. Problems found by one check are not repeated by the checks that depend on it
(an unparsable ``scene_gt.json`` does not also produce "unknown image" problems).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from bopsurg.bop._validate import Issues, get_dict, get_float, get_int
from bopsurg.bop.coco import SCENE_GT_COCO, parse_scene_gt_coco
from bopsurg.bop.dataset import BopScene, list_scene_ids, model_path, scene_stream
from bopsurg.bop.images import image_size, load_mask
from bopsurg.bop.jsonio import load_json
from bopsurg.bop.meshes import load_ply, parse_models_info
from bopsurg.bop.registry import recognise
from bopsurg.bop.scene import (
    EMPTY_BBOX,
    CameraInfo,
    GtInfo,
    GtPose,
    bbox_from_mask,
    parse_scene_camera,
    parse_scene_gt,
    parse_scene_gt_info,
)
from bopsurg.bop.targets import TARGETS_BOP24_FILENAME, parse_image_targets, parse_targets
from bopsurg.errors import DatasetError, InputError
from bopsurg.geometry import ROTATION_ATOL, is_rotation

T = TypeVar("T")

logger = logging.getLogger(__name__)

#: Tolerance of ``visib_fract == px_count_visib / px_count_all``.
VISIB_FRACT_ATOL = 1e-6
TARGETS_FILENAME = "test_targets_bop19.json"


@dataclass(frozen=True)
class Problem:
    """One problem of a dataset.

    Attributes:
        path: The file or folder concerned (``file:line`` for JSON syntax errors).
        field: The field, e.g. ``"12/0/cam_R_m2c"`` (image 12, gt_id 0), or None.
        message: What is wrong.
    """

    path: str
    field: str | None
    message: str

    def __str__(self) -> str:
        parts = [self.path, self.field, self.message]
        return " ".join(": ".join(p for p in parts if p).split())


class _EnoughProblemsError(Exception):
    """Raised internally when ``max_problems`` problems have been collected."""


class _Report:
    def __init__(self, max_problems: int | None) -> None:
        self.items: list[Problem] = []
        self.max_problems = max_problems
        #: Files that use obj_id 0, and how often (reported first, see _zero_id_problem).
        self.zero_ids: Counter[str] = Counter()

    def add(self, path: str | Path, field: str | None, message: str) -> None:
        self.items.append(Problem(str(path), field, message))
        if self.max_problems is not None and len(self.items) >= self.max_problems:
            raise _EnoughProblemsError

    def error(self, e: InputError) -> None:
        path = e.path or ""
        if e.line is not None:
            path = f"{path}:{e.line}"
        self.add(path, e.field, e.reason)

    def issues(self, issues: Issues) -> None:
        for field, reason in issues.items:
            self.add(issues.path, field, reason)


def _ids_text(ids: Iterable[int], limit: int = 10) -> str:
    s = sorted(ids)
    text = ", ".join(str(i) for i in s[:limit])
    return text + (f", ... ({len(s)} in all)" if len(s) > limit else "")


def _load(path: Path, rep: _Report, *, missing: str | None = "file not found") -> Any:
    """Decoded JSON content, or None after reporting why not (``missing=None``: silently)."""
    if not path.exists():
        if missing is not None:
            rep.add(path, None, missing)
        return None
    try:
        return load_json(path, keys_to_int=True)
    except InputError as e:
        rep.error(e)
        return None


def _parse(path: Path, content: Any, parser: Callable[[Any, Issues], Any], rep: _Report) -> Any:
    issues = Issues(path, collect=True)
    out = parser(content, issues)
    rep.issues(issues)
    return out


def _rotation_text(R: NDArray[np.float64]) -> str:
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    return (
        f"not a rotation matrix: max |R^T R - I| = {dev:.3g}, det(R) = {det:.6g} "
        f"(tolerance {ROTATION_ATOL:g})"
    )


def _mask_stats(mask: NDArray[np.bool_]) -> tuple[int, tuple[int, int, int, int]]:
    """Pixel count and (x, y, w, h) box of a mask, w = x_max - x_min as the reference."""
    return int(np.count_nonzero(mask)), bbox_from_mask(mask)


# --------------------------------------------------------------------------- models


def _check_models(root: Path, rep: _Report) -> set[int] | None:
    """Check the models folder; returns the obj_ids of models_info.json (None if unknown)."""
    models_dir = next((root / n for n in ("models_eval", "models") if (root / n).is_dir()), None)
    if models_dir is None:
        rep.add(root / "models", None, "models folder not found (looked for models_eval/, models/)")
        return None
    info_path = models_dir / "models_info.json"
    content = _load(info_path, rep)
    if content is None:
        return None
    infos = _parse(info_path, content, parse_models_info, rep)
    # Entries with schema problems still declare their obj_id: count them as known.
    declared = set()
    if isinstance(content, dict):
        declared = {k for k in content if isinstance(k, int) and k >= 0}
    if 0 in declared:
        rep.zero_ids[str(info_path)] += 1
    for obj_id, info in infos.items():
        for i, sym in enumerate(info.get("symmetries_discrete") or []):
            m = np.asarray(sym, dtype=np.float64).reshape(4, 4)
            field = f"{obj_id}/symmetries_discrete/{i}"
            if not is_rotation(m[:3, :3])[0]:
                rep.add(info_path, field, "rotation part: " + _rotation_text(m[:3, :3]))
            if not np.allclose(m[3], [0, 0, 0, 1]):
                rep.add(info_path, field, f"last row must be 0 0 0 1, got {m[3].tolist()}")
    for obj_id in sorted(declared):
        path = model_path(models_dir, obj_id)
        missing = f"model of obj_id {obj_id} (listed in models_info.json) not found"
        model = _read_or_report(path, missing, load_ply, rep)
        if model is not None and model.n_vertices == 0:
            rep.add(path, None, "model has no vertices")
    return declared


def _read_or_report(path: Path, missing: str, read: Callable[[Path], T], rep: _Report) -> T | None:
    """``read(path)``, or None after reporting why the file cannot be read (``missing`` if
    it is not there, else the reader's one-line error)."""
    if not path.is_file():
        rep.add(path, None, missing)
        return None
    try:
        return read(path)
    except InputError as e:
        rep.error(e)
        return None


def _check_camera_json(path: Path, rep: _Report) -> tuple[int, int] | None:
    """Check the dataset's camera file if present; returns its (width, height) if valid."""
    content = _load(path, rep, missing=None)
    if content is None:
        return None
    issues = Issues(path, collect=True)
    d = get_dict(content, None, issues, "camera parameters")
    size = None
    if d is not None:
        for key in ("fx", "fy", "cx", "cy"):
            if key not in d:
                issues("missing", key)
            else:
                v = get_float(d[key], key, issues)
                if v is not None and key in ("fx", "fy") and v <= 0:
                    issues(f"must be > 0, got {v}", key)
        wh = []
        for key in ("width", "height"):
            if key not in d:
                issues("missing", key)
            else:
                wh.append(get_int(d[key], key, issues, minimum=1))
        if "depth_scale" in d:
            v = get_float(d["depth_scale"], "depth_scale", issues)
            if v is not None and v <= 0:
                issues(f"must be > 0, got {v}", "depth_scale")
        if len(wh) == 2 and None not in wh:
            size = (wh[0], wh[1])
    rep.issues(issues)
    return size  # type: ignore[return-value]


# --------------------------------------------------------------------------- scenes


@dataclass
class _SceneSummary:
    """What the targets check needs to know about a scene (None = file unusable)."""

    im_ids: set[int] | None
    obj_counts: dict[int, Counter[int]] | None


def _check_cameras(
    path: Path, cams: dict[int, CameraInfo | None], has_depth: bool, rep: _Report
) -> None:
    for im_id, cam in cams.items():
        if cam is None:
            continue
        K = cam.K
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            rep.add(path, f"{im_id}/cam_K", f"fx and fy must be > 0, got {K[0, 0]}, {K[1, 1]}")
        if not np.allclose(K[2], [0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
            rep.add(path, f"{im_id}/cam_K", f"last row must be 0 0 1, got {K[2].tolist()}")
        if cam.depth_scale is not None and cam.depth_scale <= 0:
            rep.add(path, f"{im_id}/depth_scale", f"must be > 0, got {cam.depth_scale}")
        if cam.depth_scale is None and has_depth and "cam_model" not in cam.extra:
            rep.add(path, f"{im_id}/depth_scale", "missing (needed to convert depth/ to mm)")
        if cam.R_w2c is not None and not is_rotation(cam.R_w2c)[0]:
            rep.add(path, f"{im_id}/cam_R_w2c", _rotation_text(cam.R_w2c))


def _check_gts(
    path: Path, gts: dict[int, list[GtPose | None]], known_obj: set[int] | None, rep: _Report
) -> None:
    where: list[str] = []
    R_list: list[NDArray[np.float64]] = []
    unknown: dict[int, list[str]] = {}
    for im_id, items in gts.items():
        for gt_id, gt in enumerate(items):
            if gt is None:
                continue
            if gt.obj_id == 0:
                rep.zero_ids[str(path)] += 1
            if known_obj is not None and gt.obj_id not in known_obj:
                unknown.setdefault(gt.obj_id, []).append(f"{im_id}/{gt_id}/obj_id")
            if np.all(gt.t == -1):  # placeholder of a fully occluded instance
                continue
            where.append(f"{im_id}/{gt_id}/cam_R_m2c")
            R_list.append(gt.R)
    for obj_id, fields in sorted(unknown.items()):
        more = f" ({len(fields)} instances in this file)" if len(fields) > 1 else ""
        rep.add(path, fields[0], f"unknown obj_id {obj_id}: not in models_info.json{more}")
    if R_list:
        R = np.stack(R_list)
        for k in np.flatnonzero(~is_rotation(R)):
            rep.add(path, where[k], _rotation_text(R[k]))


def _check_gt_info_entry(path: Path, field: str, info: GtInfo, rep: _Report) -> None:
    expected = info.px_count_visib / info.px_count_all if info.px_count_all > 0 else 0.0
    if abs(info.visib_fract - expected) > VISIB_FRACT_ATOL:
        rep.add(
            path,
            f"{field}/visib_fract",
            f"{info.visib_fract} != px_count_visib / px_count_all = "
            f"{info.px_count_visib}/{info.px_count_all} = {expected:.6g}",
        )
    for key in ("px_count_visib", "px_count_valid"):
        if getattr(info, key) > info.px_count_all:
            rep.add(
                path,
                f"{field}/{key}",
                f"{getattr(info, key)} > px_count_all = {info.px_count_all}",
            )
    if info.px_count_visib == 0 and info.bbox_visib != EMPTY_BBOX:
        rep.add(
            path,
            f"{field}/bbox_visib",
            f"must be [-1, -1, -1, -1] when px_count_visib is 0, got {list(info.bbox_visib)}",
        )
    elif info.px_count_visib > 0 and min(info.bbox_visib[2:]) < 0:
        rep.add(path, f"{field}/bbox_visib", f"negative width/height {list(info.bbox_visib)}")


def _check_masks(
    scene: BopScene,
    im_id: int,
    infos: list[GtInfo | None] | None,
    n_gt: int,
    size: tuple[int, int] | None,
    folders: tuple[bool, bool],
    rep: _Report,
) -> None:
    """Check mask/ and mask_visib/ of one image; each file is read once."""
    has_mask, has_visib = folders
    for gt_id in range(n_gt):
        info = infos[gt_id] if infos is not None and gt_id < len(infos) else None
        masks: dict[str, NDArray[np.bool_]] = {}
        for kind, present, path in (
            ("mask", has_mask, scene.mask_path(im_id, gt_id)),
            ("mask_visib", has_visib, scene.mask_visib_path(im_id, gt_id)),
        ):
            if not present:
                continue
            missing = f"{kind} of image {im_id}, gt_id {gt_id} not found"
            m = _read_or_report(path, missing, load_mask, rep)
            if m is None:
                continue
            if size is not None and (m.shape[1], m.shape[0]) != size:
                rep.add(path, None, f"size {m.shape[1]}x{m.shape[0]} != image {size[0]}x{size[1]}")
                continue
            masks[kind] = m
            if info is None:
                continue
            count, box = _mask_stats(m)
            if kind == "mask_visib":
                if count != info.px_count_visib:
                    rep.add(
                        path,
                        None,
                        f"{count} mask pixels != px_count_visib {info.px_count_visib} "
                        f"of scene_gt_info.json {im_id}/{gt_id}",
                    )
                if box != info.bbox_visib:
                    rep.add(
                        path,
                        None,
                        f"bounding box {list(box)} != bbox_visib {list(info.bbox_visib)} "
                        f"of scene_gt_info.json {im_id}/{gt_id}",
                    )
            # mask/ is the silhouette inside the image: at least the pixels with valid depth,
            # at most the whole silhouette (which px_count_all counts beyond the image too).
            elif not info.px_count_valid <= count <= info.px_count_all:
                rep.add(
                    path,
                    None,
                    f"{count} mask pixels outside [px_count_valid, px_count_all] = "
                    f"[{info.px_count_valid}, {info.px_count_all}] of scene_gt_info.json "
                    f"{im_id}/{gt_id}",
                )
        if len(masks) == 2:
            outside = int(np.count_nonzero(masks["mask_visib"] & ~masks["mask"]))
            if outside:
                rep.add(
                    scene.mask_visib_path(im_id, gt_id),
                    None,
                    f"{outside} visible pixels lie outside the object's mask/",
                )


def _check_images(
    scene: BopScene,
    im_ids: list[int],
    gts: dict[int, list[GtPose | None]] | None,
    infos: dict[int, list[GtInfo | None]] | None,
    expected: tuple[tuple[int, int], str] | None,
    rep: _Report,
) -> None:
    d = scene.scene_dir
    has_rgb = any((d / f).is_dir() for f in scene.image_dirs)
    has_depth = scene.depth_dir is not None and (d / scene.depth_dir).is_dir()
    folders = (scene.mask_path(0, 0).parent.is_dir(), scene.mask_visib_path(0, 0).parent.is_dir())
    if not has_rgb:
        names = " nor ".join(f"{f}/" for f in scene.image_dirs)
        rep.add(d / scene.image_dirs[0], None, f"image folder not found (neither {names})")
    size_of: tuple[int, int] | None = None if expected is None else expected[0]
    source = "" if expected is None else expected[1]
    for im_id in im_ids:
        size = size_of
        if has_rgb:
            path = scene.rgb_path(im_id)
            got = _read_or_report(path, f"image {im_id} not found", image_size, rep)
            if got is not None and size_of is not None and got != size_of:
                msg = f"size {got[0]}x{got[1]} != {size_of[0]}x{size_of[1]} of {source}"
                rep.add(path, None, msg)
            size = size or got
        if has_depth:
            path = scene.depth_path(im_id)
            got = _read_or_report(path, f"depth image {im_id} not found", image_size, rep)
            if got is not None and size is not None and got != size:
                msg = f"size {got[0]}x{got[1]} != image {size[0]}x{size[1]}"
                rep.add(path, None, msg)
        if gts is not None and im_id in gts and any(folders):
            im_infos = infos.get(im_id) if infos is not None else None
            _check_masks(scene, im_id, im_infos, len(gts[im_id]), size, folders, rep)


def _check_scene(
    scene: BopScene,
    known_obj: set[int] | None,
    expected_size: tuple[tuple[int, int], str] | None,
    check_images: bool,
    rep: _Report,
) -> _SceneSummary:
    d = scene.scene_dir
    cam_path, gt_path, info_path = scene.camera_path, scene.gt_path, scene.gt_info_path
    cams = gts = infos = None
    content = _load(cam_path, rep)
    if content is not None:
        cams = _parse(cam_path, content, parse_scene_camera, rep)
        _check_cameras(cam_path, cams, (d / (scene.depth_dir or "depth")).is_dir(), rep)
    content = _load(gt_path, rep, missing="file not found (needed for evaluation)")
    if content is not None:
        gts = _parse(gt_path, content, parse_scene_gt, rep)
        _check_gts(gt_path, gts, known_obj, rep)
    content = _load(info_path, rep, missing="file not found (visibility, needed for evaluation)")
    if content is not None:
        infos = _parse(info_path, content, parse_scene_gt_info, rep)

    if cams is not None and gts is not None:
        if extra := set(gts) - set(cams):
            rep.add(gt_path, None, f"images not in {cam_path.name}: {_ids_text(extra)}")
        if extra := set(cams) - set(gts):
            rep.add(cam_path, None, f"images not in {gt_path.name}: {_ids_text(extra)}")
    if gts is not None and infos is not None:
        if extra := set(infos) - set(gts):
            rep.add(info_path, None, f"images not in {gt_path.name}: {_ids_text(extra)}")
        if extra := set(gts) - set(infos):
            rep.add(info_path, None, f"images of {gt_path.name} missing here: {_ids_text(extra)}")
        for im_id in sorted(set(gts) & set(infos)):
            if len(infos[im_id]) != len(gts[im_id]):
                rep.add(
                    info_path,
                    str(im_id),
                    f"{len(infos[im_id])} entries, but {gt_path.name} has "
                    f"{len(gts[im_id])} GT instances",
                )
    if infos is not None:
        for im_id, items in infos.items():
            for gt_id, info in enumerate(items):
                if info is not None:
                    _check_gt_info_entry(info_path, f"{im_id}/{gt_id}", info, rep)

    if check_images:
        im_ids = sorted(set(cams or ()) | set(gts or ()))
        _check_images(scene, im_ids, gts, infos, expected_size, rep)

    obj_counts = None
    if gts is not None:
        obj_counts = {
            im_id: Counter(g.obj_id for g in items if g is not None) for im_id, items in gts.items()
        }
    im_ids_known = None if cams is None and gts is None else set(cams or ()) | set(gts or ())
    return _SceneSummary(im_ids_known, obj_counts)


# --------------------------------------------------------------------------- targets


def _check_targets(
    root: Path,
    scenes: dict[int, _SceneSummary],
    known_obj: set[int] | None,
    rep: _Report,
) -> None:
    path = root / TARGETS_FILENAME
    content = _load(path, rep, missing=None)
    if content is None:
        return
    issues = Issues(path, collect=True)
    targets = parse_targets(content, issues)
    rep.issues(issues)
    missing_scenes: dict[int, int] = {}
    for i, t in enumerate(targets):
        if t.scene_id not in scenes:
            missing_scenes[t.scene_id] = missing_scenes.get(t.scene_id, i)
            continue
        s = scenes[t.scene_id]
        if known_obj is not None and t.obj_id not in known_obj:
            rep.add(path, f"{i}/obj_id", f"unknown obj_id {t.obj_id}: not in models_info.json")
        if s.im_ids is not None and t.im_id not in s.im_ids:
            rep.add(path, f"{i}/im_id", f"scene {t.scene_id} has no image {t.im_id}")
            continue
        if s.obj_counts is not None:
            n = s.obj_counts.get(t.im_id, Counter())[t.obj_id]
            if t.inst_count > n:
                rep.add(
                    path,
                    f"{i}/inst_count",
                    f"{t.inst_count} > {n} GT instances of obj_id {t.obj_id} in scene "
                    f"{t.scene_id} image {t.im_id}",
                )
    for sid, first in sorted(missing_scenes.items()):
        rep.add(path, f"{first}/scene_id", f"scene {sid} is not in the split")


def _parse_optional(path: Path, rep: _Report, parse: Callable[[Any, Issues], T]) -> T | None:
    """Parse a file that may be absent, reporting its issues; None when absent or unreadable."""
    content = _load(path, rep, missing=None)
    if content is None:
        return None
    issues = Issues(path, collect=True)
    parsed = parse(content, issues)
    rep.issues(issues)
    return parsed


def _check_image_targets(root: Path, scenes: dict[int, _SceneSummary], rep: _Report) -> None:
    """``test_targets_bop24.json`` (if present) names existing scenes and images."""
    path = root / TARGETS_BOP24_FILENAME
    targets = _parse_optional(path, rep, parse_image_targets)
    if targets is None:
        return
    for i, t in enumerate(targets):
        s = scenes.get(t.scene_id)
        if s is None:
            rep.add(path, f"{i}/scene_id", f"scene {t.scene_id} is not in the split")
        elif s.im_ids is not None and t.im_id not in s.im_ids:
            rep.add(path, f"{i}/im_id", f"scene {t.scene_id} has no image {t.im_id}")


# --------------------------------------------------------------------------- entry point


def check_dataset(
    root: str | Path,
    split: str = "test",
    *,
    split_type: str | None = None,
    check_images: bool = True,
    max_problems: int | None = None,
    progress: bool = False,
    dataset: str | None = None,
) -> list[Problem]:
    """Check a BOP dataset and return all problems found (empty list: all fine).

    Checked: the models folder (``models_eval/`` or ``models/``), the schema of
    ``models_info.json`` and that each of its models exists and loads; ``camera.json`` if
    present; per scene the schema of ``scene_camera.json``, ``scene_gt.json`` and
    ``scene_gt_info.json``, that they list the same images and as many instances, known
    obj_ids, rotations (``geometry.is_rotation``), ``cam_K`` (fx, fy > 0, last row 0 0 1),
    ``depth_scale`` > 0, ``visib_fract = px_count_visib / px_count_all`` (1e-6); with
    ``check_images``: rgb (and depth, if ``depth/`` exists) files exist with the camera.json
    size, masks exist (if ``mask/``, ``mask_visib/`` exist), a ``mask_visib`` has exactly
    ``px_count_visib`` pixels and ``bbox_visib`` as its box, a ``mask`` has between
    ``px_count_valid`` and ``px_count_all`` pixels and contains ``mask_visib``; finally
    ``test_targets_bop19.json`` (if present) names existing scenes, images and objects with
    ``inst_count`` no larger than the number of GT instances, and ``test_targets_bop24.json``
    (if present) existing scenes and images; each ``scene_gt_coco.json`` (if present) has the
    COCO layout and RLE masks of the stated size. A dataset that numbers an object 0 (as the
    AMBF pipeline's BOP writer does) gets that problem first, with the command that renumbers
    it.

    Args:
        root: The dataset folder.
        split: The split, e.g. ``"test"``.
        split_type: Optional split type (folder ``{split}_{split_type}``).
        check_images: Also check image and mask files (slower: masks are read).
        max_problems: Stop after this many problems.
        progress: Show a progress bar over the scenes.
        dataset: A standard BOP dataset's name whose defaults apply (split type, camera
            file, image size, streams; :mod:`bopsurg.bop.registry`); None: the one the
            folder's name matches, if any; ``"none"``: no defaults.

    Returns:
        The problems, in the order found.
    """
    rep = _Report(max_problems)
    try:
        _check_all(Path(root), split, split_type, check_images, progress, rep, dataset)
    except _EnoughProblemsError:
        logger.info("stopped after %d problems", len(rep.items))
    if rep.zero_ids:
        rep.items.insert(0, _zero_id_problem(Path(root), rep.zero_ids))
        if max_problems is not None:
            del rep.items[max_problems:]
    return rep.items


def _zero_id_problem(root: Path, files: Counter[str]) -> Problem:
    """The first problem of a dataset that numbers an object 0, with how to fix it.

    BOP object ids start at 1 (the reference toolkit and ``bopsurg annotate`` reject 0); the
    AMBF pipeline's BOP writer numbers its needle 0.
    """
    first, uses = next(iter(files.items()))
    more = f" and {len(files) - 1} other file(s)" if len(files) > 1 else ""
    return Problem(
        first,
        "obj_id",
        f"obj_id 0 is used ({uses}x here{more}), but BOP object ids start at 1; renumber "
        f"the objects with: bopsurg import bop {root} --out NEW_DATASET --obj-id-offset 1",
    )


def _check_all(
    root: Path,
    split: str,
    split_type: str | None,
    check_images: bool,
    progress: bool,
    rep: _Report,
    dataset: str | None = None,
) -> None:
    if not root.is_dir():
        rep.add(root, None, "dataset folder not found")
        return
    try:
        spec = recognise(root, dataset)
    except KeyError as err:
        rep.add(root, None, str(err.args[0]))
        return
    if spec is not None:
        split_type = spec.split_type(split, split_type, root)
    known_obj = _check_models(root, rep)
    camera = root / ("camera.json" if spec is None else spec.camera_file(split_type))
    camera_size = _check_camera_json(camera, rep)
    split_dir = root / (split if split_type is None else f"{split}_{split_type}")
    if not split_dir.is_dir():
        rep.add(split_dir, None, "split folder not found")
        return
    scene_ids = list_scene_ids(split_dir)
    if not scene_ids:
        rep.add(split_dir, None, "no scene folders (expected 6-digit names such as 000001)")
    summaries: dict[int, _SceneSummary] = {}
    for sid in tqdm(scene_ids, desc="checking scenes", unit="scene", disable=not progress):
        d = split_dir / f"{sid:06d}"
        try:
            scene = BopScene(sid, d, scene_stream(d, spec, None))
        except DatasetError as err:
            rep.error(err)
            continue
        expected = None if camera_size is None else (camera_size, camera.name)
        if spec is not None:  # the reference's size of this split type and stream
            stream = None if scene.stream is None else scene.stream.name
            expected = (spec.image_size(split_type, stream, split), f"the {spec.name} dataset")
        summaries[sid] = _check_scene(scene, known_obj, expected, check_images, rep)
    _check_targets(root, summaries, known_obj, rep)
    _check_image_targets(root, summaries, rep)
    for sid in scene_ids:  # 2D annotations of the COCO tasks, where present
        _parse_optional(split_dir / f"{sid:06d}" / SCENE_GT_COCO, rep, parse_scene_gt_coco)
