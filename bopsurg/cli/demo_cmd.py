"""``bopsurg demo``: the main job end to end on embedded defaults, nothing to download.

Each step runs its command's function in this process through
:func:`bopsurg.cli.commands.run_command`, with option values as Python values.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import json
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bopsurg.cli.commands import help_of, run_command
from bopsurg.cli.example_cmd import spec, spec_args
from bopsurg.cli.progress import add_progress_arg
from bopsurg.errors import BopsurgError
from bopsurg.plugins import available_plugins

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers

# Seeds the shipped model never trained on: bench/bench_estimators.py records its training
# episodes with seeds 1-4 and draws their viewpoints with seed 0 (its test set: 101-102 and 1).
# Episode k of the demo uses 1000·--seed + 200 + k and viewpoints 1000·--seed + 2.
DEMO_EPISODE_SEED = 200
DEMO_VIEW_SEED = 2

HELP = help_of("demo")

DESCRIPTION = """\
Run bopsurg end to end with nothing to download:

  1. record two short suturing episodes into rosbags          (bopsurg record)
  2. replay them from random endoscope viewpoints and lights   (bopsurg generate)
     into a small BOP test set
  3. estimate the needle's 6D pose in every frame with the     (bopsurg predict)
     small detector + pose head shipped with bopsurg
  4. evaluate: the paper's table, the ambiguity split, BOP19   (bopsurg eval)
     scores, and a rerun recording for visual error analysis

Outputs go to --out (default demo_out/): bags/, data/ (the BOP dataset), results.csv,
detections.json, eval/ (errors.csv, summary.json, scores.json, demo.rrd), eval_detector/
(the detector's COCO box AP, scores.json). Seeded: the same
--seed gives the same dataset and numbers, from episodes and viewpoints the shipped model
never saw in training. Rerunning resumes what is already done.
About 30 s on a 2-core CPU (146 frames).

With --example (or when the sim/torch extras are not installed) it evaluates the embedded
example dataset and its imitation results instead (core only, a few seconds).
"""


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    d = sub.add_parser(
        "demo",
        help=HELP,
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    d.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    d.add_argument(
        "--example",
        action="store_true",
        help="evaluate the embedded example dataset instead (no simulation, no model)",
    )
    d.add_argument(
        "--duration", type=float, default=12.0, help="length of each recorded episode, s (12)"
    )
    d.add_argument("--replays", type=int, default=3, help="viewpoint replays per episode (3)")
    d.add_argument("--device", default="auto", help="device of the estimator (default: auto)")
    spec_args(d)
    add_progress_arg(d)
    d.set_defaults(func=run_demo)


def _has(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


def _missing_for_full_demo() -> list[str]:
    missing = [m for m in ("pybullet", "rosbags", "torch") if not _has(m)]
    commands = available_plugins("command")
    missing += [c for c in ("record", "generate") if c not in commands]
    if "gdrnet" not in available_plugins("estimator"):
        missing.append("the gdrnet estimator")
    return missing


def _step(command: str, *, quiet: bool = False, **values: Any) -> None:
    """Run one bopsurg subcommand in-process (its printed report hidden when ``quiet``);
    stop the demo if it fails."""
    with contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext():
        status = run_command(command, **values)
    if status:
        raise BopsurgError(f"demo step 'bopsurg {command}' failed (exit {status})")


def _eval(dataset: Path, results: Path, out: Path, split: str, **values: Any) -> None:
    rrd = str(out / "eval" / "demo.rrd") if _has("rerun") else None
    _step(
        "eval",
        dataset=str(dataset),
        results=str(results),
        out=str(out / "eval"),
        split=split,
        rerun=rrd,
        **values,
    )


def run_demo(args: argparse.Namespace) -> int:
    """The main job (see the command's description)."""
    out = Path(args.out)
    missing = [] if args.example else _missing_for_full_demo()
    if args.example or missing:
        if missing:
            print(
                f"note: {', '.join(missing)} not installed (pip install 'bopsurg[all]'): "
                "running the embedded example instead of the full job"
            )
        return _run_example(args, out)
    t0 = time.perf_counter()
    bags = [out / "bags" / f"episode{k}.bag" for k in (1, 2)]
    print(f"[1/4] record two {args.duration:g} s suturing episodes -> {bags[0].parent}")
    for k, bag in enumerate(bags, start=1):
        seed = 1000 * args.seed + DEMO_EPISODE_SEED + k
        _step("record", quiet=True, out=str(bag), seed=seed, duration=args.duration, overwrite=True)
    data = out / "data"
    print(f"[2/4] generate a BOP test set ({args.replays} viewpoint replays each) -> {data}")
    _step(
        "generate",
        bags=[str(b) for b in bags],
        out=str(data),
        split="test",
        replays=args.replays,
        seed=1000 * args.seed + DEMO_VIEW_SEED,
        workers=max(1, min(2, os.cpu_count() or 1)),
        no_progress=args.no_progress,
    )
    results = out / "results.csv"
    print(f"[3/4] predict with the shipped detector + pose head -> {results}")
    detections = str(out / "detections.json")
    _step(
        "predict",
        dataset=str(data),
        split="test",
        out=str(results),
        device=args.device,
        detections_out=detections,
        no_progress=args.no_progress,
    )
    print("[4/4] evaluate\n")
    _eval(data, results, out, "test", detections=detections, no_progress=args.no_progress)
    _detector_ap(data, out)
    print(f"\ndemo done in {time.perf_counter() - t0:.0f} s")
    _print_rerun_hint(out)
    return 0


def _detector_ap(data: Path, out: Path) -> None:
    """The shipped detector's 2D scores (COCO AP of detections.json), beside the pose ones."""
    if not _has("pycocotools"):
        print("\ndetector AP skipped: needs pycocotools (pip install 'bopsurg[coco]')")
        return
    det_out = out / "eval_detector"
    _step(
        "eval",
        quiet=True,
        dataset=str(data),
        results=str(out / "detections.json"),
        out=str(det_out),
        split="test",
        task="coco-bbox",
    )
    s = json.loads((det_out / "scores.json").read_text())
    lo, hi = s.get("ci95", {}).get("bop22_coco_bbox_AP") or (None, None)
    interval = f" [{lo:.3f}, {hi:.3f}]" if lo is not None and hi is not None else ""
    print(
        f"\ndetector (2D boxes, COCO AP via pycocotools): AP {s['bop22_coco_bbox_AP']:.3f}"
        f"{interval}, "
        f"AP50 {s['bop22_coco_bbox_AP50']:.3f}, AP75 {s['bop22_coco_bbox_AP75']:.3f}; "
        f"on visible boxes AP {s['bop22_coco_bbox_modal_AP']:.3f} -> {det_out / 'scores.json'}"
    )


def _run_example(args: argparse.Namespace, out: Path) -> int:
    from bopsurg.example import write_example_dataset

    ex = write_example_dataset(out / "data", spec(args))
    print(f"[1/3] example dataset: {ex.root}\n      results: {ex.results}")
    print("[2/3] bopsurg check")
    _step("check", dataset=str(ex.root), split=ex.split, no_progress=args.no_progress)
    print("[3/3] bopsurg eval\n")
    _eval(ex.root, ex.results, out, ex.split, no_progress=args.no_progress)
    _print_rerun_hint(out)
    return 0


def _print_rerun_hint(out: Path) -> None:
    rrd = out / "eval" / "demo.rrd"
    if rrd.is_file():
        print(f"open the recording with: rerun {rrd}")
