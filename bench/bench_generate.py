"""Bench: annotated 640×480 frames per second of `bopsurg generate`, and its scaling.

Records one seeded bag, then generates the same replays with 1 and 2 worker processes
(RGB + depth + masks + gt_info written) and, in the same run, times the backend's
render-only rate (full scene + the needle's amodal render, nothing written) as the bound.
Ends with the time a paper-sized dataset (7,934 frames) would take at the measured rate.

    python bench/bench_generate.py [--replays 4] [--duration 20] [--period 0.5]
        [--domain paper|wide] [--workers 1 2] [--no-render-only]

With one worker the replays run in this process, and its CPU time per frame is printed
too: on a shared machine it compares profiles (``--domain``) better than wall time.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from bopsurg.generators.bags import read_bag, write_bag
from bopsurg.generators.generate import generate_dataset, make_backend
from bopsurg.generators.kinematics import ecm_camera_pose
from bopsurg.generators.replay import GenerateSettings, _camera, frame_times
from bopsurg.generators.trajectory import synthesize_suturing
from bopsurg.generators.viewpoints import draw_replay, light_in_world

PAPER_FRAMES = 7934


def render_only(settings: GenerateSettings, bag: Path, frames: int) -> float:
    rec = read_bag(bag, topic_map=settings.topic_map)
    backend = make_backend(settings)
    draw = draw_replay(np.random.default_rng(0), 0)
    T = ecm_camera_pose(draw.ecm_joints)
    cam, cam_large = _camera(settings, T), _camera(settings, T, large=True)
    light = light_in_world(draw, T)
    times = frame_times(rec.start, rec.end, settings.period)[:frames]
    t0 = time.perf_counter()
    for t in times:
        backend.set_state(rec.state_at(float(t)))
        backend.render(cam, light)
        backend.render_object_depth("needle", cam_large)
    dt = time.perf_counter() - t0
    backend.close()
    return len(times) / dt


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--replays", type=int, default=4)
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of recording")
    ap.add_argument("--period", type=float, default=0.5)
    ap.add_argument("--renderer", choices=("tiny", "egl"), default="tiny")
    ap.add_argument("--domain", choices=("paper", "wide"), default="paper")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--no-render-only", action="store_true", help="skip the render-only bound")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bopsurg-bench-"))
    try:
        bag = work / "a.bag"
        write_bag(bag, synthesize_suturing(seed=0, duration=args.duration))
        settings = GenerateSettings(
            replays=args.replays,
            period=args.period,
            min_visib=0.0,  # keep every frame: measure the full per-frame cost
            backend_config={"renderer": args.renderer},
            domain=args.domain,
        )
        n_frames = len(frame_times(0.0, args.duration, args.period)) * args.replays
        print(
            f"{args.replays} replays x {args.duration:g} s at {args.period:g} s -> "
            f"{n_frames} frames, 640x480, renderer {args.renderer}, domain {args.domain}"
        )
        if not args.no_render_only:
            bound = render_only(settings, bag, 40)
            print(f"  render only (scene + amodal needle):  {bound:6.1f} frames/s (1 process)")
        rates = {}
        for workers in args.workers:
            out = work / f"ds{workers}"
            t0, c0 = time.perf_counter(), time.process_time()
            rep = generate_dataset([bag], out, settings=settings, workers=workers, progress=False)
            dt, cpu = time.perf_counter() - t0, time.process_time() - c0
            rates[workers] = rep.frames_written / dt
            # one worker runs in this process: its CPU time is the cost, whatever else runs
            own = f", {1e3 * cpu / rep.frames_written:.0f} ms CPU/frame" if workers == 1 else ""
            print(
                f"  generate, {workers} worker(s):            {rates[workers]:6.1f} frames/s "
                f"({rep.frames_written} frames in {dt:.1f} s{own})"
            )
        if 1 in rates and 2 in rates:
            print(f"  scaling 1 -> 2 workers: {rates[2] / rates[1]:.2f}x")
        best = max(rates.values())
        print(
            f"paper-sized dataset ({PAPER_FRAMES} frames) at {best:.1f} frames/s: "
            f"{PAPER_FRAMES / best / 60:.1f} min"
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
