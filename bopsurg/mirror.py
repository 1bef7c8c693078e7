"""The mirror image of a BOP split: the same scenes showing a planar object's other face.

A suturing needle is symmetric through the plane of its arc, so a camera sees one of its two
faces; a face-on arc looks alike from both, with tip and tail swapped. A network trained on
one face answers the other with the face it knows (model card: the AMBF frames). Mirroring a
held-out split gives that other face on images of the same renderer, so a model's accuracy on
both faces can be compared without other data.

Geometry (camera frame, OpenCV pixel centres): the reflection ``F = diag(-1, 1, 1)`` maps a
scene onto its mirror image, and a pixel column ``u`` onto ``2 c_x - u``. An object that is its
own mirror image through a plane of its model frame (``S(x) = M x + d``, ``M = I - 2 n n^T``,
``d = 2 (n . c) n`` for a plane through ``c`` with unit normal ``n``) seen at ``(R, t)`` is
seen in the mirror image at the proper pose ``R' = F R M``, ``t' = F (t + R d)``: every model
point ``y = S(x)`` lands where the mirror puts ``R x + t``.

Images are mirrored by moving whole columns, so ``2 c_x`` must be an integer; a column whose
mirror lies outside the image (``c_x = W / 2`` loses column 0) is left empty (black, no depth).
Masks and ``scene_gt_info.json`` are computed again from the mirrored depth and poses, as
``bopsurg annotate`` does, so the mirrored split passes ``bopsurg check``.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from bopsurg.atomic import atomic_folder, check_new_folder
from bopsurg.bop.dataset import BopDataset, BopScene
from bopsurg.bop.images import load_depth, load_rgb, save_depth, save_rgb
from bopsurg.bop.meshes import ObjectModel
from bopsurg.bop.scene import CameraInfo, GtPose, save_scene_camera, save_scene_gt
from bopsurg.errors import DatasetError, ModelError
from bopsurg.plugins import DepthRenderer

F64 = NDArray[np.float64]
ImageT = TypeVar("ImageT", bound=np.generic)

#: The camera-frame reflection about the plane x = 0 (image columns about c_x).
FLIP = np.diag([-1.0, 1.0, 1.0])

#: Largest distance from a reflected model vertex to the model's nearest vertex, as a share of
#: the model's bounding-box diagonal, for the model to count as its own mirror image.
SYMMETRY_TOLERANCE = 1e-3

#: What :func:`mirror_split` records in the mirrored dataset's root.
RECORD_NAME = "bopsurg_mirror.json"


@dataclass(frozen=True)
class PlaneReflection:
    """A model's symmetry through a plane: ``x -> M x + d`` maps the model onto itself (mm)."""

    M: F64
    d: F64

    def pose(self, R: F64, t: F64) -> tuple[F64, F64]:
        """The pose ``(R', t')`` at which the mirror image shows an instance seen at ``(R, t)``
        (R row-major 3x3, t in mm); a proper rotation."""
        return FLIP @ R @ self.M, FLIP @ (t + R @ self.d)


def plane_reflection(
    model: ObjectModel, normal: ArrayLike, *, name: str = "model"
) -> PlaneReflection:
    """The reflection through the plane of normal ``normal`` (model frame) that maps ``model``
    onto itself; the plane passes through the vertices' centroid, which a symmetric model's
    plane contains.

    Raises:
        ModelError: ``normal`` is not a direction, or the model is not its own mirror image
            through that plane.
    """
    n = np.asarray(normal, dtype=np.float64).reshape(-1)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
        raise ModelError(f"{name}: plane_normal must be a 3-vector, got {normal!r}")
    n = n / np.linalg.norm(n)
    v = np.asarray(model.pts, dtype=np.float64)
    M = np.eye(3) - 2.0 * np.outer(n, n)  # noqa: N806  (the docs' symbol)
    d = 2.0 * float(n @ v.mean(axis=0)) * n
    gap = float(cKDTree(v).query(v @ M.T + d)[0].max())
    diagonal = float(np.linalg.norm(np.ptp(v, axis=0)))
    if gap > SYMMETRY_TOLERANCE * diagonal:
        raise ModelError(
            f"{name}: not its own mirror image through the plane of normal {n.round(4).tolist()} "
            f"(a reflected vertex lies {gap:.3g} mm from the model); a mirror would show "
            "another object"
        )
    return PlaneReflection(M, d)


def object_reflection(dataset: BopDataset, obj_id: int) -> PlaneReflection:
    """The reflection through the plane ``plane_normal`` (``models_info.json``) of object
    ``obj_id`` that maps its model onto itself.

    Raises:
        DatasetError: The object has no ``plane_normal``.
        ModelError: The model is not its own mirror image through that plane.
    """
    normal = dataset.models_info.get(obj_id, {}).get("plane_normal")
    if normal is None:
        raise DatasetError(
            f"obj_id {obj_id} has no plane_normal: a mirror needs the plane the object is "
            "symmetric about",
            path=dataset.models_dir / "models_info.json",
        )
    return plane_reflection(dataset.model(obj_id), normal, name=f"obj_id {obj_id}")


def mirror_columns(width: int, cx: float) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """For each column ``u'`` of the mirrored image, the source column ``2 c_x - u'`` and
    whether it lies inside the image.

    Raises:
        DatasetError: ``2 c_x`` is not an integer (the mirror would resample pixels).
    """
    two_cx = 2.0 * float(cx)
    if abs(two_cx - round(two_cx)) > 1e-6:
        raise DatasetError(
            f"a pixel-exact mirror needs 2 c_x to be an integer, got c_x = {cx}", field="cam_K"
        )
    src = round(two_cx) - np.arange(width, dtype=np.int64)
    inside = (src >= 0) & (src < width)
    return np.clip(src, 0, width - 1), inside


def _mirror_image(image: NDArray[ImageT], cx: float) -> NDArray[ImageT]:
    """``image`` (H, W[, C]) mirrored about column ``cx``; columns mirrored from outside: 0."""
    cols, inside = mirror_columns(image.shape[1], cx)
    out = image[:, cols].copy()
    out[:, ~inside] = 0
    return out


@dataclass(frozen=True)
class MirrorReport:
    """What :func:`mirror_split` wrote."""

    out: Path
    images: int
    instances: int


def _mirror_scene(
    scene: BopScene, dst: Path, reflection: Callable[[int], PlaneReflection]
) -> dict[int, list[GtPose]]:
    """Write the mirror image of one scene into ``dst``: RGB and depth mirrored column for
    column, the cameras (K, depth scale; no world pose) and the mirrored GT poses, which are
    returned (image id → instances)."""
    cams: dict[int, CameraInfo] = {}
    gts: dict[int, list[GtPose]] = {}
    for im_id in scene.im_ids:
        cam = scene.camera[im_id]
        cx = float(cam.K[0, 2])
        rgb_path = scene.rgb_path(im_id)
        save_rgb(dst / "rgb" / rgb_path.name, _mirror_image(load_rgb(rgb_path), cx))
        depth_path = scene.depth_path(im_id)
        if depth_path.is_file():
            depth = _mirror_image(load_depth(depth_path), cx)
            save_depth(dst / "depth" / depth_path.name, depth)
        cams[im_id] = CameraInfo(cam.K, cam.depth_scale, extra=cam.extra)
        gts[im_id] = [
            GtPose(g.obj_id, *reflection(g.obj_id).pose(g.R, g.t), extra=g.extra)
            for g in scene.gt.get(im_id, [])
        ]
    save_scene_camera(dst / "scene_camera.json", cams)
    save_scene_gt(dst / "scene_gt.json", gts)
    return gts


def mirror_split(
    root: str | Path,
    out: str | Path,
    split: str = "test",
    *,
    delta: float = 1.0,
    renderer: DepthRenderer | None = None,
    renderer_name: str | None = None,
    progress: bool = True,
) -> MirrorReport:
    """Write ``out``, a BOP dataset holding the mirror image of ``split`` of ``root``.

    Every object with GT must be its own mirror image through the plane ``plane_normal`` of
    its ``models_info.json`` entry (the needle is). Root files (``camera.json``, targets) and
    model folders are copied; RGB and depth are mirrored column for column; ``scene_gt.json``
    gets the mirrored poses; ``scene_camera.json`` keeps K and the depth scale and drops the
    world-to-camera pose (the mirrored world is another world); masks and gt_info are
    annotated again from the mirrored depth.

    Args:
        root: Dataset root.
        out: The dataset folder to create; it must not exist yet (or be empty).
        split: Split folder name.
        delta: Visibility tolerance of the masks, mm (``bopsurg generate`` uses 1).
        renderer: Depth renderer for the masks; default: the plugin ``renderer_name``.
        renderer_name: Depth renderer plugin name (default: the first installed).
        progress: Show progress bars.

    Raises:
        DatasetError: Bad input (nothing is written then), ``out`` not empty, 2 c_x not an
            integer, an object without ``plane_normal``.
        ModelError: An object is not its own mirror image through that plane.
    """
    from bopsurg.annotate import annotate_dataset

    root, out = Path(root), Path(out)
    check_new_folder(out)
    ds = BopDataset(root, split)
    reflections: dict[int, PlaneReflection] = {}

    def reflection(obj_id: int) -> PlaneReflection:
        if obj_id not in reflections:
            reflections[obj_id] = object_reflection(ds, obj_id)
        return reflections[obj_id]

    if renderer is None:
        from bopsurg.plugins import load_plugin

        renderer = load_plugin("renderer", renderer_name)()
    images = instances = 0
    with atomic_folder(out) as tmp:
        for f in root.iterdir():
            if f.is_file() and f.suffix == ".json":
                shutil.copyfile(f, tmp / f.name)
            elif f.is_dir() and f.name.startswith("models"):
                shutil.copytree(f, tmp / f.name)
        for scene in ds.iter_scenes():
            gts = _mirror_scene(scene, tmp / split / scene.scene_dir.name, reflection)
            images += len(gts)
            instances += sum(len(g) for g in gts.values())
        annotate_dataset(tmp, split, renderer=renderer, delta=delta, progress=progress)
        record = {"source": str(root.resolve()), "split": split, "delta_mm": delta}
        (tmp / RECORD_NAME).write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    return MirrorReport(out, images, instances)
