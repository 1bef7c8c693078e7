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
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

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
from bopsurg.generators.backend import (
    NEEDLE,
    CameraSpec,
    LightSpec,
    RenderBackend,
    RenderedFrame,
)
from bopsurg.generators.domain import DEFAULT_DOMAIN, DOMAIN_REVISIONS, DomainReplay, draw_domain
from bopsurg.generators.kinematics import DEFAULT_LAYOUT, SceneLayout, ecm_camera_pose
from bopsurg.generators.recording import Recording
from bopsurg.generators.viewpoints import ReplayDraw, light_in_world
from bopsurg.geometry import intrinsics_from_fov
from bopsurg.plugins import DepthRenderer
from bopsurg.visibility import InstanceVisibility, instance_visibility, large_canvas

log = logging.getLogger(__name__)

#: Default intrinsics: vertical FOV 1.2 rad at 640×480 (the simulator's endoscope).
DEFAULT_WIDTH, DEFAULT_HEIGHT = 640, 480
DEFAULT_K = tuple(
    tuple(row) for row in intrinsics_from_fov(DEFAULT_WIDTH, DEFAULT_HEIGHT, 1.2).tolist()
)

SCENE_RECORD = "bopsurg_scene.json"


#: Settings added after datasets were generated: recorded only when not at these defaults, so
#: those datasets still resume.
_NEW_DEFAULTS: dict[str, Any] = {"needle_holder": "auto", "psm_tool": None, "joint_source": None}


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
        backend: Backend plugin name (entry-point group ``bopsurg.render_backends``).
        backend_config: The scene (keys :data:`~bopsurg.generators.backend.SCENE_KEYS`, for
            :meth:`RenderBackend.load_scene`) and the backend's own options (every other
            key, for its factory); see :func:`~bopsurg.generators.backend.split_backend_config`.
        renderer: Depth renderer plugin for the object-alone renders (the one
            ``bopsurg annotate`` uses); ``None`` uses the backend's own.
        rgb_format: ``png`` (BOP real) or ``jpg`` (BOP pbr).
        domain: Randomisation profile (:data:`~bopsurg.generators.domain.DOMAINS`).
        needle_holder: For recordings of real robots (no needle pose): the arm holding the
            needle, ``auto`` (the recorded arm, or the first) or ``none`` (on the tissue).
        psm_tool: For recordings of real robots: the dVRK tool whose kinematics pose the
            arms (:data:`~bopsurg.generators.dvrk_tools.TOOL_NAMES`); None: the Large Needle
            Driver 400006.
        joint_source: ``measured`` or ``setpoint``: which joint topics to read; None: the
            first the topic map finds.
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
    backend_config: dict[str, Any] = field(default_factory=dict)
    renderer: str | None = "pybullet"
    rgb_format: str = "png"
    domain: str = DEFAULT_DOMAIN
    needle_holder: str = "auto"
    psm_tool: str | None = None
    joint_source: str | None = None

    def to_json(self) -> dict[str, Any]:
        """JSON-ready form: ``domain`` only when not the default (as before it existed), then
        with the profile's ``domain_revision`` (see
        :data:`~bopsurg.generators.domain.DOMAIN_REVISIONS`), so resuming compares it too;
        the real-recording options likewise only when set."""
        out = asdict(self)
        for key, default in _NEW_DEFAULTS.items():
            if out[key] == default:
                del out[key]
        if self.domain == DEFAULT_DOMAIN:
            del out["domain"]
        elif self.domain in DOMAIN_REVISIONS:
            out["domain_revision"] = DOMAIN_REVISIONS[self.domain]
        return out


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
        K, w, h = large_canvas(K, w, h)
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
        self.record: dict[str, Any] = {}

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


@dataclass(frozen=True)
class _View:
    """The drawn viewpoint of a replay: cameras (image, 3× canvas, right eye) and light."""

    T_world_cam: np.ndarray
    camera: CameraSpec
    canvas: CameraSpec
    right: CameraSpec | None
    light: LightSpec

    @classmethod
    def of(
        cls,
        settings: GenerateSettings,
        draw: ReplayDraw,
        offset: np.ndarray | None = None,
        layout: SceneLayout | None = None,
    ) -> _View:
        """The views of a draw; ``offset`` (4×4 ``T_cam_newcam``) moves the stereo rig;
        ``layout`` places the endoscope (default: the default layout)."""
        layout = layout or DEFAULT_LAYOUT
        T_left = ecm_camera_pose(draw.ecm_joints, layout)
        T_world_cam = T_left if offset is None else T_left @ offset
        right = None
        if settings.stereo:  # the rig moves as one: the right eye keeps its pose to the left
            T_right = ecm_camera_pose(draw.ecm_joints, layout, right=True)
            if offset is not None:
                T_right = T_world_cam @ np.linalg.solve(T_left, T_right)
            right = _camera(settings, T_right)
        return cls(
            T_world_cam=T_world_cam,
            camera=_camera(settings, T_world_cam),
            canvas=_camera(settings, T_world_cam, large=True),
            right=right,
            light=light_in_world(draw, T_world_cam),
        )


def _new_record(
    unit: ReplayUnit, draw: ReplayDraw, frames: int, dressing: DomainReplay | None = None
) -> dict[str, Any]:
    """The progress record of a replay that has not started."""
    settings = unit.settings
    record = {
        "bopsurg_version": __version__,
        "bag": str(unit.bag),
        "bag_index": unit.bag_index,
        "replay_index": unit.replay_index,
        "scene_id": unit.scene_id,
        "seed": [settings.seed, unit.bag_index, unit.replay_index],
        "draw": draw.to_json(),
        "frames": frames,
        "next_frame": 0,
        "complete": False,
    }
    if dressing is not None:  # absent for the default profile, as before
        record["domain"] = {
            **dressing.domain.to_json(),
            "camera_offset_m": dressing.camera_offset[:3, 3].tolist(),
        }
        if dressing.domain.orbit is not None:  # the orbit turns the camera too
            record["domain"]["camera_offset_R"] = dressing.camera_offset[:3, :3].tolist()
    return record


def _amodal_depths(
    backend: RenderBackend,
    amodal: AmodalRenderer | None,
    objects: list[tuple[str, int]],
    poses: list[tuple[np.ndarray, np.ndarray]],
    canvas: CameraSpec,
) -> list[np.ndarray]:
    """Each annotated object's depth alone (mm) on the 3× canvas, in ``objects`` order."""
    if amodal is None:
        return [backend.render_object_depth(name, canvas) for name, _ in objects]
    return [
        amodal.render(obj_id, R, t, canvas.K, canvas.width, canvas.height)
        for (_, obj_id), (R, t) in zip(objects, poses, strict=True)
    ]


def run_replay(
    unit: ReplayUnit,
    backend: RenderBackend,
    recording_loader: Callable[[str, str], Recording],
    *,
    amodal: AmodalRenderer | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> ReplayResult:
    """Render and write one replay (resuming where a killed run stopped).

    Args:
        unit: The replay.
        backend: A backend with the scene loaded (see :meth:`RenderBackend.load_scene`).
        recording_loader: ``(bag_path, topic_map) -> Recording`` (``bag_reader.read_bag``);
            a staged recording's ``layout`` places the endoscope (and must be the backend's).
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
    draw, domain = draw_domain(unit.rng(), unit.replay_index, settings.domain)
    if files.record.get("complete"):
        return ReplayResult(unit.scene_id, 0, len(files.gt), skipped=True)
    recording = recording_loader(unit.bag, settings.topic_map)
    times = frame_times(recording.start, recording.end, settings.period)
    layout = recording.layout
    view = _View.of(settings, draw, layout=layout)
    dressing = None
    if domain is not None:  # --domain other than paper: move the camera, dress the scene
        needle = [recording.state_at(float(t)).needle_pose[:3, 3] for t in times]
        dressing = DomainReplay(domain, backend, np.array(needle), view.T_world_cam)
        view = _View.of(settings, draw, dressing.camera_offset, layout)
    files.record = files.record or _new_record(unit, draw, len(times), dressing)
    start = int(files.record["next_frame"])
    objects = backend.annotated_objects()
    rendered = 0
    # On resume the earlier frames are rendered again, unwritten: TinyRenderer's output can
    # depend (by a pixel) on what it rendered before, and this keeps a resumed replay
    # byte-identical to an uninterrupted one (the object-alone renderer's history too).
    for k in range(len(times)):
        state = recording.state_at(float(times[k]))
        backend.set_state(replace(state, ecm_joints=np.asarray(draw.ecm_joints)))
        if dressing is not None:
            dressing.frame(float(times[k]), backend.object_pose(NEEDLE))
        frame = backend.render(view.camera, view.light)
        poses = [_pose_mm(view.T_world_cam, backend.object_pose(name)) for name, _ in objects]
        large = _amodal_depths(backend, amodal, objects, poses, view.canvas)
        if k < start:
            continue
        rendered += 1
        keep = _keep_frame(unit, k, frame, large, backend, view, files, objects, poses)
        files.record["next_frame"] = k + 1
        if keep or k == len(times) - 1:
            files.save()
        if on_frame is not None:
            on_frame(1)
    files.record["complete"] = True
    files.save()
    return ReplayResult(unit.scene_id, rendered, len(files.gt))


def _keep_frame(
    unit: ReplayUnit,
    k: int,
    frame: RenderedFrame,
    large: list[np.ndarray],
    backend: RenderBackend,
    view: _View,
    files: _SceneFiles,
    objects: list[tuple[str, int]],
    poses: list[tuple[np.ndarray, np.ndarray]],
) -> bool:
    """Write frame ``k`` and its annotations if the needle is visible enough; True if kept."""
    settings = unit.settings
    K = np.array(settings.K, dtype=np.float64)
    # The depth as it will be read back from the PNG: visibility is computed on it.
    depth_units = np.rint(frame.depth / settings.depth_scale)
    depth_saved = depth_units * settings.depth_scale
    visib = [instance_visibility(depth_saved, d, K, delta=settings.delta_mm) for d in large]
    if visib[0].info.visib_fract < settings.min_visib:
        return False
    _write_frame(unit, k, frame, depth_units, visib)
    if view.right is not None:
        right = backend.render(view.right, view.light)
        save_rgb(unit.scene_dir / "rgb_right" / f"{k:06d}.{settings.rgb_format}", right.rgb)
    T_cam_world = np.linalg.inv(view.T_world_cam)
    files.camera[k] = CameraInfo(
        K=K,
        depth_scale=settings.depth_scale,
        R_w2c=T_cam_world[:3, :3],
        t_w2c=T_cam_world[:3, 3] * 1000.0,
    )
    files.gt[k] = [
        GtPose(obj_id=obj_id, R=R, t=t) for (_, obj_id), (R, t) in zip(objects, poses, strict=True)
    ]
    files.gt_info[k] = [v.info for v in visib]
    return True


def _write_frame(
    unit: ReplayUnit,
    k: int,
    frame: RenderedFrame,
    depth_units: np.ndarray,
    visib: list[InstanceVisibility],
) -> None:
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
