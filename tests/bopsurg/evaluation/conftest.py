"""A synthetic multi-object, multi-instance BOP dataset and results for evaluation tests."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from bopsurg.bop.dataset import save_camera_json
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
from bopsurg.example import DEFAULT_K
from bopsurg.needle import NeedleSpec, needle_mesh


@dataclass
class SynthData:
    root: Path
    results: Path
    gts: dict[int, dict[int, list[GtPose]]]
    infos: dict[int, dict[int, list[GtInfo]]]
    est: PoseEstimates
    models_info: dict[int, dict]
    models: dict[int, ObjectModel]


def _info(vf: float) -> GtInfo:
    return GtInfo(
        bbox_obj=(10, 10, 20, 20),
        bbox_visib=(10, 10, 20, 20),
        px_count_all=1000,
        px_count_valid=1000,
        px_count_visib=round(1000 * vf),
        visib_fract=round(1000 * vf) / 1000,
    )


def build_synthetic(root: Path, seed: int = 0, n_scenes: int = 2, n_images: int = 8) -> SynthData:
    """Two objects (a needle; a cylinder with a continuous symmetry about z), 1-3 instances
    per image, estimates with duplicates, score ties, misses and non-target rows."""
    rng = np.random.default_rng(seed)
    needle = needle_mesh(NeedleSpec(rings=40, sides=8))
    cyl = trimesh.creation.cylinder(radius=8.0, height=30.0, sections=24)
    models = {
        1: needle,
        2: ObjectModel(pts=np.asarray(cyl.vertices, float), faces=np.asarray(cyl.faces, np.int64)),
    }
    models_info = {}
    for obj_id, m in models.items():
        save_ply(root / "models" / f"obj_{obj_id:06d}.ply", m)
        models_info[obj_id] = compute_model_info(m.pts)
    models_info[2]["symmetries_continuous"] = [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]
    save_models_info(root / "models" / "models_info.json", models_info)

    gts: dict[int, dict[int, list[GtPose]]] = {}
    infos: dict[int, dict[int, list[GtInfo]]] = {}
    rows = []
    for scene_id in range(1, n_scenes + 1):
        cams, sg, si = {}, {}, {}
        for im_id in range(n_images):
            n_inst = int(rng.integers(1, 4))
            sg[im_id], si[im_id] = [], []
            for _ in range(n_inst):
                obj_id = int(rng.integers(1, 3))
                t = np.array([rng.uniform(-30, 30), rng.uniform(-20, 20), rng.uniform(80, 200)])
                R = Rotation.random(random_state=rng).as_matrix()
                sg[im_id].append(GtPose(obj_id=obj_id, R=R, t=t))
                si[im_id].append(_info(float(rng.choice([0.0, 0.05, 0.2, 0.5, 0.5, 0.9, 1.0]))))
                # 0-2 estimates per instance, errors from tiny to huge
                for _ in range(int(rng.choice([0, 1, 1, 1, 2]))):
                    ang = np.deg2rad(rng.choice([1.0, 5.0, 20.0, 90.0]))
                    dR = Rotation.from_rotvec(rng.normal(size=3) * ang / np.sqrt(3)).as_matrix()
                    dt = rng.normal(size=3) * rng.choice([0.2, 1.0, 4.0, 30.0])
                    score = float(rng.choice([0.5, 0.7, 0.7, 0.9]))  # ties on purpose
                    rows.append((scene_id, im_id, obj_id, score, dR @ R, t + dt))
            if rng.random() < 0.3:  # an estimate of an object absent from the image
                absent = 3 - sg[im_id][0].obj_id
                if all(g.obj_id != absent for g in sg[im_id]):
                    rows.append((scene_id, im_id, absent, 0.8, np.eye(3), np.array([0, 0, 100.0])))
            cams[im_id] = CameraInfo(K=DEFAULT_K.copy(), depth_scale=0.1)
        sdir = root / "test" / f"{scene_id:06d}"
        save_scene_camera(sdir / "scene_camera.json", cams)
        save_scene_gt(sdir / "scene_gt.json", sg)
        save_scene_gt_info(sdir / "scene_gt_info.json", si)
        gts[scene_id], infos[scene_id] = sg, si
    save_targets(root / "test_targets_bop19.json", enumerate_targets(gts, infos))
    save_camera_json(root, DEFAULT_K, 640, 480, depth_scale=0.1)
    n = len(rows)
    est = PoseEstimates.from_arrays(
        scene_id=np.array([r[0] for r in rows], dtype=np.int64),
        im_id=np.array([r[1] for r in rows], dtype=np.int64),
        obj_id=np.array([r[2] for r in rows], dtype=np.int64),
        score=np.array([r[3] for r in rows]),
        R=np.array([r[4] for r in rows]).reshape(n, 3, 3),
        t=np.array([r[5] for r in rows]).reshape(n, 3),
        time=np.full(n, 0.1),
    )
    results = root / "synth_synth-test.csv"
    save_results(results, est)
    return SynthData(root, results, gts, infos, est, models_info, models)


@pytest.fixture(scope="module")
def synth(tmp_path_factory: pytest.TempPathFactory) -> SynthData:
    return build_synthetic(tmp_path_factory.mktemp("synth") / "ds")
