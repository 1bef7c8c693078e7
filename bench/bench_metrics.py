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
Each timed batched call is what ``bopsurg eval`` runs once per object: input checks, the
model's preprocessing (MSSD's hull probe and hull, the bound subsets) and all poses; nothing
is cached across calls or repeats, so the per-pose time includes the preprocessing
amortised over ``--poses``.
The torch path (``--device``: CUDA, or the CPU) is timed on all poses.

    python bench/bench_metrics.py [--poses 1000] [--vertices 5000] [--ref-poses 50] [--quick]
        [--clock cpu]

GPU (torch backend against the numpy path, both on all poses, float64 and float32)::

    python bench/bench_metrics.py --device cuda --poses 10000 --symmetries 315 --vertices 5000

With ``--device`` the metrics default to MSSD, MSPD and ADD, and a summary prints numpy and
torch ms/pose with their ratio per model and metric.
"""

from __future__ import annotations

import argparse
import json
import math
import os
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
TORCH = ("mssd", "mspd", "add")


def machine() -> str:
    """The machine in one line: platform, CPU model, cores."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.platform()}, {cpu}, {os.cpu_count()} cores"


def continuous_step(n_syms: int) -> float:
    """``max_sym_disc_step`` that discretises one continuous symmetry into ``n_syms`` rotations
    (``ceil(π / step)`` of them; 0.01 gives BOP's 315)."""
    return 0.01 if n_syms == 315 else math.pi / (n_syms - 0.5)


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


#: The clock of every timing (``--clock``): wall time, or this process's CPU time (all its
#: threads), which other processes on a shared machine disturb far less.
CLOCK: Callable[[], float] = time.perf_counter


def best_of(repeats: int, fn: Callable[[], Any]) -> tuple[float, Any]:
    """Smallest time of ``repeats`` calls (s, on ``CLOCK``) and the last result."""
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = CLOCK()
        out = fn()
        best = min(best, CLOCK() - t0)
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
    syms = metrics.symmetry_transforms(CONT_Z, continuous_step(args.symmetries))
    m = min(args.ref_poses, args.poses)
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
    for metric, unit, batched, one in [c for c in cases if c[0] in args.metrics]:
        t_fast, vals = best_of(args.repeats, batched)
        t_ref, ref_vals = best_of(1, lambda one=one: np.array([one(i) for i in range(m)]))
        fast_ms = 1e3 * t_fast / args.poses
        ref_ms = 1e3 * t_ref / m
        dev_abs, dev_rel = deviation(vals[:m], ref_vals)
        rows.append({
            "model": name, "metric": metric, "unit": unit, "poses": args.poses, "ref_poses": m,
            "bopsurg_ms_per_pose": fast_ms, "reference_ms_per_pose": ref_ms,
            "speedup": ref_ms / fast_ms, "max_abs_dev": dev_abs, "max_rel_dev": dev_rel,
            "peak_mb": float("nan") if args.device else peak_mb(batched),
            "mean_value": float(np.mean(vals)), "values": vals,
        })  # fmt: skip
    if args.device:
        numpy_vals = {r["metric"]: r for r in rows}
        rows += run_torch(name, pts, syms, (R_est, t_est, R_gt, t_gt), numpy_vals, args)
    return rows


def run_torch(
    name: str,
    pts: np.ndarray,
    syms: metrics.Symmetries,
    pairs: tuple[np.ndarray, ...],
    numpy_rows: dict[str, dict[str, Any]],
    args: Any,
) -> list[dict[str, Any]]:
    """Torch rows (float64, then float32) of the metrics timed on numpy, on all poses."""
    import torch

    from bopsurg.metrics import torch_backend as tb

    dev = tb.resolve_device(args.device)
    rows = []
    for dtype in (torch.float64, torch.float32):
        for metric, fn in [
            ("mssd", lambda dt=dtype: tb.mssd_torch(*pairs, pts, syms, device=dev, dtype=dt)),
            ("mspd", lambda dt=dtype: tb.mspd_torch(*pairs, K, pts, syms, device=dev, dtype=dt)),
            ("add", lambda dt=dtype: tb.add_torch(*pairs, pts, device=dev, dtype=dt)),
        ]:  # fmt: skip
            if metric not in numpy_rows:
                continue
            fn()  # warm-up: CUDA context, kernels, the model's hull (cached per model)
            t, out = best_of(args.repeats, lambda fn=fn: fn().cpu().numpy())
            np_row = numpy_rows[metric]
            dev_abs, dev_rel = deviation(out, np_row["values"])
            ms = 1e3 * t / args.poses
            rows.append({
                "model": name, "metric": f"{metric} ({dev.type} {str(dtype)[6:]})",
                "unit": np_row["unit"], "poses": args.poses, "ref_poses": args.poses,
                "bopsurg_ms_per_pose": ms, "reference_ms_per_pose": float("nan"),
                "speedup": float("nan"), "max_abs_dev": dev_abs, "max_rel_dev": dev_rel,
                "peak_mb": float("nan"), "mean_value": float(np.mean(out)),
                "numpy_ms_per_pose": np_row["bopsurg_ms_per_pose"],
                "torch_vs_numpy": np_row["bopsurg_ms_per_pose"] / ms,
            })  # fmt: skip
    return rows


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--poses", type=int, default=1000, help="pose pairs for the batched metrics")
    p.add_argument("--vertices", type=int, default=5000, help="model vertices")
    p.add_argument(
        "--symmetries", type=int, default=315, help="samples of the continuous symmetry (315)"
    )
    p.add_argument("--ref-poses", type=int, default=50, help="poses for the reference loop")
    p.add_argument(
        "--device",
        choices=("cpu", "cuda", "auto"),
        help="also time the torch backend on this device (all poses; default: not timed)",
    )
    p.add_argument(
        "--metrics",
        help=f"comma-separated subset of {','.join(REF)} (default: all; with --device: "
        f"{','.join(TORCH)})",
    )
    p.add_argument("--repeats", type=int, default=3, help="batched runs; the fastest counts")
    p.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="wall time, or this process's CPU time (steadier on a machine shared with other "
        "jobs; both sides of each ratio use the same clock)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="200 poses, 10 reference poses, 1 run")
    p.add_argument("--json", type=Path, help="also write the rows as JSON here")
    args = p.parse_args()
    if args.quick:
        args.poses, args.ref_poses, args.repeats = 200, 10, 1
    chosen = args.metrics or ",".join(TORCH if args.device else REF)
    args.metrics = [m.strip() for m in chosen.split(",") if m.strip()]
    unknown = set(args.metrics) - set(REF)
    if unknown:
        p.error(f"unknown metrics {sorted(unknown)}")
    return args


def print_rows(rows: list[dict[str, Any]]) -> None:
    print(
        f"{'metric':<20}{'bopsurg ms/pose':>16}{'ref ms/pose':>13}{'speed-up':>10}"
        f"{'max abs dev':>13}{'max rel dev':>13}{'peak MB':>9}"
    )
    for r in rows:
        ref = r["metric"] in REF
        ref_ms = f"{r['reference_ms_per_pose']:.4f}" if ref else "-"
        speed = f"{r['speedup']:.1f}x" if ref else "-"
        peak = f"{r['peak_mb']:.1f}" if ref and not math.isnan(r["peak_mb"]) else "-"
        print(
            f"{r['metric']:<20}{r['bopsurg_ms_per_pose']:>16.4f}{ref_ms:>13}{speed:>10}"
            f"{r['max_abs_dev']:>13.2e}{r['max_rel_dev']:>13.2e}{peak:>9}"
        )


def print_torch_summary(rows: list[dict[str, Any]], n: int) -> None:
    """numpy vs torch ms/pose and their ratio, per model and metric."""
    tr = [r for r in rows if "torch_vs_numpy" in r]
    if not tr:
        return
    print(f"\nnumpy path vs torch backend, {n} poses (ratio = numpy time / torch time):")
    print(f"{'model':<8}{'metric':<22}{'numpy ms/pose':>15}{'torch ms/pose':>15}{'ratio':>9}")
    for r in tr:
        print(
            f"{r['model']:<8}{r['metric']:<22}{r['numpy_ms_per_pose']:>15.5f}"
            f"{r['bopsurg_ms_per_pose']:>15.5f}{r['torch_vs_numpy']:>8.1f}x"
        )


def main() -> None:
    global CLOCK
    args = parse_args()
    CLOCK = time.process_time if args.clock == "cpu" else time.perf_counter
    rng = np.random.default_rng(args.seed)
    models = {"box": box_model(rng, args.vertices), "needle": needle_model(rng, args.vertices)}
    n_syms = len(metrics.symmetry_transforms(CONT_Z, continuous_step(args.symmetries))[0])
    print(
        f"bopsurg metrics bench: {args.poses} pose pairs, {args.vertices} vertices, one "
        f"continuous z symmetry ({n_syms} transforms), seed {args.seed}; reference loop timed "
        f"on the first {min(args.ref_poses, args.poses)} poses and extrapolated per pose; "
        f"batched: fastest of {args.repeats} runs, each one call on all poses with the model's "
        f"preprocessing included (as bopsurg eval does per object; no caching); {args.clock} "
        "clock"
    )
    print(f"machine: {machine()}")
    print(f"python {platform.python_version()}, numpy {np.__version__}")
    if args.device:
        import torch

        from bopsurg.metrics import torch_backend as tb

        dev = tb.resolve_device(args.device)
        name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "CPU"
        print(
            f"torch {torch.__version__}, device {dev} ({name}), {torch.get_num_threads()} threads"
        )
    rows = []
    for name, pts in models.items():
        hull = metrics.hull_vertices(pts).shape[0]
        print(f"\nmodel {name}: {len(pts)} vertices, {hull} on the convex hull")
        model_rows = run_model(name, pts, args)
        print_rows(model_rows)
        rows += model_rows
    print(
        "\ndeviations: batched numpy vs the reference loop on the reference subset; torch rows:"
        " torch vs batched numpy on all poses"
    )
    print_torch_summary(rows, args.poses)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\nprocess peak RSS: {rss:.0f} MB (includes the interpreter, numpy, scipy, torch)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        clean = [{k: v for k, v in r.items() if k != "values"} for r in rows]
        args.json.write_text(json.dumps({"machine": machine(), "rows": clean}, indent=1))


if __name__ == "__main__":
    main()
