"""``bopsurg annotate``: masks and scene_gt_info for a BOP dataset that has poses but no masks.

For every GT instance the object model is rendered alone at its GT pose with the image's K
on BOP's 3× canvas (principal point shifted by (W, H), so truncated parts count), by a depth
renderer plugin (:class:`bopsurg.plugins.DepthRenderer`; the built-in one is PyBullet's,
headless, no OpenGL install). Masks and gt_info then follow the reference toolkit's
``calc_gt_masks.py`` / ``calc_gt_info.py`` (:func:`bopsurg.visibility.instance_visibility`):

- with depth images: visibility against the measured depth (bop19 rule, tolerance δ);
- without depth images: visibility against the depth of all GT instances of the image
  rendered together (only the annotated objects can occlude each other), said in the log
  and recorded in ``bopsurg_annotate.json``.

Everything is validated before anything is written. Scenes are the unit of work: a scene's
masks are written atomically one by one, its ``scene_gt_info.json`` last, so a scene with
that file is complete; a rerun skips complete scenes (``overwrite`` redoes them).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from bopsurg.atomic import remove_stale_temporaries, write_text
from bopsurg.bop.coco import write_detection_annotations
from bopsurg.bop.dataset import BopDataset, BopScene
from bopsurg.bop.images import image_size, load_depth, save_mask
from bopsurg.bop.scene import GtInfo, save_scene_gt_info
from bopsurg.bop.targets import enumerate_targets, save_targets
from bopsurg.errors import DatasetError
from bopsurg.plugins import DepthRenderer
from bopsurg.visibility import DEFAULT_DELTA_MM, instance_visibility, large_canvas

log = logging.getLogger(__name__)

RECORD_NAME = "bopsurg_annotate.json"


@dataclass
class AnnotateReport:
    """What an annotation run did."""

    scenes: int
    scenes_skipped: int
    instances: int
    with_depth: bool


def _has_depth(scene: BopScene) -> bool:
    return (scene.scene_dir / "depth").is_dir()


def _validate(dataset: BopDataset) -> tuple[tuple[int, int], bool]:
    """Check everything annotation needs; returns the image size and whether depth exists.

    Raises:
        DatasetError: The first problem, one line naming file and field.
    """
    width, height = dataset.image_size()
    known = set(dataset.obj_ids)
    depth_flags = set()
    for scene in dataset.iter_scenes():
        depth = _has_depth(scene)
        depth_flags.add(depth)
        gt_path = scene.scene_dir / "scene_gt.json"
        for im_id, gts in scene.gt.items():
            cam = scene.camera.get(im_id)
            if cam is None:
                raise DatasetError(
                    f"image {im_id} has GT but no cam_K", path=scene.scene_dir / "scene_camera.json"
                )
            for gt_id, gt in enumerate(gts):
                if gt.obj_id < 1:
                    raise DatasetError(
                        "obj_id must be >= 1 (BOP)", path=gt_path, field=f"{im_id}/{gt_id}/obj_id"
                    )
                if gt.obj_id not in known:
                    raise DatasetError(
                        f"obj_id {gt.obj_id} has no model in {dataset.models_dir}",
                        path=gt_path,
                        field=f"{im_id}/{gt_id}/obj_id",
                    )
            if depth:
                if cam.depth_scale is None:
                    raise DatasetError(
                        "depth_scale is missing",
                        path=scene.scene_dir / "scene_camera.json",
                        field=f"{im_id}/depth_scale",
                    )
                size = image_size(scene.depth_path(im_id))
                if size != (width, height):
                    raise DatasetError(
                        f"depth image is {size[0]}x{size[1]}, the dataset's images are "
                        f"{width}x{height}",
                        path=scene.depth_path(im_id),
                    )
    for obj_id in known:
        dataset.model(obj_id)  # a missing or broken PLY fails here, before any writing
    if len(depth_flags) > 1:
        raise DatasetError(
            "some scenes have depth/ and others not; annotate them as separate splits",
            path=dataset.split_dir,
        )
    return (width, height), depth_flags == {True}


def annotate_scene(
    dataset: BopDataset,
    scene: BopScene,
    renderer: DepthRenderer,
    size: tuple[int, int],
    *,
    delta: float = DEFAULT_DELTA_MM,
) -> int:
    """Write mask/, mask_visib/ and scene_gt_info.json of one scene; returns the instances."""
    width, height = size
    with_depth = _has_depth(scene)
    for sub in ("mask", "mask_visib"):  # what a killed earlier run may have left
        remove_stale_temporaries(scene.scene_dir / sub)
    infos: dict[int, list[GtInfo]] = {}
    count = 0
    for im_id in sorted(scene.gt):
        gts = scene.gt[im_id]
        cam = scene.camera[im_id]
        canvas = large_canvas(cam.K, width, height)
        large = [renderer.render_depth(dataset.model(g.obj_id), g.R, g.t, *canvas) for g in gts]
        if with_depth:
            assert cam.depth_scale is not None
            depth_test = load_depth(scene.depth_path(im_id)) * cam.depth_scale
        else:
            # Only the GT instances can occlude each other: the test depth is their z-buffer.
            depth_test = np.zeros((height, width))
            for d in large:
                inside = d[height : 2 * height, width : 2 * width]
                hit = (inside > 0) & ((depth_test == 0) | (inside < depth_test))
                depth_test[hit] = inside[hit]
        infos[im_id] = []
        for gt_id, d in enumerate(large):
            vis = instance_visibility(depth_test, d, cam.K, delta=delta)
            save_mask(scene.mask_path(im_id, gt_id), vis.mask)
            save_mask(scene.mask_visib_path(im_id, gt_id), vis.mask_visib)
            infos[im_id].append(vis.info)
            count += 1
    save_scene_gt_info(scene.scene_dir / "scene_gt_info.json", infos)
    return count


_WORKER: dict[str, Any] = {}


def _worker_init(root: str, split: str, split_type: str | None, renderer_name: str | None) -> None:
    from bopsurg.plugins import load_plugin

    _WORKER["dataset"] = BopDataset(root, split, split_type=split_type)
    _WORKER["renderer"] = load_plugin("renderer", renderer_name)()


def _worker_scene(job: tuple[int, tuple[int, int], float]) -> tuple[int, int, int]:
    scene_id, size, delta = job
    dataset: BopDataset = _WORKER["dataset"]
    scene = dataset.scene(scene_id)
    n = annotate_scene(dataset, scene, _WORKER["renderer"], size, delta=delta)
    return scene_id, n, len(scene.gt)


def annotate_dataset(
    root: str | Path,
    split: str = "test",
    *,
    renderer: DepthRenderer | None = None,
    renderer_name: str | None = None,
    split_type: str | None = None,
    delta: float = DEFAULT_DELTA_MM,
    overwrite: bool = False,
    workers: int = 1,
    progress: bool = True,
) -> AnnotateReport:
    """Annotate every scene of a split (see the module docstring).

    Args:
        root: Dataset root.
        split: Split folder name.
        renderer: Depth renderer instance (one process); default: the plugin
            ``renderer_name``.
        renderer_name: Depth renderer plugin name (default: the first installed); each
            worker process loads its own.
        split_type: Split type suffix (``pbr`` → ``train_pbr``).
        delta: Visibility tolerance δ, mm (BOP: 15; 5 for ITODD and PBR; 1 for fine
            instruments with exact depth).
        overwrite: Redo scenes that already have scene_gt_info.json.
        workers: Processes, each annotating whole scenes (scenes never share files).
        progress: Show a progress bar over images.
    """
    if workers < 1:
        raise DatasetError("must be >= 1", field="workers")
    dataset = BopDataset(root, split, split_type=split_type)
    size, with_depth = _validate(dataset)
    if not with_depth:
        log.warning(
            "no depth images: visibility is computed from the GT instances rendered against "
            "each other (other occluders are not known)"
        )
    todo, skipped = [], 0
    for scene in dataset.iter_scenes():
        if (scene.scene_dir / "scene_gt_info.json").exists() and not overwrite:
            skipped += 1
        else:
            todo.append(scene)
    n_images = sum(len(s.gt) for s in todo)
    instances = 0
    with tqdm(total=n_images, unit="img", desc="annotate", disable=not progress) as bar:
        if workers == 1 or len(todo) <= 1:
            if renderer is None:
                from bopsurg.plugins import load_plugin

                renderer = load_plugin("renderer", renderer_name)()
            for scene in todo:
                instances += annotate_scene(dataset, scene, renderer, size, delta=delta)
                bar.update(len(scene.gt))
        else:
            import multiprocessing as mp

            ctx = mp.get_context("spawn")
            init = (str(root), split, split_type, renderer_name)
            jobs = [(s.scene_id, size, delta) for s in todo]
            with ctx.Pool(workers, initializer=_worker_init, initargs=init) as pool:
                for _, n, images in pool.imap_unordered(_worker_scene, jobs):
                    instances += n
                    bar.update(images)
    record = {
        "delta_mm": delta,
        "visibility": "depth images" if with_depth else "GT instances rendered together",
        "renderer": type(renderer).__name__ if renderer is not None else renderer_name,
    }
    write_text(dataset.split_dir / RECORD_NAME, json.dumps(record, indent=2) + "\n")
    targets = Path(root) / "test_targets_bop19.json"
    if not targets.exists():
        gts = {s.scene_id: s.gt for s in dataset.iter_scenes()}
        infos = {s.scene_id: s.gt_info or {} for s in dataset.iter_scenes()}
        save_targets(targets, enumerate_targets(gts, infos))
    write_detection_annotations(dataset, keep_targets=True)  # scene_gt_coco, BOP24 targets
    return AnnotateReport(len(todo) + skipped, skipped, instances, with_depth)
