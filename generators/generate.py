"""``bopsurg generate``: bags × replays → a BOP dataset, in parallel worker processes.

The dataset-level files (models, camera.json, the split's ``bopsurg_generate.json`` with the
seed, settings (with ``--object-model``'s path and sha256) and bag checksums, and
``test_targets_bop19.json``) are written by the driver;
each replay writes only its own scene folder (:mod:`bopsurg.generators.replay`), so workers
never write the same file. Rerunning the same command resumes: finished scenes are skipped,
an interrupted one continues at its last recorded frame.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from bopsurg._version import __version__
from bopsurg.atomic import write_text
from bopsurg.bop.coco import write_detection_annotations
from bopsurg.bop.dataset import BopDataset, save_camera_json
from bopsurg.bop.jsonio import load_json
from bopsurg.bop.meshes import compute_model_info, save_models_info, save_ply
from bopsurg.bop.scene import load_scene_gt, load_scene_gt_info
from bopsurg.bop.targets import enumerate_targets, save_targets
from bopsurg.errors import BopsurgError, InputError
from bopsurg.executors import Executor, LocalExecutor
from bopsurg.generators.backend import (
    NEEDLE,
    BackendFactory,
    RenderBackend,
    split_backend_config,
)
from bopsurg.generators.domain import DOMAINS, profile_scene
from bopsurg.generators.kinematics import DEFAULT_LAYOUT, SceneLayout
from bopsurg.generators.object_model import NeedleModel
from bopsurg.generators.recording import Recording
from bopsurg.generators.replay import (
    AmodalRenderer,
    GenerateSettings,
    ReplayResult,
    ReplayUnit,
    file_sha256,
    frame_times,
    run_replay,
)
from bopsurg.needle import NeedleSpec, needle_keypoints
from bopsurg.plugins import load_plugin

log = logging.getLogger(__name__)

INFO_NAME = "bopsurg_generate.json"


@dataclass
class GenerateReport:
    """What a generation run did."""

    scenes: int
    scenes_skipped: int
    frames_rendered: int
    frames_written: int


def _read_bag(path: str, topic_map: str, **options: Any) -> Recording:
    from bopsurg.generators.bag_reader import read_bag

    return read_bag(path, topic_map=topic_map, **options)


def load_recording(path: str, settings: GenerateSettings) -> Recording:
    """Read a bag as ``generate`` replays it: a real robot's recording staged in the scene.

    A simulator's recording (bopsurg's own, AMBF's: the topic map's or the bag meta's say)
    is returned as read. A real dVRK's is posed with the dVRK's kinematics of
    ``settings.psm_tool`` and staged by :func:`~bopsurg.generators.staging.stage_recording`
    (its arms, the needle in ``settings.needle_holder``'s jaws, the view on its workspace).

    Raises:
        InputError: ``--psm-tool`` for a simulator's recording, an unknown tool or holder.
        BagError: The bag cannot be read (one line naming it).
    """
    from bopsurg.generators.dvrk_tools import dvrk_psm
    from bopsurg.generators.staging import stage_recording

    kinematics = None if settings.psm_tool is None else dvrk_psm(settings.psm_tool)
    options: dict[str, Any] = {}
    if settings.joint_source is not None:
        options["joint_source"] = settings.joint_source
    if kinematics is not None:
        options["kinematics"] = kinematics
    rec = _read_bag(path, settings.topic_map, **options)
    if rec.robot == "simulator":
        if settings.psm_tool is not None:
            raise InputError(
                "a simulator's recording is replayed with the simulator's kinematics; "
                "--psm-tool is for recordings of real robots",
                path=path,
            )
        return rec
    needle = settings.backend_config.get("needle")
    spec = NeedleSpec(**needle) if isinstance(needle, dict) else NeedleSpec()
    staged, how = stage_recording(
        rec, kinematics or dvrk_psm(), needle=spec, needle_holder=settings.needle_holder
    )
    log.debug("%s: staged %s", path, how)
    return staged


def make_backend(settings: GenerateSettings, layout: SceneLayout | None = None) -> RenderBackend:
    """Build the backend plugin named in the settings and load the scene into it.

    The settings' ``backend_config`` holds the scene keys
    (:data:`~bopsurg.generators.backend.SCENE_KEYS`) and the backend's own options;
    ``layout`` (a staged recording's) replaces the scene's.

    Raises:
        InputError: A scene key or backend option the backend rejects (one line).
        BopsurgError: The plugin is not installed or is not a complete render backend.
    """
    factory: BackendFactory = load_plugin("backend", settings.backend)
    try:
        scene, options = split_backend_config(settings.backend_config)
        backend = factory(options)
    except BopsurgError:
        raise  # e.g. the object model: already one line naming its file
    except (TypeError, ValueError) as err:
        raise InputError(f"backend {settings.backend!r}: {err}", field="--backend-option") from err
    if layout is not None:
        scene = replace(scene, layout=layout)
    if not isinstance(backend, RenderBackend):
        methods = [m for m in dir(RenderBackend) if not m.startswith("_")]
        missing = [m for m in methods if not callable(getattr(backend, m, None))]
        raise BopsurgError(f"backend {settings.backend!r} lacks {', '.join(missing)}")
    backend.load_scene(profile_scene(settings.domain, scene))
    return backend


def make_amodal(settings: GenerateSettings, out: str | Path) -> AmodalRenderer | None:
    """The object-alone renderer of the settings (None: the backend's own)."""
    if settings.renderer is None:
        return None
    return AmodalRenderer(load_plugin("renderer", settings.renderer)(), Path(out) / "models")


# -- the unit of work, wherever it runs ----------------------------------------------------
def _replay_unit(unit: ReplayUnit, report: Callable[[int], None]) -> ReplayResult:
    """Run one replay with a backend and renderer of its own.

    A fresh backend per replay: PyBullet's TinyRenderer output can depend, by a pixel, on
    what the same client rendered before, so sharing one across replays would make the bytes
    depend on which worker ran which replays. (Textures are cached, so this costs ~0.2 s.)
    """
    rec = load_recording(unit.bag, unit.settings)
    layout = rec.layout
    backend = make_backend(unit.settings) if layout is None else make_backend(unit.settings, layout)
    try:
        amodal = make_amodal(unit.settings, unit.out)
        return run_replay(unit, backend, lambda *_: rec, amodal=amodal, on_frame=report)
    finally:
        backend.close()


# -----------------------------------------------------------------------------------------
def resolve_object_model(
    settings: GenerateSettings,
) -> tuple[GenerateSettings, NeedleModel | None]:
    """Load, fit and place the settings' ``object_model`` (``generate --object-model``).

    :func:`generate_dataset` then says in one log line what was fitted and how the mesh was
    placed (:meth:`NeedleModel.describe`; a WARNING when its radius differs from the recorded
    needle's beyond tolerance).

    Returns:
        The settings with ``backend_config["object_model"]`` as the generation record holds
        it (``{"path": resolved, "sha256": ...}``), and the model; unchanged settings and
        None without one.

    Raises:
        BopsurgError: The mesh is missing, unreadable, not a needle or not in mm (one line).
    """
    config = settings.backend_config
    if config.get("object_model") is None:
        return settings, None
    try:
        scene, _ = split_backend_config(config)
    except BopsurgError as err:
        raise InputError(str(err), field="--object-model") from None
    except (TypeError, ValueError) as err:
        raise InputError(str(err), field="--object-model") from err
    model = scene.needle_model
    assert model is not None
    return replace(settings, backend_config={**config, "object_model": model.record()}), model


def with_recorded_needle(
    settings: GenerateSettings, needles: dict[str, dict[str, Any] | None]
) -> GenerateSettings:
    """The settings with the needle the bags were recorded for (their meta's ``needle``, e.g.
    ``record --object-model``), unless ``--needle-*`` set one or the bags used bopsurg's
    default needle (then nothing changes, so older datasets resume).

    Raises:
        InputError: The bags were recorded for different needles.
    """
    from dataclasses import asdict

    if "needle" in settings.backend_config:
        return settings
    default = asdict(NeedleSpec())
    specs = {b: {**default, **n} for b, n in needles.items() if isinstance(n, dict)}
    if not specs:
        return settings
    first = min(specs)
    other = next((b for b in sorted(specs) if specs[b] != specs[first]), None)
    if other is not None:
        raise InputError(
            f"recorded for another needle than {first} (radius {specs[other]['arc_radius']} "
            f"vs {specs[first]['arc_radius']} mm); generate such bags separately",
            path=other,
        )
    spec = specs[first]
    if spec == default:
        return settings
    log.info("the bags were recorded for needle %s", spec)
    return replace(settings, backend_config={**settings.backend_config, "needle": spec})


def _check_same_object_model(old: dict[str, Any], new: dict[str, Any], info_path: Path) -> None:
    """Refuse to resume a split generated with another needle mesh (or none)."""
    before = (old.get("settings") or {}).get("backend_config", {}).get("object_model")
    now = new.get("object_model")
    if (before or {}).get("sha256") == (now or {}).get("sha256"):
        return

    def name(m: Any) -> str:
        return f"{m['path']} (sha256 {m['sha256'][:12]}…)" if m else "none (bopsurg's needle)"

    was, is_ = name(before), name(now)
    raise InputError(
        f"this split was generated with the object model {was}, not {is_}; choose a new --out "
        "or --split (nothing was changed)",
        path=info_path,
    )


def _settings_changes(old: Any, new: Any, prefix: str = "") -> list[str]:
    """What differs between two recorded settings, one ``key: recorded → now`` per field
    (nested dicts by dotted key), so a refused resume says which option to set back."""
    if isinstance(old, dict) and isinstance(new, dict):
        keys = sorted(set(old) | set(new), key=str)
        return [c for k in keys for c in _settings_changes(old.get(k), new.get(k), f"{prefix}{k}.")]
    if old == new:
        return []

    def shown(v: Any) -> str:
        text = "none" if v is None else json.dumps(v)
        return text if len(text) <= 40 else text[:39] + "…"

    return [f"{prefix.rstrip('.')}: {shown(old)} recorded, {shown(new)} now"]


def _without_model_path(settings: Any) -> Any:
    """Recorded settings without the object model's path (compared by checksum instead)."""
    config = settings.get("backend_config") if isinstance(settings, dict) else None
    if not isinstance(config, dict) or not isinstance(config.get("object_model"), dict):
        return settings
    model = {k: v for k, v in config["object_model"].items() if k != "path"}
    return {**settings, "backend_config": {**config, "object_model": model}}


def _write_dataset_files(
    out: Path,
    split: str,
    bags: Sequence[str],
    settings: GenerateSettings,
    needle_model: NeedleModel | None = None,
    layout: SceneLayout | None = None,
) -> None:
    """Models, camera.json and the split's generation record (refusing a mismatch).

    ``layout``: the staged layout with the most arms, whose instrument parts are written
    (the parts are numbered in the order of a scene's arms, so the same models serve all).
    """
    info = {
        "bopsurg_version": __version__,
        "split": split,
        "settings": settings.to_json(),
        "bags": [{"path": str(Path(b).resolve()), "sha256": file_sha256(b)} for b in bags],
    }
    info_path = out / split / INFO_NAME
    if info_path.exists():
        old = load_json(info_path)
        _check_same_object_model(old, settings.backend_config, info_path)
        # The mesh is the same by checksum; it may have moved (like the bags).
        changes = _settings_changes(
            _without_model_path(old.get("settings") or {}),
            _without_model_path(json.loads(json.dumps(info["settings"]))),
        )
        if [b["sha256"] for b in old.get("bags", [])] != [b["sha256"] for b in info["bags"]]:
            changes.insert(0, "bags: other files (by sha256)")
        if changes:
            shown = "; ".join(changes[:3]) + ("; …" if len(changes) > 3 else "")
            raise InputError(
                f"this split was generated with other bags or settings ({shown}); choose a "
                "new --out or --split (nothing was changed)",
                path=info_path,
            )
    backend = make_backend(settings) if layout is None else make_backend(settings, layout)
    try:
        if needle_model is not None:
            _check_backend_renders(backend, needle_model, settings.backend)
        infos: dict[int, dict[str, Any]] = {}
        for name, obj_id in backend.annotated_objects():
            model = backend.object_model(name)
            save_ply(out / "models" / f"obj_{obj_id:06d}.ply", model)
            infos[obj_id] = compute_model_info(model.pts)
            if name == NEEDLE:  # tip, tail and plane for the ambiguity analysis of eval
                if needle_model is not None:  # fitted: the mesh's vertex order means nothing
                    infos[obj_id] = needle_model.model_info()
                else:
                    infos[obj_id].update(needle_keypoints(model))
        save_models_info(out / "models" / "models_info.json", infos)
    finally:
        backend.close()
    save_camera_json(out, settings.K, settings.width, settings.height, settings.depth_scale)
    write_text(info_path, json.dumps(info, indent=2, sort_keys=True) + "\n")


def _check_backend_renders(backend: RenderBackend, model: NeedleModel, name: str) -> None:
    """Refuse a backend that ignores :attr:`SceneSpec.needle_model` (it would render its own)."""
    got = backend.object_model(NEEDLE).pts
    want = model.model.pts
    if got.shape != want.shape or not np.array_equal(got, want):
        raise BopsurgError(
            f"backend {name!r} does not support --object-model: its needle is not {model.path}"
        )


def _write_targets(out: Path, split: str, scene_ids: Sequence[int]) -> None:
    gts, infos = {}, {}
    for s in scene_ids:
        d = out / split / f"{s:06d}"
        gts[s] = load_scene_gt(d / "scene_gt.json")
        infos[s] = load_scene_gt_info(d / "scene_gt_info.json")
    save_targets(out / "test_targets_bop19.json", enumerate_targets(gts, infos))


def generate_dataset(
    bags: Sequence[str | Path],
    out: str | Path,
    *,
    split: str = "test",
    settings: GenerateSettings | None = None,
    workers: int = 1,
    executor: Executor | None = None,
    progress: bool = True,
) -> GenerateReport:
    """Replay every bag ``settings.replays`` times into the BOP dataset at ``out``.

    Args:
        bags: Recordings (ROS1 ``.bag`` files or ROS2 folders), in scene-id order.
        out: Dataset root (created).
        split: Split folder name, e.g. ``test`` or ``train``.
        settings: Generation settings (seed, replays, period, ...).
        workers: Worker processes of the default local executor (1 = in this process).
        executor: Where replays run (:mod:`bopsurg.executors`); default: local processes.
        progress: Show a progress bar (frames done and rate).

    Returns:
        Counts of what was done.
    """
    settings = settings or GenerateSettings()
    bag_paths = _checked_inputs(bags, settings, workers)
    # Read every bag once here: bad bags fail before any work starts, and totals are known.
    survey = _survey_bags(bag_paths, settings)
    settings = with_recorded_needle(settings, survey.needles)
    settings, needle_model = resolve_object_model(settings)  # before anything is written
    out = Path(out)
    for folder in (out, out / "models"):  # leftovers of a killed driver (not scene folders)
        for tmp in folder.glob(".*.tmp-*") if folder.is_dir() else ():
            tmp.unlink(missing_ok=True)
    _write_dataset_files(out, split, bag_paths, settings, needle_model, survey.widest)
    if needle_model is not None:
        level = logging.WARNING if needle_model.off_scale else logging.INFO
        log.log(level, "%s", needle_model.describe())
    units = [
        ReplayUnit(b, i, r, str(out), split, settings)
        for i, b in enumerate(bag_paths)
        for r in range(settings.replays)
    ]
    results = _run_units(units, survey.frames, executor or LocalExecutor(workers), progress)
    scene_ids = [u.scene_id for u in units]
    # the root's targets files name the images to evaluate: a training split must not
    # replace those of a test split generated before it into the same dataset
    test_split = not split.startswith("train")
    if test_split:
        _write_targets(out, split, scene_ids)
    write_detection_annotations(BopDataset(out, split), write_targets=test_split)  # + scene_gt_coco
    return GenerateReport(
        scenes=len(results),
        scenes_skipped=sum(r.skipped for r in results),
        frames_rendered=sum(r.frames_rendered for r in results),
        frames_written=sum(r.frames_written for r in results),
    )


def _checked_inputs(
    bags: Sequence[str | Path], settings: GenerateSettings, workers: int
) -> list[str]:
    """The bag paths, once the counts, the profile and the paths are valid (one line each)."""
    if settings.replays < 1:
        raise InputError("must be >= 1", field="replays")
    if workers < 1:
        raise InputError("must be >= 1", field="workers")
    if settings.domain not in DOMAINS:
        raise InputError(f"must be one of {', '.join(DOMAINS)}", field="domain")
    bag_paths = [str(b) for b in bags]
    if not bag_paths:
        raise InputError("no bag given")
    for b in bag_paths:
        if not Path(b).exists():
            raise InputError("file not found", path=b)
    return bag_paths


@dataclass
class _Survey:
    """What the driver learns from reading every bag once."""

    frames: list[int]  # frames per replay of each bag
    needles: dict[str, dict[str, Any] | None]  # each bag's recorded needle spec
    widest: SceneLayout | None  # the staged layout with the most arms (None: the default's)


def _survey_bags(bag_paths: Sequence[str], settings: GenerateSettings) -> _Survey:
    """Read every bag as the replays will (staged when a real robot's)."""
    survey = _Survey([], {}, None)
    for b in bag_paths:
        rec = load_recording(b, settings)
        survey.frames.append(len(frame_times(rec.start, rec.end, settings.period)))
        survey.needles[b] = rec.meta.get("needle")
        arms = (survey.widest or DEFAULT_LAYOUT).arms
        if rec.layout is not None and len(rec.layout.arms) > len(arms):
            survey.widest = rec.layout
    return survey


def _run_units(
    units: list[ReplayUnit], frames_per_bag: list[int], runner: Executor, progress: bool
) -> list[ReplayResult]:
    """Run every replay, with a progress bar over all their frames."""
    total = sum(frames_per_bag[u.bag_index] for u in units)
    bar = tqdm(total=total, unit="frame", desc="generate", disable=not progress, smoothing=0.1)
    try:
        results: list[ReplayResult] = runner.map(_replay_unit, units, on_progress=bar.update)
        for unit, res in zip(units, results, strict=True):
            # frames a resumed run did not need to render
            bar.update(frames_per_bag[unit.bag_index] - res.frames_rendered)
    finally:
        bar.close()
    return results
