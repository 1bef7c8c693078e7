"""Profile: where the torch metrics backend's MSSD and MSPD spend their time on a device.

For the box and needle models of ``bench_metrics.py`` (5,000 vertices, 315 symmetries), each
call on ``--poses`` pose pairs is timed (best of 3, synchronised), then profiled once with
``torch.profiler``: the kernels by their device time, the host-side calls (launches,
synchronisations) by CPU time, and the kernel launches counted.

    python bench/profile_torch_metrics.py --device cuda [--poses 10000] [--dtype float64]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from bench_metrics import CONT_Z, K, box_model, continuous_step, needle_model, pose_pairs
from torch.profiler import ProfilerActivity, profile

from bopsurg import metrics
from bopsurg.metrics import torch_backend as tb


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--poses", type=int, default=10_000)
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    ap.add_argument("--rows", type=int, default=12, help="rows of each profiler table")
    args = ap.parse_args()
    dev, dt = torch.device(args.device), getattr(torch, args.dtype)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    sort = "self_cuda_time_total" if dev.type == "cuda" else "self_cpu_time_total"
    syms = metrics.symmetry_transforms(CONT_Z, continuous_step(315))
    pairs = pose_pairs(np.random.default_rng(1), args.poses)
    models = {"box": box_model, "needle": needle_model}
    for name, make in models.items():
        pts = make(np.random.default_rng(0), 5000)
        calls = {
            "mssd": lambda pts=pts: tb.mssd_torch(*pairs, pts, syms, device=dev, dtype=dt),
            "mspd": lambda pts=pts: tb.mspd_torch(*pairs, K, pts, syms, device=dev, dtype=dt),
        }
        for metric, fn in calls.items():
            fn()
            sync()
            best = float("inf")
            for _ in range(3):
                t0 = time.perf_counter()
                fn()
                sync()
                best = min(best, time.perf_counter() - t0)
            with profile(activities=activities) as prof:
                fn()
                sync()
            table = prof.key_averages()
            launches = sum(
                e.count for e in table if e.key in ("cudaLaunchKernel", "cuLaunchKernel")
            )
            print(f"\n## {name} {metric} ({args.dtype}, {args.poses} poses, {dev}): "
                  f"{1e3 * best:.2f} ms per call, {launches} kernel launches")  # fmt: skip
            print(table.table(sort_by=sort, row_limit=args.rows, max_name_column_width=50))


if __name__ == "__main__":
    main()
