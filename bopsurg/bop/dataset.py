"""Lazy access to a BOP dataset folder: scenes, annotations, images, models and targets.

Nothing is read until asked for, and what is read is cached: a scene's
``scene_camera.json`` is parsed on first access to :attr:`BopScene.camera`, a model on
first :meth:`BopDataset.model` call. Images are never cached (the caller decides), only their
paths are resolved.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from bopsurg.bop.images import image_size as _image_size
from bopsurg.bop.jsonio import load_json, save_json
from bopsurg.bop.meshes import ObjectModel, load_models_info, load_ply
from bopsurg.bop.registry import VSD_DELTA_MM, DatasetSpec, Stream, recognise
from bopsurg.bop.scene import (
    CameraInfo,
    GtInfo,
    GtPose,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
)
from bopsurg.bop.targets import (
    MIN_VISIB,
    TARGETS_BOP24_FILENAME,
    ImageTarget,
    Target,
    enumerate_image_targets,
    enumerate_targets,
    load_image_targets,
    load_targets,
)
from bopsurg.errors import DatasetError

logger = logging.getLogger(__name__)

#: Suffixes tried, in order, for colour/gray images and depth images.
RGB_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif")
DEPTH_SUFFIXES = (".png", ".tif")


def scene_dir(root: str | Path, split: str, scene_id: int) -> Path:
    """The folder of a scene: ``root/split/{scene_id:06d}`` (``split`` may carry a type,
    e.g. ``"train_pbr"``)."""
    return Path(root) / split / f"{int(scene_id):06d}"


def model_path(models_dir: str | Path, obj_id: int) -> Path:
    """The model file of an object: ``models_dir/obj_{obj_id:06d}.ply``."""
    return Path(models_dir) / f"obj_{int(obj_id):06d}.ply"


def _is_scene_name(name: str) -> bool:
    return name.isascii() and name.isdigit() and f"{int(name):06d}" == name


def scene_stream(scene_dir: Path, spec: DatasetSpec | None, wanted: str | None) -> Stream | None:
    """The sensor stream a scene is read through: ``wanted`` if given; none when the scene
    has the single-stream files (``scene_gt.json`` or ``scene_camera.json``); else the first
    of the dataset's streams with a ``scene_gt_{stream}.json`` or ``scene_camera_{stream}.json``
    (see :mod:`bopsurg.bop.registry`).

    Raises:
        DatasetError: ``wanted`` is not a stream of the dataset.
    """
    if spec is None or not spec.streams:
        if wanted is not None:
            raise DatasetError(f"stream {wanted!r}: not a registered multi-stream dataset")
        return None
    if wanted is not None:
        try:
            return spec.stream(wanted)
        except KeyError as err:
            raise DatasetError(str(err.args[0]), path=scene_dir) from None
    if (scene_dir / "scene_gt.json").exists() or (scene_dir / "scene_camera.json").exists():
        return None
    for stream in spec.streams:
        names = (f"scene_gt_{stream.name}.json", f"scene_camera_{stream.name}.json")
        if any((scene_dir / n).exists() for n in names):
            return stream
    return None


def list_scene_ids(split_dir: str | Path) -> list[int]:
    """Sorted ids of the scene folders (6-digit names) of a split folder."""
    d = Path(split_dir)
    return sorted(int(p.name) for p in d.iterdir() if p.is_dir() and _is_scene_name(p.name))


class BopScene:
    """One scene of a split; annotation files are loaded on first access and cached.

    Args:
        scene_id: The scene id.
        scene_dir: Its folder.
        stream: The sensor stream of a multi-stream layout (files ``scene_gt_{stream}.json``
            ..., its image folders), or None for the single-stream layout.
    """

    def __init__(self, scene_id: int, scene_dir: Path, stream: Stream | None = None) -> None:
        self.scene_id = int(scene_id)
        self.scene_dir = Path(scene_dir)
        self.stream = stream
        self._suffix = "" if stream is None else f"_{stream.name}"

    @property
    def camera_path(self) -> Path:
        """``scene_camera.json`` (``scene_camera_{stream}.json``)."""
        return self.scene_dir / f"scene_camera{self._suffix}.json"

    @property
    def gt_path(self) -> Path:
        """``scene_gt.json`` (``scene_gt_{stream}.json``)."""
        return self.scene_dir / f"scene_gt{self._suffix}.json"

    @property
    def gt_info_path(self) -> Path:
        """``scene_gt_info.json`` (``scene_gt_info_{stream}.json``)."""
        return self.scene_dir / f"scene_gt_info{self._suffix}.json"

    @property
    def image_dirs(self) -> tuple[str, ...]:
        """Names of the folders its colour/grey images may be in (``rgb``, ``gray``)."""
        return ("rgb", "gray") if self.stream is None else self.stream.images

    @property
    def depth_dir(self) -> str | None:
        """Name of its depth folder (``depth``), None for a stream without depth."""
        return "depth" if self.stream is None else self.stream.depth

    def __repr__(self) -> str:
        return f"BopScene({self.scene_id}, {str(self.scene_dir)!r})"

    @functools.cached_property
    def camera(self) -> dict[int, CameraInfo]:
        """Image id → camera (``scene_camera.json``)."""
        return load_scene_camera(self.camera_path)

    @functools.cached_property
    def gt(self) -> dict[int, list[GtPose]]:
        """Image id → GT instances in gt_id order (``scene_gt.json``)."""
        return load_scene_gt(self.gt_path)

    @functools.cached_property
    def gt_info(self) -> dict[int, list[GtInfo]] | None:
        """Image id → GT meta information (``scene_gt_info.json``), None if the file is absent."""
        path = self.gt_info_path
        if not path.exists():
            return None
        return load_scene_gt_info(path)

    @property
    def im_ids(self) -> list[int]:
        """Sorted image ids: those of ``scene_camera.json`` (every image has a camera entry),
        or of ``scene_gt.json`` when the scene has no camera file."""
        if self.camera_path.exists() or "camera" in self.__dict__:
            return sorted(self.camera)
        return sorted(self.gt)

    def _find(self, folders: tuple[str, ...], stem: str, suffixes: tuple[str, ...]) -> Path:
        for folder in folders:
            for suffix in suffixes:
                path = self.scene_dir / folder / f"{stem}{suffix}"
                if path.exists():
                    return path
        return self.scene_dir / folders[0] / f"{stem}{suffixes[0]}"

    def rgb_path(self, im_id: int) -> Path:
        """The colour image of ``im_id``: ``rgb/{im_id:06d}`` with suffix .png, .jpg, .jpeg or
        .tif, whichever exists, else the same in ``gray/`` (a stream: its image folders);
        ``rgb/{im_id:06d}.png`` if none exists."""
        return self._find(self.image_dirs, f"{int(im_id):06d}", RGB_SUFFIXES)

    def depth_path(self, im_id: int) -> Path:
        """The depth image of ``im_id``: ``depth/{im_id:06d}.png`` (or .tif if that exists)."""
        return self._find((self.depth_dir or "depth",), f"{int(im_id):06d}", DEPTH_SUFFIXES)

    def mask_path(self, im_id: int, gt_id: int) -> Path:
        """The full-silhouette mask ``mask/{im_id:06d}_{gt_id:06d}.png`` (``mask_{stream}/``)."""
        return self.scene_dir / f"mask{self._suffix}" / f"{int(im_id):06d}_{int(gt_id):06d}.png"

    def mask_visib_path(self, im_id: int, gt_id: int) -> Path:
        """The visible-part mask ``mask_visib/{im_id:06d}_{gt_id:06d}.png``
        (``mask_visib_{stream}/``)."""
        return (
            self.scene_dir / f"mask_visib{self._suffix}" / f"{int(im_id):06d}_{int(gt_id):06d}.png"
        )


class BopDataset:
    """A BOP dataset folder, read lazily.

    Args:
        root: The dataset folder (holding ``models*/`` and the split folders).
        split: ``"test"``, ``"train"``, ``"val"`` ...
        split_type: Optional split type; the split folder is ``root/{split}_{split_type}``
            (e.g. ``train_pbr``).
        model_type: Optional model type; models are then read from ``models_{model_type}``.
            Otherwise ``models_eval/`` (the evaluation models the reference uses) if it
            exists, else ``models/``.
        name: A standard BOP dataset's name (:mod:`bopsurg.bop.registry`) whose defaults
            apply; None: the one the folder's name matches, if any; ``"none"``: no defaults.
            The defaults: the split type of a split named without one (T-LESS ``test`` →
            ``test_primesense``), the camera file, the image size, VSD's δ, the streams of a
            multi-stream layout, BOP24's estimates per image.
        stream: The sensor stream to read in a multi-stream layout (default: per scene, the
            first of the dataset's evaluated streams it has).

    Raises:
        DatasetError: ``root`` or the split folder does not exist, or ``name`` is not a
            registered dataset. A missing models folder is reported when models are first
            needed.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "test",
        *,
        split_type: str | None = None,
        model_type: str | None = None,
        name: str | None = None,
        stream: str | None = None,
    ) -> None:
        self.root = Path(root)
        self.split = split
        self.model_type = model_type
        if not self.root.is_dir():
            raise DatasetError("dataset folder not found", path=self.root)
        try:
            #: The registered dataset's defaults, or None (a custom dataset).
            self.spec = recognise(self.root, name)
        except KeyError as err:
            raise DatasetError(str(err.args[0]), path=self.root) from None
        if self.spec is not None:
            split_type = self.spec.split_type(split, split_type, self.root)
        self.split_type = split_type
        self.stream = stream
        folder = split if split_type is None else f"{split}_{split_type}"
        self.split_dir = self.root / folder
        if not self.split_dir.is_dir():
            splits = sorted(p.name for p in self.root.iterdir() if p.is_dir())
            raise DatasetError(
                f"split folder not found (folders here: {', '.join(splits) or 'none'})",
                path=self.split_dir,
            )
        self._scenes: dict[int, BopScene] = {}
        self._models: dict[int, ObjectModel] = {}
        self._image_sizes: dict[int, tuple[int, int]] = {}

    def __repr__(self) -> str:
        return f"BopDataset({str(self.root)!r}, split={self.split_dir.name!r})"

    @functools.cached_property
    def models_dir(self) -> Path:
        """The models folder (see the class docs for how it is chosen)."""
        if self.model_type is not None:
            candidates = [f"models_{self.model_type}"]
        else:
            candidates = ["models_eval", "models"]
        for name in candidates:
            if (self.root / name).is_dir():
                return self.root / name
        raise DatasetError(
            f"models folder not found (looked for {' or '.join(candidates)})",
            path=self.root / candidates[-1],
        )

    @functools.cached_property
    def scene_ids(self) -> list[int]:
        """Sorted ids of the scene folders of the split."""
        return list_scene_ids(self.split_dir)

    def scene(self, scene_id: int) -> BopScene:
        """The scene ``scene_id`` (cached).

        Raises:
            DatasetError: No such scene folder.
        """
        sid = int(scene_id)
        if sid not in self._scenes:
            d = scene_dir(self.root, self.split_dir.name, sid)
            if not d.is_dir():
                raise DatasetError(f"no scene {sid} in this split", path=d)
            self._scenes[sid] = BopScene(sid, d, scene_stream(d, self.spec, self.stream))
        return self._scenes[sid]

    def iter_scenes(self) -> Iterator[BopScene]:
        """The scenes in id order."""
        for sid in self.scene_ids:
            yield self.scene(sid)

    @functools.cached_property
    def models_info(self) -> dict[int, dict[str, Any]]:
        """obj_id → ``models_info.json`` entry of the models folder."""
        return load_models_info(self.models_dir / "models_info.json")

    @property
    def obj_ids(self) -> list[int]:
        """Sorted object ids of ``models_info.json``."""
        return sorted(self.models_info)

    def model_path(self, obj_id: int) -> Path:
        """``models_dir/obj_{obj_id:06d}.ply``."""
        return model_path(self.models_dir, obj_id)

    def model(self, obj_id: int) -> ObjectModel:
        """The model of ``obj_id`` (loaded once, then cached).

        Raises:
            DatasetError: No model file for ``obj_id``.
            ModelError: The file is malformed.
        """
        oid = int(obj_id)
        if oid not in self._models:
            path = self.model_path(oid)
            if not path.is_file():
                raise DatasetError(
                    f"unknown obj_id {oid}: no {path.name} in the models folder",
                    path=self.models_dir,
                )
            self._models[oid] = load_ply(path)
        return self._models[oid]

    def targets(self, filename: str = "test_targets_bop19.json") -> list[Target]:
        """The evaluation targets of ``root/filename``.

        If the file does not exist they are enumerated from the GT and GT info of all scenes
        (``visib_fract >= 0.1``, as the reference script does) and a warning is logged.

        Raises:
            DatasetError: Malformed targets file, or (when enumerating) missing GT files.
        """
        path = self.root / filename
        if path.exists():
            return load_targets(path)
        logger.warning(
            "%s not found: enumerating targets from the GT (visib_fract >= %s)", path, MIN_VISIB
        )
        gts, infos = {}, {}
        for scene in self.iter_scenes():
            info = scene.gt_info
            if info is None:
                raise DatasetError(
                    "scene_gt_info.json is missing, needed to enumerate the targets",
                    path=scene.scene_dir / "scene_gt_info.json",
                )
            gts[scene.scene_id] = scene.gt
            infos[scene.scene_id] = info
        return enumerate_targets(gts, infos, MIN_VISIB)

    def image_targets(self, filename: str = TARGETS_BOP24_FILENAME) -> list[ImageTarget]:
        """The 6D-detection targets of ``root/filename`` (images), or, if the file does not
        exist, every image with GT (logged).

        Raises:
            DatasetError: Malformed targets file.
        """
        path = self.root / filename
        if path.exists():
            return load_image_targets(path)
        logger.info("%s not found: evaluating every image with GT", path)
        return enumerate_image_targets({s.scene_id: s.gt for s in self.iter_scenes()})

    @property
    def vsd_delta_mm(self) -> float:
        """VSD's visibility tolerance δ for this dataset, mm (ITODD 5, else 15)."""
        return VSD_DELTA_MM if self.spec is None else self.spec.vsd_delta_mm

    @property
    def evaluates_vsd(self) -> bool:
        """Whether the reference evaluates VSD on this dataset (not on HOT3D, IPD, ...)."""
        return self.spec is None or self.spec.vsd

    @property
    def max_estimates_per_image(self) -> int:
        """Estimates per image the BOP24 evaluation keeps (100; 200 for XYZ-IBD)."""
        return 100 if self.spec is None else self.spec.max_estimates_per_image

    @property
    def camera_file(self) -> Path:
        """The dataset-level camera file: ``camera.json``, or the registered dataset's
        (``camera_primesense.json`` for T-LESS and HB, ``camera_uw.json`` for YCB-V)."""
        name = "camera.json" if self.spec is None else self.spec.camera_file(self.split_type)
        return self.root / name

    @functools.cached_property
    def camera_json(self) -> dict[str, Any] | None:
        """The content of the camera file (:attr:`camera_file`: ``fx, fy, cx, cy, width,
        height, depth_scale``), or None if absent."""
        path = self.camera_file
        if not path.exists():
            return None
        content = load_json(path)
        if not isinstance(content, dict):
            raise DatasetError("expected a JSON object", path=path)
        return content

    def image_size(self, scene_id: int | None = None) -> tuple[int, int]:
        """Image size (width, height) in px.

        A registered dataset's size for the split type and the scene's stream (what the
        reference scales MSPD by); else from the camera file if it has ``width`` and
        ``height``, else from the first image of ``scene_id`` (default: the first scene).

        Raises:
            DatasetError: No camera file size and no image to measure.
        """
        if self.spec is not None:
            stream = None
            if self.spec.streams and (scene_id is not None or self.scene_ids):
                found = self.scene(self.scene_ids[0] if scene_id is None else scene_id).stream
                stream = None if found is None else found.name
            return self.spec.image_size(self.split_type, stream, self.split)
        cam = self.camera_json
        if cam is not None and "width" in cam and "height" in cam:
            try:
                return int(cam["width"]), int(cam["height"])
            except (TypeError, ValueError):
                raise DatasetError(
                    "width and height must be integers", path=self.camera_file
                ) from None
        if scene_id is None:
            if not self.scene_ids:
                raise DatasetError("no scene folders in this split", path=self.split_dir)
            scene_id = self.scene_ids[0]
        sid = int(scene_id)
        if sid not in self._image_sizes:
            scene = self.scene(sid)
            im_ids = scene.im_ids
            if not im_ids:
                raise DatasetError("scene has no images", path=scene.scene_dir)
            self._image_sizes[sid] = _image_size(scene.rgb_path(im_ids[0]))
        return self._image_sizes[sid]


def save_camera_json(
    root: str | Path, K: Any, width: int, height: int, depth_scale: float | None = None
) -> None:
    """Write the dataset's ``camera.json`` (fx, fy, cx, cy, width, height, depth_scale)."""
    cam: dict[str, Any] = {
        "cx": float(K[0][2]),
        "cy": float(K[1][2]),
        "fx": float(K[0][0]),
        "fy": float(K[1][1]),
        "height": int(height),
        "width": int(width),
    }
    if depth_scale is not None:
        cam["depth_scale"] = float(depth_scale)
    save_json(Path(root) / "camera.json", cam)
