"""A small valid BOP dataset built with the bopsurg savers: 1 scene, 2 images, a cube model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bopsurg.bop import (
    CameraInfo,
    GtInfo,
    GtPose,
    ObjectModel,
    compute_model_info,
    save_depth,
    save_json,
    save_mask,
    save_models_info,
    save_ply,
    save_rgb,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)

W, H = 64, 48
K = np.array([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])
# Unit cube (mm) with 8 vertices and 12 triangles.
CUBE_PTS = np.array(
    [[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], dtype=np.float64
)
CUBE_FACES = np.array(
    [
        [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
        [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],
    ],
    dtype=np.int64,
)  # fmt: skip


def cube_model() -> ObjectModel:
    return ObjectModel(pts=CUBE_PTS.copy(), faces=CUBE_FACES.copy())


def bbox_of(mask: np.ndarray) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return (-1, -1, -1, -1)
    return (int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min()))


def build_dataset(root: Path) -> Path:
    """Write the dataset under ``root`` and return ``root``.

    Image 0 has two instances of obj 1 (the second one truncated by the image border), image 1
    one instance. Masks are rectangles; gt_info is computed from them.
    """
    models = root / "models"
    save_ply(models / "obj_000001.ply", cube_model())
    save_models_info(models / "models_info.json", {1: compute_model_info(CUBE_PTS)})
    save_json(
        root / "camera.json",
        {
            "cx": 32.0,
            "cy": 24.0,
            "depth_scale": 0.1,
            "fx": 50.0,
            "fy": 50.0,
            "height": H,
            "width": W,
        },
    )
    scene = root / "test" / "000001"
    rots = Rotation.from_euler("xyz", [[10, 20, 30], [40, -50, 60], [-70, 80, 5]], degrees=True)
    R = rots.as_matrix()
    # (im_id, gt_id): (silhouette rect in the image, visible rect, pixels cut off by the border)
    rects = {
        (0, 0): ((5, 5, 20, 15), (5, 5, 15, 15), 0),
        (0, 1): ((50, 30, 64, 48), (52, 30, 64, 48), 40),
        (1, 0): ((10, 10, 30, 30), (10, 10, 30, 30), 0),
    }
    cams, gts, infos = {}, {}, {}
    k = 0
    for im_id, n_gt in ((0, 2), (1, 1)):
        cams[im_id] = CameraInfo(K=K, depth_scale=0.1, extra={"view_level": 0})
        gts[im_id], infos[im_id] = [], []
        rgb = np.full((H, W, 3), 40 * (im_id + 1), dtype=np.uint8)
        save_rgb(scene / "rgb" / f"{im_id:06d}.png", rgb)
        save_depth(scene / "depth" / f"{im_id:06d}.png", np.full((H, W), 5000 + im_id))
        for gt_id in range(n_gt):
            gts[im_id].append(GtPose(obj_id=1, R=R[k], t=np.array([1.0, 2.0, 500.0 + k])))
            k += 1
            (x0, y0, x1, y1), (vx0, vy0, vx1, vy1), cut = rects[(im_id, gt_id)]
            mask = np.zeros((H, W), dtype=bool)
            mask[y0:y1, x0:x1] = True
            visib = np.zeros((H, W), dtype=bool)
            visib[vy0:vy1, vx0:vx1] = True
            save_mask(scene / "mask" / f"{im_id:06d}_{gt_id:06d}.png", mask)
            save_mask(scene / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png", visib)
            n_all = int(mask.sum()) + cut
            n_visib = int(visib.sum())
            infos[im_id].append(
                GtInfo(
                    bbox_obj=(x0, y0, x1 - x0 - 1, y1 - y0 - 1 + cut // 10),
                    bbox_visib=bbox_of(visib),
                    px_count_all=n_all,
                    px_count_valid=int(mask.sum()),
                    px_count_visib=n_visib,
                    visib_fract=n_visib / n_all,
                )
            )
    save_scene_camera(scene / "scene_camera.json", cams)
    save_scene_gt(scene / "scene_gt.json", gts)
    save_scene_gt_info(scene / "scene_gt_info.json", infos)
    return root


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    return build_dataset(tmp_path / "ds")
