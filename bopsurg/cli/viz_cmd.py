"""``bopsurg viz``: evaluate a results CSV and write a rerun recording for error analysis."""

from __future__ import annotations

import argparse
import logging
import time
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of
from bopsurg.cli.inputs import (
    add_dataset_and_results,
    add_detections_arg,
    load_dataset_and_results,
    load_detections_arg,
)

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers

log = logging.getLogger(__name__)

HELP = help_of("viz")

DESCRIPTION = """\
Evaluate 6D pose estimates on a BOP dataset split (as 'bopsurg eval', without VSD) and write
a rerun recording: per image the RGB with GT (blue) and estimated (green) silhouettes, the 3D
camera and needle meshes, per-frame RE/TE/MSSD series, histograms, the paper's table and the
list of the worst frames (largest MSSD). Needs bopsurg[rerun]; open with 'rerun FILE.rrd'.

Images go for every frame up to 100 frames; beyond that for the 100 worst frames plus 100
spread uniformly over the others (with --max-frames N: N/2 worst, the rest spread), while the
scalar series cover every frame.
"""


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "viz",
        help=HELP,
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_dataset_and_results(p)
    p.add_argument("--out", required=True, metavar="FILE.rrd", help="rerun recording to write")
    p.add_argument(
        "--min-visib",
        type=float,
        default=0.3,
        help="visibility threshold of the paper's table (default: 0.3)",
    )
    p.add_argument(
        "--max-frames",
        type=int,
        default=None,
        help="at most this many frames with images (default: all up to 100, "
        "else the 100 worst + 100 spread)",
    )
    p.add_argument("--worst", type=int, default=20, help="length of the worst-frames list")
    add_detections_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Evaluate, then log the recording."""
    from bopsurg.evaluation.runner import evaluate
    from bopsurg.viz import log_evaluation

    t0 = time.perf_counter()
    dataset, est = load_dataset_and_results(args)
    boxes = load_detections_arg(args)
    result = evaluate(dataset, est, min_visib=args.min_visib)
    rrd = log_evaluation(
        dataset, est, result, args.out, max_frames=args.max_frames, worst=args.worst,
        detections=boxes,
    )  # fmt: skip
    print(f"wrote {rrd} ({len(est)} estimates, {time.perf_counter() - t0:.1f} s)")
    print(f"open it with: rerun {rrd}")
    return 0
