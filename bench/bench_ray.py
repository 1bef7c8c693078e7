"""Bench: `bopsurg generate` on the local process pool vs a local Ray cluster, same 2 cores.

Records a seeded bag, starts a two-node Ray cluster (1 CPU each, token authentication, in a
loopback-only network namespace: needs root and iproute2) and times its start, then
generates the same replays with ``--executor local --workers 2`` and with ``--executor ray``
on the running cluster, alternating (``--repeat`` rounds, so load from elsewhere on the
machine hits both alike), checks the bytes are equal, and prints frames/s and the Ray
steady-state overhead (cluster start excluded: it is paid once per cluster, not per job).
From the measured per-frame cost it estimates the time of a 100,000-frame dataset on N nodes.

    sudo python bench/bench_ray.py [--replays 12] [--duration 20] [--repeat 2]
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bopsurg.generators.bags import write_bag
from bopsurg.generators.trajectory import synthesize_suturing
from tests.ray_netns import Cluster, netns_available


def digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "bopsurg_generate.json"
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--replays", type=int, default=12, help="replays of the bag (12)")
    ap.add_argument("--duration", type=float, default=20.0, help="bag length, s (20)")
    ap.add_argument("--repeat", type=int, default=2, help="rounds of local + Ray runs (2)")
    args = ap.parse_args()
    if not netns_available():
        sys.exit("needs root and ip netns")
    work = Path(tempfile.mkdtemp(prefix="bopsurg-ray-"))
    bag = work / "a.bag"
    write_bag(bag, synthesize_suturing(seed=0, duration=args.duration))
    t0 = time.perf_counter()
    cluster = Cluster(nodes=2, cpus_per_node=1, token="bench-" + hashlib.sha256(b"x").hexdigest())
    start_s = time.perf_counter() - t0
    try:
        common = f"--replays {args.replays} --period 0.5 --seed 3 --min-visib 0 --no-progress"
        runs = {
            "local pool, 2 workers": "--executor local --workers 2",
            "Ray, 2 nodes x 1 CPU": f"--executor ray --ray-address {cluster.address}",
        }
        times: dict[str, list[float]] = {label: [] for label in runs}
        outs: dict[str, Path] = {}
        frames = 0
        print(f"Ray cluster start (2 nodes, token auth): {start_s:.1f} s")
        for k in range(args.repeat):
            for label, opts in runs.items():
                out = work / f"{label.split(',')[0].replace(' ', '_')}_{k}"
                t0 = time.perf_counter()
                r = cluster.sh(f"bopsurg generate {bag} --out {out} {common} {opts}")
                dt = time.perf_counter() - t0
                frames = int(r.stdout.split(" frames written")[0].split()[-1])
                times[label].append(dt)
                outs[label] = out
                print(f"  round {k + 1}  {label:<24} {frames / dt:6.2f} frames/s "
                      f"({frames} frames, {dt:.1f} s)")  # fmt: skip
        a, b = outs.values()
        print(f"identical bytes: {digest(a) == digest(b)}")
        local, ray = (statistics.median(t) for t in times.values())
        print(f"median of {args.repeat}: local {local:.1f} s, Ray {ray:.1f} s for {frames} frames")
        print(f"Ray steady-state overhead vs the local pool: {100 * (ray / local - 1):+.1f} %")
        print(f"(plus the cluster start, once per cluster: {start_s:.1f} s)")
        per_frame_core = 2 * ray / frames  # core-seconds per frame on this machine, Ray included
        print("estimate for 100,000 frames (CPU time scales with nodes; per-node cores as here):")
        for nodes, cores in ((1, 2), (4, 16), (16, 16), (64, 16)):
            minutes = 100_000 * per_frame_core / (nodes * cores) / 60
            print(f"  {nodes:>3} node(s) x {cores:>2} cores: {minutes:7.1f} min")
    finally:
        cluster.close()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
