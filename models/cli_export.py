"""``bopsurg export``: the built-in estimator's networks to ONNX, checked against torch."""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from bopsurg.errors import BopsurgError

HELP = "export the detector, pose head(s) and needle segmenter to ONNX (+ JSON metadata)"

DESCRIPTION = """\
Export the networks of the built-in 'gdrnet' estimator to ONNX, one NAME.onnx and NAME.json
per checkpoint in --out. Defaults: the shipped detector, pose head and needle segmenter
(models/weights). The JSON beside each model holds what running it needs without torch:
input/output names and shapes, classes, input size, letterbox grey, the xyz normaliser, crop
padding and zoom, the needle's arc, and the source checkpoint's SHA-256.

The batch axis is free in every model, and the detector's input height and width too
(multiples of 32). With onnxruntime installed (pip install 'bopsurg[onnx]') every export is
checked: onnxruntime's outputs on seeded sample inputs must equal torch's to 1e-4, else the
command fails.

Run the exported pipeline (detector + pose head, direct decoding; no torch):
  bopsurg predict DATASET --split test --out results.csv \\
      --estimator gdrnet-onnx --option dir=DIR
  python -m bopsurg.models.onnx_runtime DIR image.png --K fx,fy,cx,cy
"""

EPILOG = """\
examples:
  bopsurg export --out exported
  bopsurg export --out exported --detector runs/det/detector.pt --pose runs/pose/pose.pt \\
      --segmenter none
"""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "export",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", metavar="DIR", required=True, help="folder to write (created)")
    p.add_argument("--detector", metavar="PT", help="detector checkpoint, or 'none'")
    p.add_argument(
        "--pose", metavar="PT", action="append", help="pose-head checkpoint (repeat per object)"
    )
    p.add_argument("--segmenter", metavar="PT", help="needle-segmenter checkpoint, or 'none'")
    p.add_argument("--opset", type=int, default=None, help="ONNX opset (default 17)")
    p.add_argument(
        "--exporter",
        choices=("torchscript", "dynamo"),
        default="torchscript",
        help="torch's exporter: torchscript (default) or dynamo (needs onnxscript)",
    )
    p.add_argument("--no-check", action="store_true", help="skip the onnxruntime comparison")
    p.set_defaults(func=run)


def _chosen(value: str | None, role: str) -> Path | None:
    """The checkpoint a flag names (default: the shipped one, which must exist), or None."""
    from bopsurg.models.predict_config import weight_file

    if value is not None and value.lower() == "none":
        return None
    path: Path = weight_file(role, "shipped" if value is None else value)
    return path


def run(args: argparse.Namespace) -> int:
    """Execute the subcommand."""
    from bopsurg.models import export

    jobs: list[tuple[Path, object]] = []
    det = _chosen(args.detector, "detector")
    if det is not None:
        jobs.append((det, export.load_detector))
    for pose in args.pose or [None]:
        pose_path = _chosen(pose, "pose")
        if pose_path is not None:
            jobs.append((pose_path, export.load_pose_head))
    seg = _chosen(args.segmenter, "segmenter")
    if seg is not None:
        jobs.append((seg, export.load_segmenter))
    if not jobs:
        raise BopsurgError("export: nothing to export (every model is 'none')")
    names = [p.stem for p, _ in jobs]
    if len(set(names)) != len(names):
        raise BopsurgError(f"export: two checkpoints share a file name {names}; rename one")
    check = not args.no_check and importlib.util.find_spec("onnxruntime") is not None
    if not args.no_check and not check:
        print("onnxruntime is not installed: exported without the check (bopsurg[onnx])")
    opset = args.opset or export.DEFAULT_OPSET
    worst = 0.0
    for path, load in jobs:
        item = load(path)  # type: ignore[operator]
        onnx_path = export.write_export(
            item, args.out, source=path, opset=opset, exporter=args.exporter
        )
        size = onnx_path.stat().st_size / 2**20
        line = f"{item.kind:10s} {path} -> {onnx_path} ({size:.1f} MiB)"
        if check:
            diff = export.max_difference(onnx_path, item)
            worst = max(worst, diff)
            line += f", max |onnxruntime - torch| = {diff:.2e}"
        print(line)
    if worst > export.CHECK_ATOL:
        raise BopsurgError(
            f"export: onnxruntime differs from torch by {worst:.2e} > {export.CHECK_ATOL:g}"
        )
    return 0
