"""``bopsurg predict``: run a pose estimator plugin over a dataset split, write a results CSV."""

from __future__ import annotations

import argparse
import logging
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of
from bopsurg.cli.inputs import key_value
from bopsurg.errors import BopsurgError

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers

log = logging.getLogger(__name__)

HELP = help_of("predict")

#: Images per call of the estimator by default (``--batch-size``).
DEFAULT_BATCH = 8

DESCRIPTION = """\
Estimate the 6D poses of the objects in every target image of a BOP dataset split and
write a BOP19 results CSV (scene_id,im_id,obj_id,score,R,t,time; R row-major, t in mm,
time = the estimator's run time for the image in s, image decoding excluded), ready for
'bopsurg eval'. Images go to the estimator --batch-size at a time (the next batch is decoded
meanwhile); each image's time is its batch's time divided by the batch's images.

Images: those of DATASET/test_targets_bop19.json in the split when the file exists (with the
objects it lists), else every image of the split. An interrupted run resumes from
RESULTS.partial.

The built-in estimator 'gdrnet' (pip install bopsurg[torch]) runs a YOLOX-like detector and
a GDR-Net-like pose head; without --detector/--pose it uses the small model shipped with
bopsurg (see 'bopsurg train --help' to train your own). Other estimators register under the
'bopsurg.estimators' entry-point group.

Settings: --config FILE (YAML) and --option KEY=VALUE (repeatable; dotted keys reach nested
settings, values are YAML: refine.depth.weight=8, head.zoom=[1], ends.classifier=none) are
laid over the estimator's defaults, in that order, then --detector/--pose/--device. Every
setting of gdrnet, with its default and unit, is in bopsurg.models.predict_config (the docs'
configuration page). The resolved settings are written to RESULTS.config.yaml beside the
results: a --config file that reproduces the run.

Model frames: a pose only means something in the frame of its object model. When the
estimator says which needle model it was trained on and the dataset's model differs (e.g. the
AMBF pipeline's Needle.ply, your own CAD needle), the poses are mapped into the dataset's
model frame through the two fitted needle arcs (one line says so); needles of different
radius or arc, or models that are not needles, are refused.

Depth: an estimator that uses depth images gets each image's (DATASET's depth/ folder, in mm
through scene_camera's depth_scale) unless --no-depth. gdrnet's refinement then fits the
needle's arc to the 3D points of its visible mask, which fixes the tilt and the distance that
the image alone leaves uncertain; --no-depth (or --option refine.depth.mode=none) is the
RGB-only method, the one the paper evaluates. The run prints which input it used.
"""

EPILOG = """\
examples:
  bopsurg predict data/needle --split test --out results.csv
  bopsurg predict data/needle --out results.csv --detector runs/det/detector.pt \\
      --pose runs/pose/pose.pt --device cuda
  bopsurg predict data/needle --out results.csv --boxes yolox_boxes.json   # external boxes
  bopsurg eval data/needle results.csv --out eval/
"""


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "predict",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", help="dataset root folder (holds the split folders)")
    p.add_argument("--split", default="test", help="split folder name (default: test)")
    p.add_argument("--split-type", default=None, help="split type suffix, e.g. pbr")
    p.add_argument("--out", required=True, metavar="RESULTS.csv", help="results CSV to write")
    p.add_argument("--estimator", default="gdrnet", help="estimator plugin name (default: gdrnet)")
    p.add_argument("--detector", default=None, metavar="CKPT", help="detector checkpoint (.pt)")
    p.add_argument("--pose", default=None, metavar="CKPT", help="pose head checkpoint (.pt)")
    p.add_argument(
        "--device", default=None, help="cpu, cuda, cuda:1 ... (default: auto = cuda if any)"
    )
    p.add_argument(
        "--config",
        default=None,
        metavar="FILE.yaml",
        help="the estimator's settings (YAML; e.g. a RESULTS.config.yaml of an earlier run)",
    )
    p.add_argument(
        "--option",
        type=key_value,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="one setting, over --config (repeatable; dotted keys: refine.depth.weight=8)",
    )
    p.add_argument(
        "--boxes",
        default=None,
        metavar="DETECTIONS.json",
        help="2D boxes from another detector (BOP detections JSON) instead of our detector",
    )
    p.add_argument(
        "--detections-out",
        default=None,
        metavar="FILE.json",
        help="also write the 2D box of every estimate (BOP COCO results JSON: bopsurg eval "
        "scores it with --task coco-bbox)",
    )
    p.add_argument(
        "--no-depth",
        action="store_true",
        help="RGB only: give the estimator no depth images (by default an estimator that uses "
        "depth, like gdrnet's depth fit, gets each image's depth when the dataset has one)",
    )
    p.add_argument(
        "--batch-size",
        type=int,
        default=DEFAULT_BATCH,
        metavar="N",
        help=f"images per call of the estimator (default: {DEFAULT_BATCH}; 1: image by image). "
        "gdrnet runs its networks and fits on the whole batch at once; the same poses at any N",
    )
    p.add_argument("--max-images", type=int, default=None, help="stop after N images")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Execute the subcommand."""
    from bopsurg.bop.dataset import BopDataset
    from bopsurg.bop.detections import load_detections
    from bopsurg.estimation import (
        estimator_config,
        estimator_report,
        estimator_uses_depth,
        load_estimator,
    )
    from bopsurg.options import plugin_options
    from bopsurg.prediction import predict_dataset, save_run_config

    if args.max_images is not None and args.max_images < 1:
        raise BopsurgError(f"--max-images must be >= 1, got {args.max_images}")
    if args.batch_size < 1:
        raise BopsurgError(f"--batch-size must be >= 1, got {args.batch_size}")
    dataset = BopDataset(args.dataset, args.split, split_type=args.split_type)
    options = plugin_options(args.config, args.option, {"device": "auto"})
    for key in ("device", "detector", "pose"):
        if getattr(args, key) is not None:
            options[key] = getattr(args, key)
    boxes = None
    if args.boxes is not None:
        boxes, _ = load_detections(args.boxes)
    estimator = load_estimator(args.estimator, options)
    written = save_run_config(args.out, args.estimator, estimator_config(estimator) or options)
    done = predict_dataset(
        dataset,
        estimator,
        args.out,
        boxes=boxes,
        detections_out=args.detections_out,
        max_images=args.max_images,
        progress=not args.no_progress,
        depth=not args.no_depth,
        batch_size=args.batch_size,
    )
    print(
        f"{len(done.estimates)} estimates in {done.images} images, "
        f"{1000 * done.mean_time:.1f} ms per image -> {args.out}"
    )
    if estimator_uses_depth(estimator):
        print(
            "input: RGB only (--no-depth)"
            if args.no_depth
            else f"input: RGB-D (depth images of {done.depth_images} images)"
        )
    print(f"settings: {written}")
    report = estimator_report(estimator)
    if report:
        print(f"{args.estimator}: {report}")
    if len(done.estimates) == 0:
        log.warning("the estimator found nothing in %d images", done.images)
    print(f"next: bopsurg eval {args.dataset} {args.out} --split {args.split} --out EVAL_DIR")
    return 0
