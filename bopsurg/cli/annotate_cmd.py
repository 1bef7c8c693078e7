"""``bopsurg annotate``: masks and scene_gt_info from GT poses, models and depth."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of
from bopsurg.cli.progress import add_progress_arg
from bopsurg.plugins import load_plugin

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers

HELP = help_of("annotate")

#: Default of --delta, mm: bopsurg.visibility.DEFAULT_DELTA_MM (a test keeps them equal;
#: importing it here would load numpy just to build the parser).
DEFAULT_DELTA_MM = 15.0

DESCRIPTION = """\
Fill in what the BOP toolkit's calc_gt_masks.py and calc_gt_info.py compute, with the same
definitions, headless and with no OpenGL install: every GT instance is rendered alone at its
GT pose (on a 3x canvas, so truncated parts count) by a depth renderer plugin (PyBullet's,
from bopsurg[vsd]), then

  mask/IM_GT.png          amodal silhouette inside the image
  mask_visib/IM_GT.png    visible part: (d_model - d_test <= delta) or no depth, bop19 rule
  scene_gt_info.json      bbox_obj, bbox_visib, px_count_all/valid/visib, visib_fract
  test_targets_bop19.json when missing (instances with visib_fract >= 0.1)

Without depth images, visibility comes from the GT instances rendered against each other.
Scenes that already have scene_gt_info.json are left alone unless --overwrite.
"""


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "annotate",
        help=HELP,
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", help="dataset root folder")
    p.add_argument("--split", default="test", help="split folder name (default: test)")
    p.add_argument("--split-type", default=None, help="split type suffix, e.g. pbr")
    p.add_argument(
        "--delta",
        type=float,
        default=DEFAULT_DELTA_MM,
        help="visibility tolerance in mm (default: 15 as BOP; 5 for PBR images, 1 for exact "
        "synthetic depth of thin instruments)",
    )
    p.add_argument("--renderer", default=None, help="depth renderer plugin (default: first)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default: 1)")
    p.add_argument("--overwrite", action="store_true", help="redo scenes already annotated")
    add_progress_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Annotate and report."""
    from bopsurg.annotate import annotate_dataset

    load_plugin("renderer", args.renderer)  # fail early, with a one-line hint, if missing
    report = annotate_dataset(
        args.dataset,
        args.split,
        renderer_name=args.renderer,
        workers=args.workers,
        split_type=args.split_type,
        delta=args.delta,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    source = "depth images" if report.with_depth else "GT instances rendered together (no depth)"
    print(
        f"{args.dataset}: {report.instances} instances annotated in "
        f"{report.scenes - report.scenes_skipped} scenes ({report.scenes_skipped} left as they "
        f"were); visibility from {source}"
    )
    return 0
