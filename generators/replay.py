"""Replay one recording from one drawn viewpoint into one BOP scene, resumably.

A *replay* (bag b, replay r) is the unit of work: it becomes BOP scene
``scene_id = b × replays + r + 1`` and depends only on its :class:`ReplayUnit` (bag path,
indices, the dataset seed and the settings), so units run in any order, in any process, and
give the same bytes. Every random choice of a unit comes from
``numpy.random.SeedSequence([seed, b, r])`` and is written into the scene's
``bopsurg_scene.json``.

Per frame (one every ``period`` seconds of the recording) the backend renders RGB, depth and
the instance map; every annotated object's amodal depth is rendered alone on BOP's 3× canvas;
masks and scene_gt_info follow the reference toolkit's rules (:mod:`bopsurg.visibility`) on the
depth *as saved* (uint16 × depth_scale), so ``bopsurg annotate`` on the written files gives
the same pixels and counts. Frames whose needle ``visib_fract`` is below ``min_visib`` are
dropped.

Crash safety: images are written atomically first, then the scene's JSON files, then the
progress record ``bopsurg_scene.json`` (``next_frame``), each by temp file + rename. A killed
run restarts a scene at its recorded ``next_frame``; frames are a pure function of the unit,
so the result is byte-identical to an uninterrupted run.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from bopsurg._version import __version__
from bopsurg.atomic import remove_stale_temporaries, write_text
from bopsurg.bop.images import save_depth, save_mask, save_rgb
from bopsurg.bop.jsonio import load_json
from bopsurg.bop.meshes import ObjectModel, load_ply
from bopsurg.bop.scene import (
    CameraInfo,
    GtInfo,
    GtPose,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from bopsurg.errors import InputError
from bopsurg.generators.backend import NEEDLE, CameraSpec, RenderBackend, SceneState
from bopsurg.generators.kinematics import ecm_camera_pose
from bopsurg.generators.viewpoints import ReplayDraw, draw_replay, light_in_world
from bopsurg.geometry import intrinsics_from_fov
from bopsurg.plugins import DepthRenderer
from bopsurg.visibility import instance_visibility

log = logging.getLogger(__name__)

#: Default intrinsics: vertical FOV 1.2 rad at 640×480 (the simulator's endoscope).
DEFAULT_WIDTH, DEFAULT_HEIGHT = 640, 480
DEFAULT_K = tuple(
    tuple(row) for row in intrinsics_from_fov(DEFAULT_WIDTH, DEFAULT_HEIGHT, 1.2).tolist()
)

SCENE_RECORD = "bopsurg_scene.json"


@dataclass(frozen=True)
class GenerateSettings:
    """Settings shared by every replay of a dataset (all recorded in dataset_info.json).

    Attributes:
        replays: Replays per bag.
        period: Seconds of recording between two frames.
        seed: Dataset seed.
        min_visib: Frames whose needle visib_fract is below this are dropped.
        delta_mm: Visibility tolerance δ of the bop19 rule, mm (1 mm as the paper).
        depth_scale: mm per depth PNG unit (0.1 → 0.1 mm steps, up to 6.5 m).
        width, height: Image size, px.
        K: Camera matrix, px.
        stereo: Also render the right camera (4 mm baseline) into ``rgb_right/``.
        topic_map: Topic map of the bags (name or TOML path).
        backend: Backend plugin name.
        backend_config: ``load_scene`` config of the backend.
        renderer: Depth renderer plugin for the object-alone renders (the one
            ``bopsurg annotate`` uses); ``None`` uses the backend's own.
        rgb_format: ``png`` (BOP real) or ``jpg`` (BOP pbr).
    """

    replays: int = 20
    period: float = 0.5
    seed: int = 0
    min_visib: float = 0.1
    delta_mm: float = 1.0
    depth_scale: float = 0.1
    width: int = DEFAULT_WIDTH
    height: int = DEFAULT_HEIGHT
    K: tuple[tuple[float, float, float], ...] = DEFAULT_K
    stereo: bool = False
    topic_map: str = "crtk"
    backend: str = "pybullet"
    backend_config: dict = field(default_factory=dict)
    renderer: str | None = "pybullet"
    rgb_format: str = "png"

    def to_json(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


@dataclass(frozen=True)
class ReplayUnit:
    """One replay: a bag seen from one drawn viewpoint, written as one BOP scene."""

    bag: str
    bag_index: int
    replay_index: int
    out: str
    split: str
    settings: GenerateSettings

    @property
    def scene_id(self) -> int:
        """BOP scene id (1-based, bags in command-line order)."""
        return self.bag_index * self.settings.replays + self.replay_index + 1

    @property
    def scene_dir(self) -> Path:
        """Folder of the scene."""
        return Path(self.out) / self.split / f"{self.scene_id:06d}"

    def rng(self) -> np.random.Generator:
        """The unit's own random stream."""
        seq = np.random.SeedSequence([self.settings.seed, self.bag_index, self.replay_index])
        return np.random.default_rng(seq)


@dataclass
class ReplayResult:
    """What a replay wrote."""

    scene_id: int
    frames_rendered: int
    frames_written: int
    skipped: bool = False


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file (or of all files of a ROS2 bag folder, in name order)."""
    p = Path(path)
    h = hashlib.sha256()
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    for f in files:
        with f.open("rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def frame_times(start: float, end: float, period: float) -> np.ndarray:
    """Sample times ``start + k × period`` within [start, end] (k integer, exact multiples)."""
    if period <= 0:
        raise InputError("must be > 0", field="period")
    n = int(np.floor((end - start) / period + 1e-9)) + 1
    return start + period * np.arange(max(n, 0))


def _camera(
    settings: GenerateSettings, T_world_cam: np.ndarray, *, large: bool = False
) -> CameraSpec:
    K = np.array(settings.K, dtype=np.float64)
    w, h = settings.width, settings.height
    if large:  # BOP's 3× canvas: truncated parts are rendered too
        K = K.copy()
        K[0, 2] += w
        K[1, 2] += h
        w, h = 3 * w, 3 * h
    return CameraSpec(K=K, width=w, height=h, T_world_cam=T_world_cam)


def _pose_mm(T_world_cam: np.ndarray, T_world_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Model-to-camera (R, t mm) from world poses in metres."""
    T = np.linalg.solve(T_world_cam, T_world_obj)
    return T[:3, :3].copy(), T[:3, 3] * 1000.0


class AmodalRenderer:
    """Object-alone depth from the dataset's written models, through a depth renderer plugin.

    Args:
        renderer: A :class:`bopsurg.plugins.DepthRenderer`.
        models_dir: The dataset's ``models/`` folder (read back exactly as annotate reads it).
    """

    def __init__(self, renderer: DepthRenderer, models_dir: str | Path) -> None:
        self.renderer = renderer
        self.models_dir = Path(models_dir)
        self._models: dict[int, ObjectModel] = {}

    def render(
        self, obj_id: int, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int
    ) -> np.ndarray:
        """(height, width) depth in mm of object ``obj_id`` at (R, t mm)."""
        if obj_id not in self._models:
            self._models[obj_id] = load_ply(self.models_dir / f"obj_{obj_id:06d}.ply")
        return self.renderer.render_depth(self._models[obj_id], R, t, K, width, height)


class _SceneFiles:
    """The scene's JSON state, loaded for resuming and saved after every frame."""

    def __init__(self, unit: ReplayUnit) -> None:
        self.dir = unit.scene_dir
        self.camera: dict[int, CameraInfo] = {}
        self.gt: dict[int, list[GtPose]] = {}
        self.gt_info: dict[int, list[GtInfo]] = {}
        self.record: dict = {}

    def load(self) -> None:
        # A SIGKILL can leave a writer's temporary file behind; this unit owns the folder.
        remove_stale_temporaries(self.dir)
        rec = self.dir / SCENE_RECORD
        if not rec.exists():
            return
        self.record = load_json(rec)
        if self.record.get("next_frame", 0) > 0:
            self.camera = load_scene_camera(self.dir / "scene_camera.json")
            self.gt = load_scene_gt(self.dir / "scene_gt.json")
            self.gt_info = load_scene_gt_info(self.dir / "scene_gt_info.json")

    def save(self) -> None:
        save_scene_camera(self.dir / "scene_camera.json", self.camera)
        save_scene_gt(self.dir / "scene_gt.json", self.gt)
        save_scene_gt_info(self.dir / "scene_gt_info.json", self.gt_info)
        write_text(
            self.dir / SCENE_RECORD, json.dumps(self.record, indent=2, sort_keys=True) + "\n"
        )


def run_replay(
    unit: ReplayUnit,
    backend: RenderBackend,
    recording_loader: Callable[[str, str], object],
    *,
    amodal: AmodalRenderer | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> ReplayResult:
    """Render and write one replay (resuming where a killed run stopped).

    Args:
        unit: The replay.
        backend: A backend with the scene loaded (see :meth:`RenderBackend.load_scene`).
        recording_loader: ``(bag_path, topic_map) -> Recording`` (``bags.read_bag``).
        amodal: Renders each GT instance alone from its *written* model and pose, exactly as
            ``bopsurg annotate`` will, so re-annotating the files reproduces the generator's
            masks pixel for pixel; without it the backend's own object-alone render is used.
        on_frame: Called with 1 after each rendered frame (progress).

    Returns:
        What was rendered and written.
    """
    settings = unit.settings
    files = _SceneFiles(unit)
    files.load()
    draw = draw_replay(unit.rng(), unit.replay_index)
    if files.record.get("complete"):
        return ReplayResult(unit.scene_id, 0, len(files.gt), skipped=True)
    recording = recording_loader(unit.bag, settings.topic_map)
    times = frame_times(recording.start, recording.end, settings.period)  # type: ignore[attr-defined]
    if not files.record:
        files.record = {
            "bopsurg_version": __version__,
            "bag": str(unit.bag),
            "bag_index": unit.bag_index,
            "replay_index": unit.replay_index,
            "scene_id": unit.scene_id,
            "seed": [settings.seed, unit.bag_index, unit.replay_index],
            "draw": draw.to_json(),
            "frames": len(times),
            "next_frame": 0,
            "complete": False,
        }
    start = int(files.record["next_frame"])
    T_world_cam = ecm_camera_pose(draw.ecm_joints)
    T_world_cam_r = ecm_camera_pose(draw.ecm_joints, right=True) if settings.stereo else None
    camera = _camera(settings, T_world_cam)
    camera_large = _camera(settings, T_world_cam, large=True)
    light = light_in_world(draw, T_world_cam)
    objects = backend.annotated_objects()
    K = np.array(settings.K, dtype=np.float64)
    rendered = 0
    # On resume the earlier frames are rendered again, unwritten: TinyRenderer's output can
    # depend (by a pixel) on what it rendered before, and this keeps a resumed replay
    # byte-identical to an uninterrupted one.
    for k in range(len(times)):
        warm_up = k < start
        state = recording.state_at(float(times[k]))  # type: ignore[attr-defined]
        state = SceneState(
            psm_joints=state.psm_joints,
            jaws=state.jaws,
            ecm_joints=np.asarray(draw.ecm_joints),
            needle_pose=state.needle_pose,
        )
        backend.set_state(state)
        frame = backend.render(camera, light)
        if warm_up:
            for name, obj_id in objects:  # the object-alone renderer's history too
                if amodal is not None:
                    R, t = _pose_mm(T_world_cam, backend.object_pose(name))
                    amodal.render(
                        obj_id, R, t, camera_large.K, camera_large.width, camera_large.height
                    )
                else:
                    backend.render_object_depth(name, camera_large)
            continue
        rendered += 1
        # The depth as it will be read back from the PNG: visibility is computed on it.
        depth_units = np.rint(frame.depth / settings.depth_scale)
        depth_saved = depth_units * settings.depth_scale
        poses = [_pose_mm(T_world_cam, backend.object_pose(name)) for name, _ in objects]
        visib = []
        for (name, obj_id), (R, t) in zip(objects, poses, strict=True):
            if amodal is not None:
                large = amodal.render(
                    obj_id, R, t, camera_large.K, camera_large.width, camera_large.height
                )
            else:
                large = backend.render_object_depth(name, camera_large)
            visib.append(instance_visibility(depth_saved, large, K, delta=settings.delta_mm))
        keep = visib[0].info.visib_fract >= settings.min_visib
        if keep:
            _write_frame(unit, k, frame, depth_units, visib)
            if T_world_cam_r is not None:
                right = backend.render(_camera(settings, T_world_cam_r), light)
                save_rgb(unit.scene_dir / "rgb_right" / f"{k:06d}.{settings.rgb_format}", right.rgb)
            files.camera[k] = CameraInfo(
                K=K,
                depth_scale=settings.depth_scale,
                R_w2c=np.linalg.inv(T_world_cam)[:3, :3],
                t_w2c=np.linalg.inv(T_world_cam)[:3, 3] * 1000.0,
            )
            files.gt[k] = [
                GtPose(obj_id=obj_id, R=R, t=t)
                for (_, obj_id), (R, t) in zip(objects, poses, strict=True)
            ]
            files.gt_info[k] = [v.info for v in visib]
        files.record["next_frame"] = k + 1
        if keep or k == len(times) - 1:
            files.save()
        if on_frame is not None:
            on_frame(1)
    files.record["complete"] = True
    files.save()
    return ReplayResult(unit.scene_id, rendered, len(files.gt))


def _write_frame(unit: ReplayUnit, k: int, frame, depth_units: np.ndarray, visib: list) -> None:
    """Images of one kept frame: rgb, depth, and mask/mask_visib per GT instance."""
    d = unit.scene_dir
    save_rgb(d / "rgb" / f"{k:06d}.{unit.settings.rgb_format}", frame.rgb)
    if depth_units.max(initial=0) > np.iinfo(np.uint16).max:
        raise InputError(
            f"depth exceeds the uint16 range at depth_scale {unit.settings.depth_scale}",
            field="depth_scale",
        )
    save_depth(d / "depth" / f"{k:06d}.png", depth_units)
    for gt_id, v in enumerate(visib):
        save_mask(d / "mask" / f"{k:06d}_{gt_id:06d}.png", v.mask)
        save_mask(d / "mask_visib" / f"{k:06d}_{gt_id:06d}.png", v.mask_visib)


__all__ = [
    "DEFAULT_K",
    "NEEDLE",
    "AmodalRenderer",
    "GenerateSettings",
    "ReplayDraw",
    "ReplayResult",
    "ReplayUnit",
    "file_sha256",
    "frame_times",
    "run_replay",
]
