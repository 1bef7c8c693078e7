"""Bench: batched bopsurg metrics vs the per-pose reference loop, same run, same data.

Workload (seeded): a 5,000-vertex model, either random points in a 40×30×60 mm box or a thin
needle-like torus arc (radius 12 mm, wire radius 0.4 mm, half a turn; not convex); 1,000
random (estimate, GT) pose pairs with GT 100-300 mm in front of the camera and estimates a few
degrees / mm off; one continuous z symmetry (BOP's step 0.01 → 315 transforms).

For each metric (MSSD, MSPD, ADD, ADD-S, proj, RE, TE) it times the batched bopsurg function
on all poses and the reference per-pose loop (:mod:`bopsurg.metrics.reference`, written from
``bop_toolkit_lib.pose_error``) on a subset of poses, whose per-pose time is extrapolated.
It prints per-pose times, the speed-up, the largest absolute and relative deviation on the
subset, and the peak memory of each batched call (tracemalloc, in a separate untimed run).
The torch path (CPU here, or CUDA if present) is timed on a subset too.

    python bench/bench_metrics.py [--poses 1000] [--vertices 5000] [--ref-poses 50] [--quick]
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from bopsurg import metrics
from bopsurg.metrics import reference as ref

K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
CONT_Z = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
REF = ("mssd", "mspd", "add", "adi", "proj", "re", "te")


def box_model(rng: np.random.Generator, v: int) -> np.ndarray:
    return rng.uniform(-0.5, 0.5, (v, 3)) * np.array([40.0, 30.0, 60.0])


def needle_model(rng: np.random.Generator, v: int) -> np.ndarray:
    th = rng.uniform(0.0, np.pi, v)
    ph = rng.uniform(0.0, 2.0 * np.pi, v)
    r = 12.0 + 0.4 * np.cos(ph)
    return np.stack([r * np.cos(th), r * np.sin(th), 0.4 * np.sin(ph)], axis=1)


def pose_pairs(rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    R_gt = Rotation.random(n, random_state=int(rng.integers(2**31))).as_matrix()
    t_gt = np.c_[rng.uniform(-40, 40, n), rng.uniform(-30, 30, n), rng.uniform(100, 300, n)]
    d = Rotation.from_rotvec(rng.normal(0.0, 1.0, (n, 3)) * np.deg2rad(3.0)).as_matrix()
    return d @ R_gt, t_gt + rng.normal(0.0, 3.0, (n, 3)), R_gt, t_gt


def best_of(repeats: int, fn: Callable[[], Any]) -> tuple[float, Any]:
    """Smallest wall time of ``repeats`` calls (s) and the last result."""
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def peak_mb(fn: Callable[[], Any]) -> float:
    """Peak traced allocation (numpy arrays included) of one call, MB."""
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def deviation(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Largest |a − b| and largest |a − b| / |b| (over |b| > 1e-9)."""
    d = np.abs(np.asarray(a, float) - np.asarray(b, float))
    big = np.abs(b) > 1e-9
    rel = float(np.max(d[big] / np.abs(b[big]))) if np.any(big) else 0.0
    return float(np.max(d)), rel


def run_model(name: str, pts: np.ndarray, args: argparse.Namespace) -> list[dict[str, Any]]:
    rng = np.random.default_rng(args.seed + 1)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, args.poses)
    syms = metrics.symmetry_transforms(CONT_Z, 0.01)
    m = min(args.ref_poses, args.poses)
    sub = (R_est[:m], t_est[:m], R_gt[:m], t_gt[:m])
    cases: list[tuple[str, str, Callable[[], Any], Callable[[int], float]]] = [
        ("mssd", "mm", lambda: metrics.mssd(R_est, t_est, R_gt, t_gt, pts, syms),
         lambda i: ref.mssd_ref(R_est[i], t_est[i], R_gt[i], t_gt[i], pts, syms)),
        ("mspd", "px", lambda: metrics.mspd(R_est, t_est, R_gt, t_gt, K, pts, syms),
         lambda i: ref.mspd_ref(R_est[i], t_est[i], R_gt[i], t_gt[i], K, pts, syms)),
        ("add", "mm", lambda: metrics.add(R_est, t_est, R_gt, t_gt, pts),
         lambda i: ref.add_ref(R_est[i], t_est[i], R_gt[i], t_gt[i], pts)),
        ("adi", "mm", lambda: metrics.adi(R_est, t_est, R_gt, t_gt, pts),
         lambda i: ref.adi_ref(R_est[i], t_est[i], R_gt[i], t_gt[i], pts)),
        ("proj", "px", lambda: metrics.proj(R_est, t_est, R_gt, t_gt, K, pts),
         lambda i: ref.proj_ref(R_est[i], t_est[i], R_gt[i], t_gt[i], K, pts)),
        ("re", "deg", lambda: metrics.re(R_est, R_gt), lambda i: ref.re_ref(R_est[i], R_gt[i])),
        ("te", "mm", lambda: metrics.te(t_est, t_gt), lambda i: ref.te_ref(t_est[i], t_gt[i])),
    ]  # fmt: skip
    rows = []
    for metric, unit, batched, one in cases:
        t_fast, vals = best_of(args.repeats, batched)
        t_ref, ref_vals = best_of(1, lambda one=one: np.array([one(i) for i in range(m)]))
        fast_ms = 1e3 * t_fast / args.poses
        ref_ms = 1e3 * t_ref / m
        dev_abs, dev_rel = deviation(vals[:m], ref_vals)
        rows.append({
            "model": name, "metric": metric, "unit": unit, "poses": args.poses, "ref_poses": m,
            "bopsurg_ms_per_pose": fast_ms, "reference_ms_per_pose": ref_ms,
            "speedup": ref_ms / fast_ms, "max_abs_dev": dev_abs, "max_rel_dev": dev_rel,
            "peak_mb": peak_mb(batched), "mean_value": float(np.mean(vals)),
        })  # fmt: skip
    if args.torch:
        rows += run_torch(name, pts, syms, sub, args)
    return rows


def run_torch(
    name: str, pts: np.ndarray, syms: metrics.Symmetries, sub: tuple[np.ndarray, ...], args: Any
) -> list[dict[str, Any]]:
    try:
        from bopsurg.metrics import torch_backend as tb
    except ImportError:
        return []
    dev = tb.resolve_device("auto")
    m = min(args.torch_poses, len(sub[0]))
    pairs = tuple(a[:m] for a in sub)
    rows = []
    for metric, fn, np_fn in [
        ("mssd", lambda: tb.mssd_torch(*pairs, pts, syms, device=dev),
         lambda: metrics.mssd(*pairs, pts, syms)),
        ("mspd", lambda: tb.mspd_torch(*pairs, K, pts, syms, device=dev),
         lambda: metrics.mspd(*pairs, K, pts, syms)),
        ("add", lambda: tb.add_torch(*pairs, pts, device=dev), lambda: metrics.add(*pairs, pts)),
    ]:  # fmt: skip
        fn()  # warm-up (CUDA context, kernels)
        t, out = best_of(args.repeats, lambda fn=fn: fn().cpu().numpy())
        dev_abs, dev_rel = deviation(out, np_fn())
        rows.append({
            "model": name, "metric": f"{metric} (torch {dev.type})", "unit": "",
            "poses": m, "ref_poses": m, "bopsurg_ms_per_pose": 1e3 * t / m,
            "reference_ms_per_pose": float("nan"), "speedup": float("nan"),
            "max_abs_dev": dev_abs, "max_rel_dev": dev_rel, "peak_mb": float("nan"),
            "mean_value": float(np.mean(out)),
        })  # fmt: skip
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--poses", type=int, default=1000, help="pose pairs for the batched metrics")
    p.add_argument("--vertices", type=int, default=5000, help="model vertices")
    p.add_argument("--ref-poses", type=int, default=50, help="poses for the reference loop")
    p.add_argument("--torch-poses", type=int, default=20, help="poses for the torch path")
    p.add_argument("--repeats", type=int, default=3, help="batched runs; the fastest counts")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-torch", dest="torch", action="store_false", help="skip the torch path")
    p.add_argument("--quick", action="store_true", help="200 poses, 10 reference poses, 1 run")
    p.add_argument("--json", type=Path, help="also write the rows as JSON here")
    args = p.parse_args()
    if args.quick:
        args.poses, args.ref_poses, args.torch_poses, args.repeats = 200, 10, 5, 1

    rng = np.random.default_rng(args.seed)
    models = {"box": box_model(rng, args.vertices), "needle": needle_model(rng, args.vertices)}
    print(
        f"bopsurg metrics bench: {args.poses} pose pairs, {args.vertices} vertices, one "
        f"continuous z symmetry (315 transforms), seed {args.seed}; reference loop timed on "
        f"the first {min(args.ref_poses, args.poses)} poses and extrapolated per pose; "
        f"batched: fastest of {args.repeats} runs"
    )
    print(f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
    rows = []
    for name, pts in models.items():
        hull = metrics.hull_vertices(pts).shape[0]
        print(f"\nmodel {name}: {len(pts)} vertices, {hull} on the convex hull")
        print(
            f"{'metric':<18}{'bopsurg ms/pose':>16}{'ref ms/pose':>13}{'speed-up':>10}"
            f"{'max abs dev':>13}{'max rel dev':>13}{'peak MB':>9}"
        )
        for r in run_model(name, pts, args):
            rows.append(r)
            ref_ms = f"{r['reference_ms_per_pose']:.4f}" if r["metric"] in REF else "-"
            speed = f"{r['speedup']:.1f}x" if r["metric"] in REF else "-"
            peak = f"{r['peak_mb']:.1f}" if r["metric"] in REF else "-"
            print(
                f"{r['metric']:<18}{r['bopsurg_ms_per_pose']:>16.4f}{ref_ms:>13}{speed:>10}"
                f"{r['max_abs_dev']:>13.2e}{r['max_rel_dev']:>13.2e}{peak:>9}"
            )
    print(
        "\ndeviations: batched numpy vs the reference loop on the reference subset; torch rows:"
        " torch vs batched numpy on the torch subset (dense evaluation of every symmetry)"
    )
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\nprocess peak RSS: {rss:.0f} MB (includes the interpreter, numpy, scipy, torch)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
