"""``bopsurg check``: validate a BOP dataset and list every problem, one line each."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of
from bopsurg.cli.inputs import add_dataset
from bopsurg.cli.progress import add_progress_arg

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers

HELP = help_of("check")

DESCRIPTION = """\
Validate a BOP dataset split and print one line per problem: file, field, what is wrong.

Checks models_info.json and the PLY models, camera.json, every scene's scene_camera,
scene_gt and scene_gt_info (schemas, image ids agreeing across files, known obj_ids, R
orthonormal, K and depth_scale sane), that rgb/depth/mask files exist with the right size,
that mask_visib pixel counts and boxes agree with scene_gt_info, and test_targets_bop19.json.

A standard BOP dataset (lmo, tless, ycbv, itodd, hb, icbin, tudl, hope, hot3d, handal, ipd,
xyzibd ...), recognised by the folder's name or --dataset NAME, is checked with its
registered defaults: split type (tless test -> test_primesense), camera file, image size,
the per-stream files of multi-stream layouts (scene_gt_{stream}.json); see docs/datasets.md.

Exit code: 0 when the dataset is valid, 1 when problems were found, 2 on a usage error.
"""


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "check",
        help=HELP,
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_dataset(p)
    p.add_argument("--no-images", action="store_true", help="skip reading images and masks")
    p.add_argument(
        "--max-problems", type=int, default=None, metavar="N", help="stop after N problems"
    )
    add_progress_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the check; returns 0 when valid, 1 when problems were found."""
    from bopsurg.bop.check import check_dataset

    problems = check_dataset(
        args.dataset,
        split=args.split,
        split_type=args.split_type,
        check_images=not args.no_images,
        max_problems=args.max_problems,
        progress=not args.no_progress,
        dataset=args.dataset_name,
    )
    for problem in problems:
        print(problem)
    if problems:
        print(f"{len(problems)} problem(s) found")
        return 1
    print(f"{args.dataset}: OK")
    return 0
