"""Bench: `bopsurg eval` on many estimates (default 100,000), end to end.

Builds a scene-files-only BOP dataset (the needle model, N images with one GT each, spread
over scenes of 1,000 images) and a results CSV with one estimate per image plus 5 %
duplicates, then times each stage: loading the CSV, checking it against the dataset, the
evaluation (both matchings, all metrics, BOP19 scores) and writing the outputs. Seeded.

    python bench/bench_eval.py [--estimates 100000] [--out bench/out/eval]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bopsurg.bop.dataset import BopDataset, save_camera_json
from bopsurg.bop.meshes import compute_model_info, save_models_info, save_ply
from bopsurg.bop.results import (
    PoseEstimates,
    check_results_against_dataset,
    load_results,
    save_results,
)
from bopsurg.bop.scene import (
    CameraInfo,
    GtInfo,
    GtPose,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from bopsurg.bop.targets import enumerate_targets, save_targets
from bopsurg.evaluation.runner import evaluate, write_evaluation
from bopsurg.example import DEFAULT_K
from bopsurg.metrics.registry import METRICS
from bopsurg.needle import needle_mesh


def build(root: Path, n: int, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    model = needle_mesh()
    save_ply(root / "models" / "obj_000001.ply", model)
    save_models_info(root / "models" / "models_info.json", {1: compute_model_info(model.pts)})
    save_camera_json(root, DEFAULT_K, 640, 480, depth_scale=0.1)
    per_scene = 1000
    R = Rotation.random(n, random_state=rng).as_matrix()
    t = np.c_[rng.uniform(-20, 20, n), rng.uniform(-15, 15, n), rng.uniform(60, 160, n)]
    vf = rng.uniform(0, 1, n)
    gts, infos = {}, {}
    for s in range((n + per_scene - 1) // per_scene):
        ids = range(s * per_scene, min(n, (s + 1) * per_scene))
        sg = {k - s * per_scene: [GtPose(1, R[k], t[k])] for k in ids}
        si = {
            k - s * per_scene: [
                GtInfo(
                    (1, 1, 5, 5), (1, 1, 5, 5), 100, 100, int(vf[k] * 100), int(vf[k] * 100) / 100
                )
            ]
            for k in ids
        }
        d = root / "test" / f"{s:06d}"
        save_scene_gt(d / "scene_gt.json", sg)
        save_scene_gt_info(d / "scene_gt_info.json", si)
        save_scene_camera(
            d / "scene_camera.json", {i: CameraInfo(K=DEFAULT_K, depth_scale=0.1) for i in sg}
        )
        gts[s], infos[s] = sg, si
    save_targets(root / "test_targets_bop19.json", enumerate_targets(gts, infos))
    dup = rng.random(n) < 0.05
    idx = np.r_[np.arange(n), np.flatnonzero(dup)]
    m = idx.size
    ang = np.deg2rad(rng.lognormal(np.log(7), 0.7, m))
    axis = rng.normal(size=(m, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    R_e = Rotation.from_rotvec(axis * ang[:, None]).as_matrix() @ R[idx]
    t_e = t[idx] + rng.normal(size=(m, 3)) * [0.5, 0.5, 1.6]
    est = PoseEstimates.from_arrays(
        scene_id=(idx // per_scene).astype(np.int64),
        im_id=(idx % per_scene).astype(np.int64),
        obj_id=np.ones(m, dtype=np.int64),
        score=rng.uniform(0.3, 1.0, m),
        R=R_e,
        t=t_e,
        time=np.full(m, 0.05),
    )
    results = root / "bench_needle-test.csv"
    save_results(results, est)
    return results


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--estimates", type=int, default=100_000, help="GT images (= estimates before duplicates)"
    )
    ap.add_argument("--out", default="bench/out/eval", help="working folder")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    root = Path(args.out) / "dataset"
    t0 = time.perf_counter()
    results = build(root, args.estimates, args.seed)
    print(f"built dataset + results: {time.perf_counter() - t0:.1f} s")

    times = {}
    t0 = time.perf_counter()
    est = load_results(results)
    times["load_results"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ds = BopDataset(root, "test")
    images = {(s, i) for s in ds.scene_ids for i in ds.scene(s).camera}
    check_results_against_dataset(est, results, images=images, obj_ids=set(ds.obj_ids))
    times["load GT + check"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = evaluate(ds, est)
    times["evaluate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    write_evaluation(res, Path(args.out) / "eval")
    times["write outputs"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fast = [m for m in METRICS if m != "adi"]
    evaluate(ds, est, instance_metrics=fast)
    t_fast = time.perf_counter() - t0
    n_vertices = ds.model(1).pts.shape[0]
    print(f"estimates: {len(est)}, GT instances: {len(res.gt_rows)}, vertices: {n_vertices}")
    for k, v in times.items():
        print(f"  {k:<18}{v:8.2f} s")
    print(f"  {'total':<18}{sum(times.values()):8.2f} s")
    print(f"evaluate without ADD-S (--metrics {','.join(fast)}): {t_fast:.2f} s")
    scores = res.scores
    print(
        f"AR_MSSD {scores['bop19_average_recall_mssd']:.4f}  "
        f"AR_MSPD {scores['bop19_average_recall_mspd']:.4f}"
    )


if __name__ == "__main__":
    main()
