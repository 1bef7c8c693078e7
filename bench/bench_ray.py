"""Bench: `bopsurg generate` on the local process pool vs a local Ray cluster, same 2 cores.

Records a seeded bag, generates the same replays with ``--executor local --workers 2`` and
with ``--executor ray`` on a two-node Ray cluster (1 CPU each, in a loopback-only network
namespace: needs root and iproute2), checks the bytes are equal, prints frames/s and the Ray
overhead, and estimates from the measured per-replay cost the time of a 100,000-frame dataset
on N nodes.

    sudo python bench/bench_ray.py [--replays 6] [--duration 20]
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bopsurg.generators.bags import write_bag
from bopsurg.generators.trajectory import synthesize_suturing
from tests.ray_netns import PORT, Cluster, netns_available


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
    ap.add_argument("--replays", type=int, default=6)
    ap.add_argument("--duration", type=float, default=20.0)
    args = ap.parse_args()
    if not netns_available():
        sys.exit("needs root and ip netns")
    work = Path(tempfile.mkdtemp(prefix="bopsurg-ray-"))
    cluster = Cluster(nodes=2, cpus_per_node=1)
    try:
        bag = work / "a.bag"
        write_bag(bag, synthesize_suturing(seed=0, duration=args.duration))
        common = f"--replays {args.replays} --period 0.5 --seed 3 --min-visib 0 --no-progress"
        runs = {
            "local pool, 2 workers": "--executor local --workers 2",
            "Ray, 2 nodes x 1 CPU": f"--executor ray --ray-address 127.0.0.1:{PORT}",
        }
        rates, outs = {}, {}
        frames = 0
        for label, opts in runs.items():
            out = work / label.split(",")[0].replace(" ", "_")
            t0 = time.perf_counter()
            r = cluster.sh(f"bopsurg generate {bag} --out {out} {common} {opts}")
            dt = time.perf_counter() - t0
            frames = int(r.stdout.split(" frames written")[0].split()[-1])
            rates[label], outs[label] = frames / dt, out
            print(f"  {label:<24} {frames / dt:6.2f} frames/s ({frames} frames, {dt:.1f} s)")
        a, b = outs.values()
        print(f"  identical bytes: {digest(a) == digest(b)}")
        local, ray = rates.values()
        print(f"  Ray overhead vs the local pool: {100 * (local / ray - 1):+.1f} %")
        per_frame_core = 2 / ray  # core-seconds per frame on this machine, Ray included
        print("estimate for 100,000 frames (CPU time scales with nodes; per-node cores as here):")
        for nodes, cores in ((1, 2), (4, 16), (16, 16), (64, 16)):
            hours = 100_000 * per_frame_core / (nodes * cores) / 3600
            print(f"  {nodes:>3} node(s) x {cores:>2} cores: {hours:6.2f} h")
    finally:
        cluster.close()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
