"""``bopsurg record``: synthesise a seeded suturing episode and write it as a rosbag."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from bopsurg.errors import InputError
from bopsurg.generators.bags import write_bag
from bopsurg.generators.trajectory import synthesize_suturing

log = logging.getLogger(__name__)

HELP = "synthesise a suturing episode (two dVRK PSMs and a needle) into a rosbag"

DESCRIPTION = """\
Synthesise a realistic, seeded suturing episode and write it as a rosbag (ROS1 .bag file,
or a ROS2 bag folder with sqlite3 or MCAP storage) for 'bopsurg generate' to replay.

The episode: the needle rests on the tissue; PSM1 approaches with open jaws, grasps it near
the tail and drives it along its own arc through the tissue (entry and exit a chord apart);
PSM2 grasps the emerged tip side (hand-off), PSM1 lets go and PSM2 pulls the needle through.
Given time (about 35 s or more), PSM2 hands the needle back for a second throw. Motions are
minimum-jerk with pauses, speed changes and 8-12 Hz hand tremor; joints come from inverse
kinematics within the PSM limits. The same --seed always gives the same bag.
With --object-model PLY the episode is planned for that needle (its fitted arc radius,
extent and wire); the bag records them, and 'bopsurg generate' replays it with them.

Topics (stamps: header = bag time; t = 0 at 2023-11-14T22:13:20Z unless recorded otherwise):
  /psm1/measured_js, /psm2/measured_js     sensor_msgs/JointState  6 joints: outer_yaw,
                                           outer_pitch, outer_insertion [m], outer_roll,
                                           outer_wrist_pitch, outer_wrist_yaw [rad]
  /psm1/jaw/measured_js, /psm2/jaw/...     sensor_msgs/JointState  jaw opening [rad]
                                           (<= 0.2 holds the needle)
  /ecm/measured_js                         sensor_msgs/JointState  endoscope yaw, pitch [rad],
                                           insertion [m], roll [rad]
  /needle/measured_cp                      geometry_msgs/PoseStamped  needle model frame in
                                           'world' [m] (tissue surface z = 0, +Z up)
  /bopsurg/meta                            std_msgs/String  JSON: seed, generator version,
                                           layout, needle spec, task events
"""

EPILOG = """\
examples:
  bopsurg record --out bags/ep001.bag --seed 1
  bopsurg record --out bags/ep002 --seed 2 --duration 45 --format mcap
  bopsurg record --out bags/mine.bag --seed 3 --object-model Needle.ply   # your needle
"""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``record`` subcommand."""
    p = sub.add_parser(
        "record",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out", required=True, help="bag to write: FILE.bag (ros1) or a folder (ros2, mcap)"
    )
    p.add_argument("--seed", type=int, required=True, help="random seed of the episode")
    p.add_argument("--duration", type=float, default=30.0, help="episode length, s (default 30)")
    p.add_argument("--rate", type=float, default=50.0, help="sample rate, Hz (default 50)")
    p.add_argument(
        "--format",
        choices=("ros1", "ros2", "mcap"),
        default=None,
        help="bag format (default: ros1 for a .bag name, else ros2 with sqlite3 storage)",
    )
    p.add_argument(
        "--object-model",
        metavar="PLY",
        default=None,
        help="plan the episode for this needle mesh (mm): its fitted radius, wire and arc "
        "(recorded in the bag; 'generate' then uses them)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Synthesise the episode, write the bag and print what was written."""
    t0 = time.perf_counter()
    out = Path(args.out)
    fmt = args.format or ("ros1" if out.suffix == ".bag" else "ros2")
    if (out.exists() or out.is_symlink()) and not args.overwrite:
        raise InputError("exists already; pass --overwrite to replace it", path=out)
    needle, mesh = None, None
    if args.object_model is not None:
        from bopsurg.generators.object_model import needle_spec_of_mesh

        needle, mesh = needle_spec_of_mesh(args.object_model)
    rec = synthesize_suturing(args.seed, duration=args.duration, rate_hz=args.rate, needle=needle)
    if mesh is not None:
        rec.meta["object_model"] = mesh.record()
        print(
            f"needle from {mesh.path}: radius {mesh.arc.radius:.2f} mm, arc "
            f"{mesh.arc.extent_deg:.1f} deg, wire {2 * mesh.arc.wire_radius:.2f} mm"
        )
    counts = write_bag(out, rec, format=fmt, overwrite=args.overwrite)
    throws = rec.meta["throws"]
    print(
        f"wrote {out} ({fmt}): seed {args.seed}, {rec.duration:.2f} s at {args.rate:g} Hz, "
        f"{throws} throw{'s' if throws > 1 else ''}, {time.perf_counter() - t0:.1f} s"
    )
    width = max(len(topic) for topic in counts)
    for topic, n in counts.items():
        print(f"  {topic:<{width}}  {n:6d} messages")
    return 0
