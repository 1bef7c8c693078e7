"""Import the data of the paper's AMBF pipeline as BOP datasets that ``bopsurg check`` accepts.

The seed pipeline of *Realistic Data Generation for 6D Pose Estimation of Surgical
Instruments* wrote, before its BOP writer, one folder per recording::

    SRC/
      raw_img/NNNNN.png        RGB frames
      depth_img/NNNNN.png      uint16 depth (1 unit = 1 mm in that pipeline: --depth-scale)
      segmented_img/NNNNN.png  flat material colours (not needed: masks are rendered)
      intrinsic.yaml           intrinsic: 'fx, 0, cx, 0, fy, cy, 0, 0, 1'   (one string)
      extrinsic.yaml           'NNNNN': {rot_model2cam: '9 numbers, row-major',
                                         t_model2cam: '3 numbers, mm'}      (strings)

with the needle's pose model-to-camera in the frame of the pipeline's own needle mesh.
:func:`import_ambf_yaml` turns it into one BOP scene: ``rgb/``, ``depth/`` with its
``depth_scale``, ``scene_camera.json``, ``scene_gt.json`` (the needle is ``obj_id`` 1),
the needle model and ``models_info.json`` (with tip, tail and plane normal from
:func:`bopsurg.needle.fit_needle`), then masks, ``scene_gt_info.json`` and the test targets
by :func:`bopsurg.annotate.annotate_dataset`. Everything is read and validated first; the
dataset is built in a temporary folder beside ``out`` and renamed onto it at the end, so a
failed import leaves nothing half-written.

The pipeline's later BOP writer numbers its needle ``obj_id`` 0 (BOP ids start at 1):
:func:`import_bop_renumbered` copies such a dataset with every obj_id shifted (models, their
files, ``scene_gt.json``, test targets), and annotates the scenes that lack masks and
``scene_gt_info.json``, with the same all-or-nothing writing.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from bopsurg.atomic import atomic_folder, check_new_folder
from bopsurg.bop.dataset import list_scene_ids, model_path, save_camera_json
from bopsurg.bop.images import image_size, load_depth, save_depth
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.bop.meshes import ObjectModel, load_ply, save_models_info, save_ply
from bopsurg.bop.scene import (
    CameraInfo,
    GtPose,
    load_scene_gt,
    load_scene_gt_info,
    save_scene_camera,
    save_scene_gt,
)
from bopsurg.errors import DatasetError
from bopsurg.geometry import is_rotation
from bopsurg.needle import NeedleArc, fit_needle, needle_mesh, needle_model_info
from bopsurg.plugins import DepthRenderer

log = logging.getLogger(__name__)

#: The needle's obj_id in the imported dataset (BOP ids start at 1).
NEEDLE_OBJ_ID = 1
#: Visibility tolerance of the masks, mm: the paper's pipeline computed its masks with 1 mm
#: (its depth is exact up to the 1 mm rounding); BOP's 15 mm would count the tissue a needle
#: is stitched through, a few mm in front of it, as not occluding.
AMBF_DELTA_MM = 1.0
#: The scene the frames go to.
SCENE_ID = 1
RECORD_NAME = "bopsurg_import.json"
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


@dataclass(frozen=True)
class AmbfFrame:
    """One frame of the YAML layout: its files and the needle's GT pose (mm)."""

    key: str
    im_id: int
    rgb: Path
    depth: Path | None
    R: np.ndarray
    t: np.ndarray


@dataclass(frozen=True)
class AmbfRecording:
    """A validated YAML-layout folder: the camera matrix, image size and frames."""

    K: np.ndarray
    size: tuple[int, int]
    frames: list[AmbfFrame]


@dataclass(frozen=True)
class ImportReport:
    """What an import wrote."""

    out: Path
    images: int
    with_depth: bool
    arc: NeedleArc
    visib_fract: list[float]


def _numbers(value: Any, n: int, path: Path, field: str) -> np.ndarray:
    """``n`` numbers from the pipeline's comma-separated string (or a YAML list)."""
    if isinstance(value, list) and all(isinstance(v, (int, float)) for v in value):
        out = np.asarray(value, dtype=np.float64)
    elif isinstance(value, str):
        tokens = [s.strip() for s in value.split(",")]
        if not all(_NUMBER.fullmatch(s) for s in tokens):
            raise DatasetError(
                f"expected {n} comma-separated numbers, got {value!r}", path=path, field=field
            )
        out = np.array([float(s) for s in tokens])
    else:
        raise DatasetError(
            f"expected {n} comma-separated numbers, got {type(value).__name__}",
            path=path,
            field=field,
        )
    if out.shape != (n,) or not np.isfinite(out).all():
        raise DatasetError(f"expected {n} finite numbers, got {out.size}", path=path, field=field)
    return out


def _load_yaml(path: Path) -> Any:
    if not path.is_file():
        raise DatasetError("file not found (part of the AMBF YAML layout)", path=path)
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        mark = getattr(err, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        reason = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise DatasetError(f"not valid YAML ({reason})", path=path, line=line) from None


def _read_intrinsics(intr_path: Path) -> np.ndarray:
    """K (3, 3), px, of ``intrinsic.yaml``, checked to be a camera matrix."""
    intr = _load_yaml(intr_path)
    if not isinstance(intr, dict) or "intrinsic" not in intr:
        raise DatasetError(
            "missing ('fx, 0, cx, 0, fy, cy, 0, 0, 1')", path=intr_path, field="intrinsic"
        )
    K = _numbers(intr["intrinsic"], 9, intr_path, "intrinsic").reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise DatasetError(
            f"not a camera matrix: {K.ravel().tolist()}", path=intr_path, field="intrinsic"
        )
    return K


def _read_frame(
    key: Any, entry: Any, extr_path: Path, rgb_dir: Path, depth_dir: Path | None
) -> AmbfFrame:
    """One entry of ``extrinsic.yaml``: its pose checked, its RGB (and depth) image found."""
    if not isinstance(key, str) or not key.isdigit():
        raise DatasetError(
            f"frame key must be a quoted frame number such as '00010', got {key!r}",
            path=extr_path,
        )
    if not isinstance(entry, dict):
        raise DatasetError("expected rot_model2cam and t_model2cam", path=extr_path, field=key)
    for name in ("rot_model2cam", "t_model2cam"):
        if name not in entry:
            raise DatasetError("missing", path=extr_path, field=f"{key}/{name}")
    R = _numbers(entry["rot_model2cam"], 9, extr_path, f"{key}/rot_model2cam").reshape(3, 3)
    t = _numbers(entry["t_model2cam"], 3, extr_path, f"{key}/t_model2cam")
    if not is_rotation(R)[0]:
        raise DatasetError(
            "not a rotation matrix (orthonormal, det +1)",
            path=extr_path,
            field=f"{key}/rot_model2cam",
        )
    rgb = rgb_dir / f"{key}.png"
    if not rgb.is_file():
        raise DatasetError(f"frame {key} of {extr_path.name} has no image", path=rgb)
    depth = depth_dir / f"{key}.png" if depth_dir is not None else None
    if depth is not None and not depth.is_file():
        raise DatasetError(f"frame {key} of {extr_path.name} has no depth image", path=depth)
    return AmbfFrame(key, int(key), rgb, depth, R, t)


def read_ambf_yaml(src: str | Path) -> AmbfRecording:
    """Read and validate a folder of the YAML layout (see the module docstring).

    Raises:
        DatasetError: The first problem, one line naming file and field: a missing file or
            folder, a frame without an image (or an image without a pose), numbers that do
            not parse, a rotation that is not one, images of different sizes.
    """
    src = Path(src)
    if not src.is_dir():
        raise DatasetError("folder not found", path=src)
    extr_path = src / "extrinsic.yaml"
    K = _read_intrinsics(src / "intrinsic.yaml")
    extr = _load_yaml(extr_path)
    if not isinstance(extr, dict) or not extr:
        raise DatasetError(
            "expected a mapping from frame number ('00010') to a pose", path=extr_path
        )
    rgb_dir, depth_dir = src / "raw_img", src / "depth_img"
    if not rgb_dir.is_dir():
        raise DatasetError("folder of RGB frames not found", path=rgb_dir)
    has_depth = depth_dir.is_dir()
    if not has_depth:
        log.warning("%s: no depth_img/ folder; visibility will come from the needle alone", src)
    frames = [
        _read_frame(key, entry, extr_path, rgb_dir, depth_dir if has_depth else None)
        for key, entry in extr.items()
    ]
    ids = [f.im_id for f in frames]
    if len(set(ids)) != len(ids):
        raise DatasetError("two frame keys name the same frame number", path=extr_path)
    posed = {f.rgb.name for f in frames}
    unposed = sorted(p.name for p in rgb_dir.glob("*.png") if p.name not in posed)
    if unposed:
        raise DatasetError(
            f"{len(unposed)} image(s) have no pose in {extr_path.name}, e.g. {unposed[0]}",
            path=rgb_dir,
        )
    frames.sort(key=lambda f: f.im_id)
    size = image_size(frames[0].rgb)
    for f in frames:
        for path in (f.rgb, f.depth):
            if path is not None and image_size(path) != size:
                got = image_size(path)
                raise DatasetError(
                    f"size {got[0]}x{got[1]} != {size[0]}x{size[1]} of {frames[0].rgb.name}",
                    path=path,
                )
    return AmbfRecording(K, size, frames)


def ambf_needle() -> ObjectModel:
    """bopsurg's needle (:func:`~bopsurg.needle.needle_mesh`) in the AMBF needle's frame.

    The AMBF pipeline's ``Needle.ply`` lies in its XY plane around the origin, its tail at
    about 183° and its tip at about 56° about +Z: bopsurg's needle turned half a turn about
    +X (the arc then runs clockwise) and 183° about +Z. Used when no ``--model`` is given;
    the pipeline's own mesh is closer.
    """
    m = needle_mesh()
    a = np.deg2rad(183.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    R = Rz @ np.diag([1.0, -1.0, -1.0])
    normals = None if m.normals is None else m.normals @ R.T
    return ObjectModel(m.pts @ R.T, m.faces, normals)  # a rotation keeps the winding


def _check_depth(frame: AmbfFrame) -> None:
    assert frame.depth is not None
    depth = load_depth(frame.depth)  # single channel or a one-line error
    if depth.max() <= 0:
        raise DatasetError("depth image is all zero", path=frame.depth)


def import_ambf_yaml(
    src: str | Path,
    out: str | Path,
    *,
    model: str | Path | None = None,
    split: str = "test",
    depth_scale: float = 1.0,
    delta: float = AMBF_DELTA_MM,
    renderer: DepthRenderer | None = None,
    renderer_name: str | None = None,
    progress: bool = True,
) -> ImportReport:
    """Write the BOP dataset ``out`` from the YAML-layout folder ``src``.

    Args:
        src: The pipeline's folder (raw_img/, depth_img/, intrinsic.yaml, extrinsic.yaml).
        out: The dataset folder to create; it must not exist yet (or be empty).
        model: The needle mesh the poses refer to (PLY, mm), e.g. the pipeline's
            ``Needle.ply``; None: :func:`ambf_needle`, bopsurg's needle in that frame.
        split: Split folder name.
        depth_scale: mm per stored depth unit (the AMBF pipeline stores 1 mm).
        delta: Visibility tolerance of the masks, mm (see ``bopsurg annotate``).
        renderer: Depth renderer for the masks; default: the plugin ``renderer_name``.
        renderer_name: Depth renderer plugin name (default: the first installed).
        progress: Show progress bars.

    Raises:
        DatasetError: Bad or partial input (nothing is written then), ``out`` not empty.
        ModelError: The model cannot be read or is not a needle.
    """
    from bopsurg.annotate import annotate_dataset

    src, out = Path(src), Path(out)
    if not depth_scale > 0:
        raise DatasetError(f"must be > 0, got {depth_scale}", field="depth_scale")
    check_new_folder(out)
    rec = read_ambf_yaml(src)
    for frame in rec.frames:
        if frame.depth is not None:
            _check_depth(frame)
    needle = load_ply(model) if model is not None else ambf_needle()
    arc = fit_needle(needle, name=str(model) if model is not None else "the built-in needle")
    if renderer is None:
        from bopsurg.plugins import load_plugin

        renderer = load_plugin("renderer", renderer_name)()

    with atomic_folder(out) as tmp:
        _write(tmp, rec, needle, arc, split, depth_scale)
        annotate_dataset(tmp, split, renderer=renderer, delta=delta, progress=progress)
        record = {
            "source": str(src.resolve()),
            "layout": "ambf-yaml",
            "model": str(Path(model).resolve()) if model is not None else "bopsurg ambf_needle()",
            "depth_scale": depth_scale,
            "delta_mm": delta,
            "frames": {f.key: f.im_id for f in rec.frames},
        }
        (tmp / RECORD_NAME).write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    infos = load_scene_gt_info(out / split / f"{SCENE_ID:06d}" / "scene_gt_info.json")
    visib = [i[0].visib_fract for _, i in sorted(infos.items())]
    return ImportReport(out, len(rec.frames), rec.frames[0].depth is not None, arc, visib)


def _write(
    root: Path,
    rec: AmbfRecording,
    needle: ObjectModel,
    arc: NeedleArc,
    split: str,
    depth_scale: float,
) -> None:
    """Models, camera and one scene with images and GT (masks come from annotate)."""
    models = root / "models"
    save_ply(model_path(models, NEEDLE_OBJ_ID), needle)
    save_models_info(models / "models_info.json", {NEEDLE_OBJ_ID: needle_model_info(needle, arc)})
    with_depth = rec.frames[0].depth is not None
    save_camera_json(root, rec.K, *rec.size, depth_scale=depth_scale if with_depth else None)
    scene = root / split / f"{SCENE_ID:06d}"
    cams: dict[int, CameraInfo] = {}
    gts: dict[int, list[GtPose]] = {}
    for f in rec.frames:
        # PNG bytes are kept as they are: no re-encoding of the pipeline's pixels.
        (scene / "rgb").mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f.rgb, scene / "rgb" / f"{f.im_id:06d}.png")
        if f.depth is not None:
            save_depth(scene / "depth" / f"{f.im_id:06d}.png", load_depth(f.depth))
        cams[f.im_id] = CameraInfo(rec.K, depth_scale if with_depth else None)
        gts[f.im_id] = [GtPose(NEEDLE_OBJ_ID, f.R, f.t)]
    save_scene_camera(scene / "scene_camera.json", cams)
    save_scene_gt(scene / "scene_gt.json", gts)


# --------------------------------------------------------------------------- BOP, obj_id 0

_MODEL_DIRS = ("models", "models_eval", "models_cad", "models_fine")


@dataclass(frozen=True)
class RenumberReport:
    """What :func:`import_bop_renumbered` wrote."""

    out: Path
    obj_ids: dict[int, int]
    instances: int
    annotated_splits: list[str]


def _split_dirs(root: Path) -> list[Path]:
    """Folders of ``root`` that hold scenes (6-digit subfolders)."""
    return sorted(d for d in root.iterdir() if d.is_dir() and list_scene_ids(d))


def _load_scene_gts(
    src: Path, splits: list[Path], ids: set[int]
) -> dict[Path, dict[int, list[GtPose]]]:
    """Every split's ``scene_gt.json`` (by path relative to ``src``), each obj_id checked to
    be one of ``ids``."""
    gts = {}
    for split in splits:
        for sid in list_scene_ids(split):
            path = split / f"{sid:06d}" / "scene_gt.json"
            if path.is_file():
                gts[path.relative_to(src)] = load_scene_gt(path)
    for gt_file, scene_gts in gts.items():
        for im_id, items in scene_gts.items():
            for gt_id, gt in enumerate(items):
                if gt.obj_id not in ids:
                    raise DatasetError(
                        f"unknown obj_id {gt.obj_id}: not in models_info.json",
                        path=src / gt_file,
                        field=f"{im_id}/{gt_id}/obj_id",
                    )
    return gts


def _load_targets(src: Path) -> dict[str, Any]:
    """The dataset's ``test_targets*.json`` by file name, each a list of targets."""
    targets = {p.name: load_json(p) for p in sorted(src.glob("test_targets*.json"))}
    for name, content in targets.items():
        # BOP19 targets name an object; BOP24 ones (per image) name none and stay as they are.
        if not isinstance(content, list) or not all(
            isinstance(t, dict) and isinstance(t.get("obj_id", 0), int) for t in content
        ):
            raise DatasetError("expected a list of targets with integer obj_id", path=src / name)
    return targets


def _renumber_models(folder: Path, info: dict[Any, Any], new_id: dict[int, int]) -> None:
    """Rename the model files of ``folder`` to their new obj_ids and rewrite its
    ``models_info.json`` (``info``, the source's) with them."""
    moved = {}
    for i in new_id:  # two steps, so that obj 0 -> 1 does not overwrite obj 1 -> 2
        old = model_path(folder, i)
        if old.is_file():
            moved[i] = old.rename(old.with_name(f".renumber-{old.name}"))
    for i, path in moved.items():
        path.rename(model_path(folder, new_id[i]))
    save_json(folder / "models_info.json", {new_id[int(k)]: v for k, v in info.items()})


def import_bop_renumbered(
    src: str | Path,
    out: str | Path,
    *,
    obj_id_offset: int = 1,
    delta: float = AMBF_DELTA_MM,
    renderer_name: str | None = None,
    progress: bool = True,
) -> RenumberReport:
    """Copy the BOP dataset ``src`` to ``out`` with every obj_id shifted by ``obj_id_offset``.

    Renumbers ``models*/models_info.json`` and the model files, every split's
    ``scene_gt.json`` and ``test_targets*.json``; masks and ``scene_gt_info.json`` do not name
    objects and are copied as they are. Scenes without ``scene_gt_info.json`` are annotated
    (masks, gt_info, targets: ``bopsurg annotate`` with ``delta`` mm).

    Raises:
        DatasetError: A file that does not parse, an id that would stay below 1, ``out`` not
            empty; nothing is written then.
    """
    src, out = Path(src), Path(out)
    if not src.is_dir():
        raise DatasetError("dataset folder not found", path=src)
    check_new_folder(out)
    model_dirs = [src / n for n in _MODEL_DIRS if (src / n / "models_info.json").is_file()]
    if not model_dirs:
        raise DatasetError("no models/models_info.json (the objects to renumber)", path=src)
    infos = {d.name: load_json(d / "models_info.json", keys_to_int=True) for d in model_dirs}
    ids = sorted({int(k) for info in infos.values() for k in info})
    if min(ids) + obj_id_offset < 1:
        raise DatasetError(
            f"obj_id {min(ids)} + offset {obj_id_offset} is below 1 (BOP ids start at 1)",
            path=model_dirs[0] / "models_info.json",
        )
    splits = _split_dirs(src)
    gts = _load_scene_gts(src, splits, set(ids))  # validated before anything is written
    targets = _load_targets(src)
    cocos = {
        path.relative_to(src): load_json(path)
        for split in splits
        for path in sorted(split.glob("*/scene_gt_coco.json"))
    }

    new_id = {i: i + obj_id_offset for i in ids}
    annotated: list[str] = []
    with atomic_folder(out) as tmp:
        shutil.copytree(src, tmp, dirs_exist_ok=True, ignore=shutil.ignore_patterns(".*.tmp-*"))
        for d in model_dirs:
            _renumber_models(tmp / d.name, infos[d.name], new_id)
        for gt_file, scene_gts in gts.items():
            renumbered = {
                im_id: [GtPose(new_id[g.obj_id], g.R, g.t, g.extra) for g in items]
                for im_id, items in scene_gts.items()
            }
            save_scene_gt(tmp / gt_file, renumbered)
        for name, content in targets.items():
            save_json(tmp / name, [_renumber_field(t, "obj_id", new_id) for t in content])
        for coco_file, coco in cocos.items():  # 2D GT: its categories are the obj_ids
            save_json(tmp / coco_file, _renumber_coco(coco, new_id, src / coco_file))
        for split in splits:
            scenes = [split / f"{s:06d}" for s in list_scene_ids(split)]
            if any(not (s / "scene_gt_info.json").is_file() for s in scenes):
                from bopsurg.annotate import annotate_dataset

                annotate_dataset(
                    tmp, split.name, renderer_name=renderer_name, delta=delta, progress=progress
                )
                annotated.append(split.name)
        record = {"source": str(src.resolve()), "layout": "bop", "obj_ids": new_id}
        (tmp / RECORD_NAME).write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    instances = sum(len(v) for g in gts.values() for v in g.values())
    return RenumberReport(out, new_id, instances, annotated)


def _renumber_field(item: dict[str, Any], key: str, new_id: dict[int, int]) -> dict[str, Any]:
    """``item`` with ``item[key]`` (an obj_id) renumbered, if it has one."""
    if key not in item:
        return item
    return {**item, key: new_id.get(item[key], item[key])}


def _renumber_coco(coco: Any, new_id: dict[int, int], path: Path) -> dict[str, Any]:
    """A ``scene_gt_coco.json`` with its category ids (obj_ids) renumbered."""
    if not isinstance(coco, dict) or not isinstance(coco.get("annotations", []), list):
        raise DatasetError("expected a COCO object with an 'annotations' list", path=path)
    return {
        **coco,
        "annotations": [_renumber_field(a, "category_id", new_id) for a in coco["annotations"]],
        "categories": [
            {**c, "id": new_id.get(c["id"], c["id"]), "name": str(new_id.get(c["id"], c["id"]))}
            for c in coco.get("categories", [])
        ],
    }
