"""The embedded example: a small BOP dataset of a suturing needle and a results file, by code.

``bopsurg eval`` and the tests run on it with nothing to download. It is a real BOP dataset
(models, scene_camera, scene_gt, scene_gt_info, masks, RGB, targets) whose annotations agree
with its pixels: silhouettes are the projected needle mesh, filled triangle by triangle on the
BOP 3× canvas (so truncation is counted), minus a synthetic instrument shaft that occludes
part of the needle in some frames. The results imitate a pose estimator whose errors resemble
the paper's (RE median ≈ 8°, TE median ≈ 1.5 mm, larger when the needle is seen edge-on), with
a few missed frames and duplicate detections. Everything flows from one seed, recorded in
``example_info.json``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bopsurg.atomic import write_text
from bopsurg.bop.dataset import save_camera_json
from bopsurg.bop.images import save_mask, save_rgb
from bopsurg.bop.meshes import ObjectModel, compute_model_info, save_models_info, save_ply
from bopsurg.bop.results import PoseEstimates, save_results
from bopsurg.bop.scene import (
    CameraInfo,
    GtInfo,
    GtPose,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from bopsurg.bop.targets import enumerate_targets, save_targets
from bopsurg.geometry import intrinsics_from_fov
from bopsurg.needle import NeedleSpec, needle_keypoints, needle_mesh
from bopsurg.silhouette import project_silhouette
from bopsurg.visibility import instance_visibility_from_masks

log = logging.getLogger(__name__)

NEEDLE_OBJ_ID = 1
WIDTH, HEIGHT = 640, 480
#: Endoscope intrinsics from a vertical FOV of 1.2 rad at 640×480 (surgical_scene_facts).
DEFAULT_K = intrinsics_from_fov(WIDTH, HEIGHT, 1.2)
FY = float(DEFAULT_K[1, 1])


@dataclass(frozen=True)
class ExampleSpec:
    """What the example contains; every random draw flows from ``seed``."""

    seed: int = 0
    scenes: int = 3
    images_per_scene: int = 12
    method: str = "bopsurgsim"
    occluded_fraction: float = 0.5
    missed_fraction: float = 0.04
    duplicate_fraction: float = 0.08


@dataclass(frozen=True)
class ExampleDataset:
    """Paths of a written example."""

    root: Path
    split: str
    results: Path


def _fill_silhouette(model: ObjectModel, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Amodal silhouette on the BOP 3× canvas (principal point shifted by (W, H))."""
    Kl = K.copy()
    Kl[0, 2] += WIDTH
    Kl[1, 2] += HEIGHT
    return project_silhouette(model.pts, model.faces, Kl, R, t, (3 * HEIGHT, 3 * WIDTH))


def _shaft_mask(rng: np.random.Generator, target: np.ndarray) -> np.ndarray:
    """A grey instrument shaft entering from an image border and ending near ``target`` (px)."""
    mask = np.zeros((HEIGHT, WIDTH), dtype=np.uint8)
    start = (
        np.array([rng.uniform(0, WIDTH), -40.0])
        if rng.random() < 0.5
        else np.array([-40.0, rng.uniform(0, HEIGHT)])
    )
    end = target + rng.uniform(-45.0, 45.0, size=2)
    thickness = int(rng.uniform(28, 60))
    cv2.line(mask, tuple(start.astype(int)), tuple(end.astype(int)), 255, thickness)
    return mask > 0


def _gt_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A needle pose in the endoscope's view: 60–160 mm away, any orientation."""
    z = rng.uniform(60.0, 160.0)
    u = rng.uniform(60.0, WIDTH - 60.0)
    v = rng.uniform(50.0, HEIGHT - 50.0)
    t = np.array([(u - DEFAULT_K[0, 2]) * z / FY, (v - DEFAULT_K[1, 2]) * z / FY, z])
    R = Rotation.random(random_state=rng).as_matrix()
    return R, t


def _estimate(
    rng: np.random.Generator, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A plausible estimate of a GT pose; harder (larger errors) when seen edge-on."""
    normal_cam = R[:, 2]  # needle-plane normal in the camera frame
    view = t / np.linalg.norm(t)
    edge_on = 1.0 - abs(float(normal_cam @ view))  # 1 = plane contains the viewing ray
    scale = 1.0 + 3.0 * edge_on**4
    angle = np.deg2rad(rng.lognormal(np.log(6.5), 0.7) * scale)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R_est = Rotation.from_rotvec(axis * angle).as_matrix() @ R
    # Depth is the hardest direction for a monocular estimator.
    dt = rng.normal(size=3) * np.array([0.45, 0.45, 1.6]) * scale
    return R_est, t + dt


#: One imitation estimate: scene_id, im_id, score, R, t mm, image time s.
_EstRow = tuple[int, int, float, np.ndarray, np.ndarray, float]


def _write_scene(
    root: Path,
    scene_id: int,
    model: ObjectModel,
    spec: ExampleSpec,
    rng: np.random.Generator,
    est_rows: list[_EstRow],
) -> tuple[dict[int, list[GtPose]], dict[int, list[GtInfo]]]:
    """One scene's images, masks and annotations; appends its imitation estimates to
    ``est_rows``. Returns the scene's GT poses and gt_info per image."""
    scene_dir = root / "test" / f"{scene_id:06d}"
    cams: dict[int, CameraInfo] = {}
    gts: dict[int, list[GtPose]] = {}
    infos: dict[int, list[GtInfo]] = {}
    for im_id in range(spec.images_per_scene):
        R, t = _gt_pose(rng)
        large = _fill_silhouette(model, DEFAULT_K, R, t)
        centre = DEFAULT_K[:2, :2] @ (t[:2] / t[2]) + DEFAULT_K[:2, 2]
        occluded = rng.random() < spec.occluded_fraction
        shaft = _shaft_mask(rng, centre) if occluded else None
        inside = large[HEIGHT : 2 * HEIGHT, WIDTH : 2 * WIDTH]
        visib = inside & ~shaft if shaft is not None else inside
        gt_info = instance_visibility_from_masks(large, visib)
        cams[im_id] = CameraInfo(K=DEFAULT_K.copy(), depth_scale=0.1)
        gts[im_id] = [GtPose(obj_id=NEEDLE_OBJ_ID, R=R, t=t)]
        infos[im_id] = [gt_info]
        save_mask(scene_dir / "mask" / f"{im_id:06d}_000000.png", inside)
        save_mask(scene_dir / "mask_visib" / f"{im_id:06d}_000000.png", visib)
        save_rgb(scene_dir / "rgb" / f"{im_id:06d}.png", _render_rgb(rng, visib, shaft))

        im_time = float(np.round(rng.uniform(0.04, 0.09), 4))
        if gt_info.px_count_visib > 0 and rng.random() >= spec.missed_fraction:
            R_e, t_e = _estimate(rng, R, t)
            score = float(np.round(rng.uniform(0.5, 1.0), 4))
            est_rows.append((scene_id, im_id, score, R_e, t_e, im_time))
            if rng.random() < spec.duplicate_fraction:
                R_d, t_d = _estimate(rng, R, t + rng.normal(size=3) * 4.0)
                est_rows.append((scene_id, im_id, score * 0.5, R_d, t_d, im_time))
    save_scene_camera(scene_dir / "scene_camera.json", cams)
    save_scene_gt(scene_dir / "scene_gt.json", gts)
    save_scene_gt_info(scene_dir / "scene_gt_info.json", infos)
    return gts, infos


def _estimates(rows: list[_EstRow]) -> PoseEstimates:
    n = len(rows)
    return PoseEstimates.from_arrays(
        scene_id=np.array([r[0] for r in rows], dtype=np.int64),
        im_id=np.array([r[1] for r in rows], dtype=np.int64),
        obj_id=np.full(n, NEEDLE_OBJ_ID, dtype=np.int64),
        score=np.array([r[2] for r in rows]),
        R=np.array([r[3] for r in rows]).reshape(n, 3, 3),
        t=np.array([r[4] for r in rows]).reshape(n, 3),
        time=np.array([r[5] for r in rows]),
    )


def write_example_dataset(out_dir: str | Path, spec: ExampleSpec | None = None) -> ExampleDataset:
    """Write the example dataset and its results CSV under ``out_dir``.

    Layout: ``out_dir/needle/{models, test/000001.., camera.json, test_targets_bop19.json,
    example_info.json}`` and ``out_dir/{method}_needle-test.csv`` (the BOP results name).

    Args:
        out_dir: Destination folder (created).
        spec: Contents; defaults to :class:`ExampleSpec`.

    Returns:
        The paths written.
    """
    spec = spec or ExampleSpec()
    rng = np.random.default_rng(spec.seed)
    out = Path(out_dir)
    root = out / "needle"
    model = needle_mesh(NeedleSpec())
    save_ply(root / "models" / f"obj_{NEEDLE_OBJ_ID:06d}.ply", model)
    info = {**compute_model_info(model.pts), **needle_keypoints(model)}
    save_models_info(root / "models" / "models_info.json", {NEEDLE_OBJ_ID: info})
    save_camera_json(root, DEFAULT_K, WIDTH, HEIGHT, depth_scale=0.1)

    est_rows: list[_EstRow] = []
    all_gt: dict[int, dict[int, list[GtPose]]] = {}
    all_info: dict[int, dict[int, list[GtInfo]]] = {}
    for scene_id in range(1, spec.scenes + 1):
        gts, infos = _write_scene(root, scene_id, model, spec, rng, est_rows)
        all_gt[scene_id] = gts
        all_info[scene_id] = infos

    save_targets(root / "test_targets_bop19.json", enumerate_targets(all_gt, all_info))
    info_doc = {"generator": "bopsurg.example", "spec": asdict(spec), "obj_ids": [NEEDLE_OBJ_ID]}
    write_text(root / "example_info.json", json.dumps(info_doc, indent=2) + "\n")

    n = len(est_rows)
    results = out / f"{spec.method}_needle-test.csv"
    save_results(results, _estimates(est_rows))
    log.info(
        "example dataset: %s (%d images, %d estimates)",
        root,
        len(all_gt) * spec.images_per_scene,
        n,
    )
    return ExampleDataset(root=root, split="test", results=results)


def _render_rgb(
    rng: np.random.Generator, needle: np.ndarray, shaft: np.ndarray | None
) -> np.ndarray:
    """A cheap stand-in picture: tissue-coloured noise, the shaft in grey, the needle silver."""
    base = np.array([176, 92, 84], dtype=np.float32)
    noise = cv2.GaussianBlur(rng.normal(0, 18, size=(HEIGHT, WIDTH)).astype(np.float32), (0, 0), 6)
    img = base[None, None, :] + noise[..., None]
    if shaft is not None:
        img[shaft] = (70, 72, 76)
    img[needle] = (205, 208, 212)
    result: np.ndarray = np.clip(img, 0, 255).astype(np.uint8)
    return result
