"""``bopsurg inspect``: what a recording holds and what ``bopsurg generate`` will do with it."""

from __future__ import annotations

import argparse

HELP = "show a bag's topics, the streams generate finds in it, and the kinematics check"

DESCRIPTION = """\
For each bag (ROS1 .bag file, ROS2 sqlite3 or MCAP folder): its topics (message type, count,
rate, header frame), the streams the topic map finds (each PSM's joints, Cartesian pose and
jaw, the ECM, the needle, bopsurg's meta), whose kinematics replay it (a bag bopsurg wrote:
the simulator's; any other: the real dVRK's, tool --psm-tool), and what 'bopsurg generate'
will do with it: which arms it renders, which one holds the needle, how the camera is placed,
how many frames a replay writes.

For every arm recorded with both joints and Cartesian poses (measured_cp), the line
  fk-check PSM2: N pairs, rms X mm, max Y mm, rotation rms A deg, max B deg
gives the tool-tip residuals of the forward kinematics, rigidly registered (no scale) to
the recorded poses, samples paired by header stamp: well under 0.1 mm when the kinematics
(tool) are the robot's.
"""

EPILOG = """\
examples:
  bopsurg inspect pitch_exp_traj_01.bag
  bopsurg inspect recordings/*.bag --joints setpoint --psm-tool PROGRASP_FORCEPS_400093
"""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``inspect`` subcommand."""
    from bopsurg.generators.cli_generate import add_recording_args

    p = sub.add_parser(
        "inspect",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("bags", nargs="+", metavar="BAG", help="recordings (ROS1 .bag or ROS2 folder)")
    p.add_argument("--topic-map", default="crtk", help="topic map: crtk, ambf or a TOML file")
    p.add_argument(
        "--period", type=float, default=0.5, help="generate's seconds between frames (default 0.5)"
    )
    add_recording_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Print the report of every bag."""
    from bopsurg.errors import InputError
    from bopsurg.generators.inspect_bag import inspect_bag

    if args.period <= 0:
        raise InputError("must be > 0", field="--period")
    for k, bag in enumerate(args.bags):
        report = inspect_bag(
            bag,
            topic_map=args.topic_map,
            joint_source=args.joints,
            psm_tool=args.psm_tool,
            needle_holder=args.needle_holder,
            period=args.period,
        )
        if k:
            print()
        print("\n".join(report.lines()))
    return 0
