"""``bopsurg import``: bring data of other pipelines (the paper's AMBF one) in as BOP datasets."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of
from bopsurg.cli.progress import add_progress_arg

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers

HELP = help_of("import")

#: Default of --delta, mm: bopsurg.ambf_import.AMBF_DELTA_MM (a test keeps them equal;
#: importing the importer here would make 'bopsurg import --help' load OpenCV).
AMBF_DELTA_MM = 1.0

DESCRIPTION = """\
Turn data written by the paper's AMBF pipeline into a BOP dataset that 'bopsurg check'
accepts and 'bopsurg predict' / 'bopsurg eval' run on. The dataset is built in a temporary
folder and appears only when complete: bad or partial input leaves nothing behind.

  ambf-yaml SRC   the per-frame YAML layout: raw_img/NNNNN.png, depth_img/NNNNN.png (uint16,
                  1 unit = --depth-scale mm), intrinsic.yaml ('fx, 0, cx, 0, fy, cy, 0, 0, 1')
                  and extrinsic.yaml ('NNNNN': rot_model2cam, t_model2cam; model to camera,
                  mm). Writes one scene (000001, image ids = frame numbers) with rgb/, depth/,
                  scene_camera.json, scene_gt.json (the needle is obj_id 1), the needle model
                  and models_info.json (tip, tail and plane normal fitted from the mesh), then
                  masks, scene_gt_info.json and test targets as 'bopsurg annotate' does.
                  --model is the needle mesh the poses refer to: the pipeline's Needle.ply (in
                  mm). Without it, bopsurg's needle placed in the AMBF needle's frame is used.
  bop SRC         a BOP dataset whose objects start at obj_id 0 (the pipeline's BOP writer
                  numbers its needle 0): a copy with every obj_id shifted by --obj-id-offset;
                  scenes without scene_gt_info.json are annotated.

Masks need the depth renderer plugin (pip install 'bopsurg[vsd]').
"""

EPILOG = """\
examples:
  bopsurg import ambf-yaml needle_dataset_V0.0.1 --out data/ambf --model Needle.ply
  bopsurg check data/ambf
  bopsurg predict data/ambf --out ambf.csv      # poses mapped into Needle.ply's frame
  bopsurg eval data/ambf ambf.csv --out eval/
  bopsurg import bop needle_gripper_dataset --out data/gripper --obj-id-offset 1
"""


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "import",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("layout", choices=("ambf-yaml", "bop"), help="what SRC is (see above)")
    p.add_argument("src", metavar="SRC", help="the folder to import")
    p.add_argument("--out", required=True, metavar="DATASET", help="dataset folder to create")
    p.add_argument(
        "--model", default=None, metavar="PLY", help="ambf-yaml: the needle mesh (mm) of the poses"
    )
    p.add_argument("--split", default="test", help="ambf-yaml: split folder (default: test)")
    p.add_argument(
        "--depth-scale",
        type=float,
        default=1.0,
        help="ambf-yaml: mm per stored depth unit (default: 1, as the AMBF pipeline writes)",
    )
    p.add_argument(
        "--obj-id-offset",
        type=int,
        default=1,
        help="bop: added to every obj_id (default: 1, so the needle's 0 becomes 1)",
    )
    p.add_argument(
        "--delta",
        type=float,
        default=AMBF_DELTA_MM,
        help="visibility tolerance of the masks in mm (default: 1, as the AMBF pipeline; "
        "BOP's 15 would count tissue a few mm in front of the needle as not occluding)",
    )
    p.add_argument("--renderer", default=None, help="depth renderer plugin (default: first)")
    add_progress_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Import and report."""
    import numpy as np

    from bopsurg.ambf_import import import_ambf_yaml, import_bop_renumbered
    from bopsurg.plugins import load_plugin

    if args.layout == "ambf-yaml":
        renderer = load_plugin("renderer", args.renderer)  # fail early, with a hint, if missing
        rep = import_ambf_yaml(
            args.src,
            args.out,
            model=args.model,
            split=args.split,
            depth_scale=args.depth_scale,
            delta=args.delta,
            renderer=renderer(),
            progress=not args.no_progress,
        )
        arc = rep.arc
        v = np.asarray(rep.visib_fract)
        print(
            f"needle model: arc radius {arc.radius:.2f} mm over {arc.extent_deg:.1f} deg, wire "
            f"radius {arc.wire_radius:.2f} mm (fit RMS {arc.rms_mm:.3f} mm)"
        )
        print(
            f"{args.out}: {rep.images} images of {args.src} imported "
            f"({'with' if rep.with_depth else 'without'} depth), needle visib_fract "
            f"{v.min():.2f}-{v.max():.2f} (median {np.median(v):.2f})"
        )
        split = args.split
    else:
        rep2 = import_bop_renumbered(
            args.src,
            args.out,
            obj_id_offset=args.obj_id_offset,
            delta=args.delta,
            renderer_name=args.renderer,
            progress=not args.no_progress,
        )
        ids = ", ".join(f"{a}->{b}" for a, b in rep2.obj_ids.items())
        done = f"; annotated {', '.join(rep2.annotated_splits)}" if rep2.annotated_splits else ""
        print(f"{args.out}: {rep2.instances} GT instances, obj_ids renumbered {ids}{done}")
        split = "test"
    print(f"next: bopsurg check {args.out} --split {split}")
    return 0
