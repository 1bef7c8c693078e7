r"""Bench: the needle fit's time per needle for batches of needles (:meth:`NeedleRefiner.fit`).

The fit runs every needle of a call at once (batched torch on the refiner's device); its
fixed cost per call is spread over the batch. On a small rendered scene (three needles, the
test suite's :mod:`tests.models.refine_scene`), the fit of batches of 1, 8 and 32 needles
(the scene's needles repeated, each copy from its own slightly moved start), RGB and RGB-D,
the median of ``--repeat`` runs; prints ms per batch and per needle, and the process's CPU
time per needle (on a shared machine the steadier of the two: it leaves out waiting for a
core).

    python bench/bench_fit_batch.py [--device cpu|cuda] [--repeat 5] [--threads 2] [--profile]

``--profile``: also how many torch operator calls one RGB-D fit of 8 needles makes and their
mean CPU time (``torch.profiler``, every aten call counted, views included), with the ops that
take most of it.

Evidence preparation (cv2 distance transforms, back-projection: per ROI) is included: it is
part of each call.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bopsurg.models.pose.roi import crop
from bopsurg.models.refine.refiner import EvidenceFn, NeedleRefiner, RoiMasks
from tests.models.refine_scene import ARC, K, rot, scene

BATCHES = (1, 8, 32)
#: Evidence grid side, px: the shipped segmenter's ROI (read 2x finer by the default fit).
GRID = 160


def evidence_source(mask: np.ndarray) -> EvidenceFn:
    """Crops of the scene's mask as the segmenter crops the image."""
    m = torch.from_numpy(mask.astype(np.float32))[None, None]

    def evidence(
        image: torch.Tensor, centre: torch.Tensor, side: torch.Tensor, size: int
    ) -> np.ndarray:
        index = torch.zeros(len(centre), dtype=torch.long)
        return np.asarray(crop(m, centre, side, size, "bilinear", index=index).numpy()[:, 0])

    return evidence


def batch(
    masks: RoiMasks, R0: np.ndarray, t0: np.ndarray, n: int, seed: int = 0
) -> tuple[RoiMasks, np.ndarray, np.ndarray]:
    """n needles: the scene's three in turn, each start turned by about 1 deg and moved by
    about 0.5 mm (its own problem, that converges at its own step)."""
    rng = np.random.default_rng(seed)
    rows = np.arange(n) % 3
    R = rot(rng.normal(0.0, 0.02, (n, 3))) @ R0[rows]
    t = t0[rows] + rng.normal(0.0, 0.5, (n, 3))
    return masks.subset(rows), R, t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--profile", action="store_true", help="count an RGB-D fit's torch calls")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    sc = scene()
    refiner = NeedleRefiner(evidence_source(sc.visible), ARC, GRID, device=args.device)
    box = torch.as_tensor(sc.boxes[:3], dtype=torch.float32)
    masks = refiner.observe(None, K, box, sc.R0[:3], sc.t0[:3])
    refiner.fit(masks, K, sc.R0[:3], sc.t0[:3], sc.depth)  # warm-up
    print(f"device {args.device}, torch {torch.__version__}, {args.threads} threads")
    print(f"{'mode':6s} {'needles':>7s} {'ms/batch':>9s} {'ms/needle':>10s} {'CPU ms/needle':>14s}")
    for mode, depth in (("RGB", None), ("RGB-D", sc.depth)):
        for n in BATCHES:
            m, R, t = batch(masks, sc.R0, sc.t0, n)
            times, cpu = [], []
            for _ in range(args.repeat):
                t_start, c_start = time.perf_counter(), time.process_time()
                refiner.fit(m, K, R, t, depth)
                if args.device.startswith("cuda"):
                    torch.cuda.synchronize()
                times.append(time.perf_counter() - t_start)
                cpu.append(time.process_time() - c_start)
            ms, cpu_ms = 1e3 * float(np.median(times)), 1e3 * float(np.median(cpu))
            print(f"{mode:6s} {n:7d} {ms:9.1f} {ms / n:10.2f} {cpu_ms / n:14.2f}")
    if args.profile:
        profile_calls(refiner, masks, sc)


def profile_calls(refiner: NeedleRefiner, masks: RoiMasks, sc: Any) -> None:
    """Print the torch operator calls of one RGB-D fit of 8 needles and their CPU time."""
    from torch.profiler import profile

    m, R, t = batch(masks, sc.R0, sc.t0, 8)
    with profile() as prof:
        refiner.fit(m, K, R, t, sc.depth)
    ops = prof.key_averages()
    calls = sum(e.count for e in ops)
    self_us = sum(e.self_cpu_time_total for e in ops)
    print(f"RGB-D, 8 needles, one fit: {calls} torch calls, {self_us / calls:.1f} us each (mean)")
    print(ops.table(sort_by="self_cpu_time_total", row_limit=8))


if __name__ == "__main__":
    main()
