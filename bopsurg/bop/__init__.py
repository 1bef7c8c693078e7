"""BOP datasets and results, read and written exactly as the BOP toolkit (``bop_toolkit_lib``)
does, with plain one-line messages (``file:line: field: reason``) for anything malformed.

Dataset layout (BOP-scenewise)::

    DATASET/
      camera.json                      # optional: fx, fy, cx, cy, width, height, depth_scale
      test_targets_bop19.json          # evaluation targets: [{im_id, inst_count, obj_id, scene_id}]
      models[_eval]/                   # models_eval/ (evaluation models) is preferred
        models_info.json               # {obj_id: {diameter, min_x.., size_x.., symmetries_*}}
        obj_{obj_id:06d}.ply           # mesh, vertices in mm
      {split}[_{split_type}]/          # test/, train_pbr/ ...
        {scene_id:06d}/
          scene_camera.json            # {im_id: {cam_K [9], depth_scale, cam_R_w2c?, cam_t_w2c?}}
          scene_gt.json                # {im_id: [{obj_id, cam_R_m2c [9], cam_t_m2c [3] mm}]}
          scene_gt_info.json           # {im_id: [{bbox_obj, bbox_visib, px_count_*, visib_fract}]}
          rgb/{im_id:06d}.png|.jpg     # gray/ for gray-scale datasets
          depth/{im_id:06d}.png        # uint16, mm = value × depth_scale
          mask/{im_id:06d}_{gt_id:06d}.png        # silhouette inside the image, 255 = object
          mask_visib/{im_id:06d}_{gt_id:06d}.png  # visible part

Conventions: poses map model to camera, ``x_cam = R @ x_model + t``, ``R`` written as 9 floats
row-major, ``t`` and model vertices in mm; the ``gt_id`` of an instance is its index in the
image's ``scene_gt.json`` list. JSON files use integer ids as string keys and the reference's
one-entry-per-line layout (:func:`save_json`).

Pose results are the BOP19 CSV ``scene_id,im_id,obj_id,score,R,t,time`` (:mod:`.results`).

Modules: :mod:`.jsonio` (JSON), :mod:`.scene` (scene_camera / scene_gt / scene_gt_info),
:mod:`.images` (rgb, depth, masks), :mod:`.models` (PLY, models_info), :mod:`.results` (CSV),
:mod:`.targets`, :mod:`.dataset` (lazy :class:`BopDataset`), :mod:`.check`
(:func:`check_dataset`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from bopsurg._lazy import lazy_exports

if TYPE_CHECKING:
    from bopsurg.bop.check import Problem, check_dataset
    from bopsurg.bop.dataset import BopDataset, BopScene, model_path, save_camera_json, scene_dir
    from bopsurg.bop.images import (
        image_size,
        load_depth,
        load_mask,
        load_rgb,
        save_depth,
        save_mask,
        save_rgb,
    )
    from bopsurg.bop.jsonio import load_json, save_json
    from bopsurg.bop.meshes import (
        ObjectModel,
        compute_model_info,
        load_models_info,
        load_ply,
        save_models_info,
        save_ply,
    )
    from bopsurg.bop.results import (
        PoseEstimates,
        average_time_per_image,
        check_results_against_dataset,
        load_results,
        save_results,
    )
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
    from bopsurg.bop.targets import Target, enumerate_targets, load_targets, save_targets

#: The module of each public name, imported on first access (:mod:`bopsurg._lazy`): the VSD
#: worker process, which needs images and meshes, loads no other.
_HOME: dict[str, str] = {
    "BopDataset": ".dataset",
    "BopScene": ".dataset",
    "CameraInfo": ".scene",
    "GtInfo": ".scene",
    "GtPose": ".scene",
    "ObjectModel": ".meshes",
    "PoseEstimates": ".results",
    "Problem": ".check",
    "Target": ".targets",
    "average_time_per_image": ".results",
    "check_dataset": ".check",
    "check_results_against_dataset": ".results",
    "compute_model_info": ".meshes",
    "enumerate_targets": ".targets",
    "image_size": ".images",
    "load_depth": ".images",
    "load_json": ".jsonio",
    "load_mask": ".images",
    "load_models_info": ".meshes",
    "load_ply": ".meshes",
    "load_results": ".results",
    "load_rgb": ".images",
    "load_scene_camera": ".scene",
    "load_scene_gt": ".scene",
    "load_scene_gt_info": ".scene",
    "load_targets": ".targets",
    "model_path": ".dataset",
    "save_camera_json": ".dataset",
    "save_depth": ".images",
    "save_json": ".jsonio",
    "save_mask": ".images",
    "save_models_info": ".meshes",
    "save_ply": ".meshes",
    "save_results": ".results",
    "save_rgb": ".images",
    "save_scene_camera": ".scene",
    "save_scene_gt": ".scene",
    "save_scene_gt_info": ".scene",
    "save_targets": ".targets",
    "scene_dir": ".dataset",
}

__all__ = [
    "BopDataset",
    "BopScene",
    "CameraInfo",
    "GtInfo",
    "GtPose",
    "ObjectModel",
    "PoseEstimates",
    "Problem",
    "Target",
    "average_time_per_image",
    "check_dataset",
    "check_results_against_dataset",
    "compute_model_info",
    "enumerate_targets",
    "image_size",
    "load_depth",
    "load_json",
    "load_mask",
    "load_models_info",
    "load_ply",
    "load_results",
    "load_rgb",
    "load_scene_camera",
    "load_scene_gt",
    "load_scene_gt_info",
    "load_targets",
    "model_path",
    "save_camera_json",
    "save_depth",
    "save_json",
    "save_mask",
    "save_models_info",
    "save_ply",
    "save_results",
    "save_rgb",
    "save_scene_camera",
    "save_scene_gt",
    "save_scene_gt_info",
    "save_targets",
    "scene_dir",
]


lazy_exports(__name__, _HOME)
