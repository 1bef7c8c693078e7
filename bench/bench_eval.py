"""Bench: `bopsurg eval` end to end, against the reference toolkit's scripts or at scale.

With ``--data DATASET --results CSV`` (e.g. the demo's ``demo_out/data`` and
``demo_out/results.csv``): times the ``bopsurg eval`` command (a fresh process, imports
included, default options: VSD with the installed renderer, BOP19 and BOP24, intervals) and,
given ``--toolkit`` (a thodan/bop_toolkit checkout) and ``--toolkit-python`` (a Python that
runs it: numpy < 2, scipy, pypng, imageio, vispy, PyOpenGL; headless Mesa EGL), the
reference's ``scripts/eval_bop19_pose.py`` (VSD, MSSD, MSPD, one worker) on the same data laid
out as its ``lm`` dataset. Prints both wall times, their ratio and both sets of ARs.

    python bench/bench_eval.py --data demo_out/data --results demo_out/results.csv \
        --toolkit ../bop_toolkit --toolkit-python ../bop-venv/bin/python

Without ``--data``: builds a scene-files-only BOP dataset (the needle model, N images with one
GT each, spread over scenes of 1,000 images) and a results CSV with one estimate per image
plus 5 % duplicates, then times each stage: loading the CSV, checking it against the dataset,
the evaluation (both matchings, all metrics, BOP19 scores) and writing the outputs. Seeded.

    python bench/bench_eval.py [--estimates 100000] [--out bench/out/eval]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
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


#: The toolkit's ``lm``: the only layout its scripts accept for a dataset of ours.
LM_OBJECTS, LM_SCENES = range(1, 16), range(1, 16)
AR_KEYS = ("bop19_average_recall_vsd", "bop19_average_recall_mssd", "bop19_average_recall_mspd")


def as_lm(data: Path, bop_path: Path) -> None:
    """Copy a 640x480 dataset with scene ids and object ids in 1..15 into ``bop_path/lm``."""
    lm = bop_path / "lm"
    shutil.rmtree(lm, ignore_errors=True)
    (lm / "models_eval").mkdir(parents=True)
    info = json.loads((data / "models" / "models_info.json").read_text())
    first = min(int(k) for k in info)
    for obj_id in LM_OBJECTS:
        src = obj_id if str(obj_id) in info else first
        ply = data / "models" / f"obj_{src:06d}.ply"
        shutil.copy(ply, lm / "models_eval" / f"obj_{obj_id:06d}.ply")
        info[str(obj_id)] = info[str(src)]
    (lm / "models_eval" / "models_info.json").write_text(json.dumps(info))
    shutil.copytree(data / "test", lm / "test")
    for scene_id in LM_SCENES:  # the toolkit expects every lm scene; empty ones do
        d = lm / "test" / f"{scene_id:06d}"
        if not d.exists():
            d.mkdir()
            for name in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json"):
                (d / name).write_text("{}")
    shutil.copy(data / "test_targets_bop19.json", lm / "test_targets_bop19.json")


def run_toolkit(args: argparse.Namespace, work: Path) -> tuple[float, dict[str, float]]:
    """The reference's eval_bop19_pose.py on the data laid out as lm: (wall s, scores)."""
    bop, res, ev = work / "bop", work / "results", work / "eval"
    as_lm(args.data, bop)
    for d in (res, ev):
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
    shutil.copy(args.results, res / "bench_lm-test.csv")
    python = Path(args.toolkit_python).absolute()
    env = {
        **os.environ,
        "PYTHONPATH": str(Path(args.toolkit).resolve()),
        "BOP_PATH": str(bop.resolve()),
        "BOP_RESULTS_PATH": str(res.resolve()),
        "BOP_EVAL_PATH": str(ev.resolve()),
        "PATH": f"{python.parent}{os.pathsep}{os.environ['PATH']}",
        "PYOPENGL_PLATFORM": "egl",
        "EGL_PLATFORM": "surfaceless",
    }
    script = Path(args.toolkit) / "scripts" / "eval_bop19_pose.py"
    cmd = [str(python), str(script), "--result_filenames=bench_lm-test.csv", "--num_workers=1"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    out = ev / "bench_lm-test" / "scores_bop19.json"
    if proc.returncode != 0 or not out.exists():
        sys.exit(f"the toolkit failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return seconds, json.loads(out.read_text())


def run_bopsurg(
    args: argparse.Namespace, work: Path, verbose: bool = False
) -> tuple[float, float, dict[str, float], str]:
    """``bopsurg eval`` with its defaults in a fresh process: (wall s, CPU s, scores, its
    stderr; ``verbose``: with ``-v``, debug messages included). CPU is user + system time of
    the command and of the processes it waited for (VSD's worker)."""
    out = work / "bopsurg_eval"
    shutil.rmtree(out, ignore_errors=True)
    bopsurg = Path(sys.executable).parent / "bopsurg"
    cmd = [str(bopsurg), *(["-v"] if verbose else []), "eval", str(args.data), str(args.results)]
    cmd += ["--out", str(out), "--no-progress", *args.eval_args]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, check=True, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return seconds, cpu, json.loads((out / "scores.json").read_text()), done.stderr


def vsd_timeline(args: argparse.Namespace, work: Path) -> str:
    """One more ``bopsurg -v eval``: its log line on how VSD's images were shared between the
    worker and the main process (``PendingVsd``), with the wall time of that run."""
    seconds, _, _, stderr = run_bopsurg(args, work, verbose=True)
    lines = [x for x in stderr.splitlines() if "VSD:" in x] or ["(no VSD worker ran)"]
    return f"{lines[-1].split('VSD:', 1)[-1].strip()}; the run took {seconds:.3f} s"


def compare_with_reference(args: argparse.Namespace) -> dict[str, object]:
    """Time bopsurg eval (best of ``--repeats``) and the reference; print the comparison."""
    work = Path(args.out)
    runs = [run_bopsurg(args, work) for _ in range(args.repeats)]
    t_ours, _, ours, _ = min(runs, key=lambda r: r[0])
    cpu = sorted(r[1] for r in runs)[len(runs) // 2]
    print(f"bopsurg eval: {t_ours:.2f} s (best of {args.repeats}; all: "
          f"{', '.join(f'{r[0]:.2f}' for r in runs)}); "
          f"CPU (user + sys, median) {cpu:.2f} s")  # fmt: skip
    row: dict[str, object] = {
        "bopsurg_s": t_ours,
        "bopsurg_cpu_s": cpu,
        "bopsurg": {k: ours.get(k) for k in AR_KEYS},
    }
    if args.toolkit:
        t_ref, ref = run_toolkit(args, work)
        row |= {"reference_s": t_ref, "ratio": t_ref / t_ours}
        row["reference"] = {k: ref.get(k) for k in AR_KEYS}
        print(f"reference scripts (eval_bop19_pose.py, 1 worker): {t_ref:.2f} s")
        print(f"ratio: bopsurg eval is {t_ref / t_ours:.1f}x the reference")
    for k in AR_KEYS:
        ref_v = row.get("reference", {}).get(k) if args.toolkit else None  # type: ignore[union-attr]
        print(f"  {k:<28} bopsurg {ours.get(k)}   reference {ref_v}")
    if args.timeline:
        row["vsd_timeline"] = vsd_timeline(args, work)
        print(f"VSD (one more run, -v): {row['vsd_timeline']}")
    return row


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--estimates", type=int, default=100_000, help="GT images (= estimates before duplicates)"
    )
    ap.add_argument("--out", default="bench/out/eval", help="working folder")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", type=Path, help="a BOP dataset: compare with the reference")
    ap.add_argument("--results", type=Path, help="its results CSV (with --data)")
    ap.add_argument("--toolkit", type=Path, help="thodan/bop_toolkit checkout (with --data)")
    ap.add_argument("--toolkit-python", default="python", help="Python that runs the toolkit")
    ap.add_argument(
        "--timeline", action="store_true",
        help="with --data: one more run that prints how VSD's images were shared between its "
        "worker and the main process, and how long the main process then waited",
    )  # fmt: skip
    ap.add_argument("--repeats", type=int, default=3, help="bopsurg eval runs (the fastest counts)")
    ap.add_argument(
        "--eval-arg", dest="eval_args", action="append", default=[], help="extra eval argument"
    )
    ap.add_argument("--json", type=Path, help="also write the numbers as JSON here")
    args = ap.parse_args()
    if args.data:
        if not args.results:
            ap.error("--data needs --results")
        row = compare_with_reference(args)
        if args.json:
            args.json.write_text(json.dumps(row, indent=1))
        return
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
    if args.json:
        numbers = {"estimates": len(est), "vertices": n_vertices, "stages_s": times}
        numbers |= {"total_s": sum(times.values()), "evaluate_without_adi_s": t_fast}
        args.json.write_text(json.dumps(numbers, indent=1))


if __name__ == "__main__":
    main()
