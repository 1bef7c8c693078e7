"""``bopsurg generate``: replay recorded bags from randomised viewpoints into a BOP dataset."""

from __future__ import annotations

import argparse
import logging
import time

from bopsurg.errors import InputError

log = logging.getLogger(__name__)

HELP = "replay bags from randomised endoscope viewpoints and lighting into a BOP dataset"

DESCRIPTION = """\
Replay each recording (rosbag) --replays times from randomised endoscope (ECM) viewpoints
and lighting in a headless renderer (PyBullet), and write a BOP dataset:

  DATASET/models/obj_000001.ply (+ models_info.json)   the needle (obj 1), built by code
  DATASET/camera.json, DATASET/test_targets_bop19.json
  DATASET/SPLIT/SCENE/{rgb,depth,mask,mask_visib}/     one scene per (bag, replay)
  DATASET/SPLIT/SCENE/scene_camera.json, scene_gt.json, scene_gt_info.json
  DATASET/SPLIT/SCENE/bopsurg_scene.json                the drawn viewpoint, light and seed
  DATASET/SPLIT/bopsurg_generate.json                   settings, seed, bag checksums

Scene ids: bag i (0-based, in command-line order), replay r -> scene i*replays + r + 1.
A frame is written every --period seconds of the recording; frames whose needle
visib_fract is below --min-visib are dropped. Depth is uint16 with depth_scale 0.1 mm.
Rerun the same command after an interruption: it resumes, and the same seed gives
byte-identical files.
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the subcommand."""
    from bopsurg.generators.replay import GenerateSettings

    d = GenerateSettings()
    p = sub.add_parser(
        "generate",
        help=HELP,
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("bags", nargs="+", metavar="BAG", help="recordings (ROS1 .bag or ROS2 folder)")
    p.add_argument("--out", required=True, metavar="DATASET", help="dataset root (created)")
    p.add_argument("--split", default="test", help="split folder (default: test)")
    p.add_argument("--replays", type=int, default=d.replays, help="replays per bag (default: 20)")
    p.add_argument(
        "--period", type=float, default=d.period, help="seconds between frames (default: 0.5)"
    )
    p.add_argument("--seed", type=int, default=d.seed, help="dataset seed (default: 0)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default: 1)")
    p.add_argument(
        "--min-visib",
        type=float,
        default=d.min_visib,
        help="drop frames whose needle visib_fract is below this (default: 0.1)",
    )
    p.add_argument(
        "--delta", type=float, default=d.delta_mm, help="visibility tolerance, mm (default: 1)"
    )
    p.add_argument("--topic-map", default=d.topic_map, help="topic map: crtk, ambf or a TOML file")
    p.add_argument("--stereo", action="store_true", help="also render the right camera")
    p.add_argument(
        "--annotate-instruments",
        action="store_true",
        help="annotate instrument parts as further objects (obj_id 2, 3, ...)",
    )
    p.add_argument("--renderer", choices=("tiny", "egl"), default="tiny", help="PyBullet renderer")
    p.add_argument("--backend", default=d.backend, help="generator backend plugin (pybullet)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Generate the dataset and report what was written."""
    from bopsurg.generators.generate import generate_dataset
    from bopsurg.generators.replay import GenerateSettings

    if args.period <= 0:
        raise InputError("must be > 0", field="--period")
    settings = GenerateSettings(
        replays=args.replays,
        period=args.period,
        seed=args.seed,
        min_visib=args.min_visib,
        delta_mm=args.delta,
        stereo=args.stereo,
        topic_map=args.topic_map,
        backend=args.backend,
        backend_config={
            "annotate_instruments": bool(args.annotate_instruments),
            "renderer": args.renderer,
        },
    )
    t0 = time.perf_counter()
    report = generate_dataset(
        args.bags,
        args.out,
        split=args.split,
        settings=settings,
        workers=args.workers,
        progress=not args.no_progress,
    )
    dt = time.perf_counter() - t0
    rate = report.frames_rendered / dt if dt > 0 else 0.0
    print(
        f"{args.out}: {report.scenes} scenes ({report.scenes_skipped} already done), "
        f"{report.frames_written} frames written of {report.frames_rendered} rendered "
        f"in {dt:.1f} s ({rate:.1f} frames/s)"
    )
    return 0
