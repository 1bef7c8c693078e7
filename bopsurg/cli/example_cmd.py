"""``bopsurg example`` and ``bopsurg demo``: the embedded example dataset and its evaluation."""

from __future__ import annotations

import argparse
from pathlib import Path

from bopsurg.evaluation.runner import INSTANCE_METRICS
from bopsurg.example import ExampleSpec, write_example_dataset

EXAMPLE_HELP = "write the embedded example: a needle BOP dataset and a results CSV"
DEMO_HELP = "the main job on embedded defaults: example dataset -> evaluation -> table"

DEMO_DESCRIPTION = """\
Run bopsurg end to end on embedded data, with nothing to download:

  1. write the example needle dataset and a results CSV (bopsurg example),
  2. validate the dataset (bopsurg check),
  3. evaluate the results (bopsurg eval), print the paper's table and BOP19 scores, and
     write a rerun recording for visual error analysis (open it with: rerun FILE.rrd).

Outputs go to --out (default: demo_out/).
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add the subcommands."""
    p = sub.add_parser("example", help=EXAMPLE_HELP, description=EXAMPLE_HELP)
    p.add_argument("--out", required=True, help="output folder (created)")
    _spec_args(p)
    p.set_defaults(func=run_example)

    d = sub.add_parser(
        "demo",
        help=DEMO_HELP,
        description=DEMO_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    d.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    _spec_args(d)
    d.set_defaults(func=run_demo)


def _spec_args(p: argparse.ArgumentParser) -> None:
    defaults = ExampleSpec()
    p.add_argument("--seed", type=int, default=defaults.seed, help="random seed (default: 0)")
    p.add_argument("--scenes", type=int, default=defaults.scenes, help="number of scenes")
    p.add_argument("--images", type=int, default=defaults.images_per_scene, help="images per scene")


def _spec(args: argparse.Namespace) -> ExampleSpec:
    return ExampleSpec(seed=args.seed, scenes=args.scenes, images_per_scene=args.images)


def run_example(args: argparse.Namespace) -> int:
    """Write the example and say where it is."""
    ex = write_example_dataset(args.out, _spec(args))
    print(f"dataset: {ex.root} (split {ex.split})\nresults: {ex.results}")
    return 0


def _has_rerun() -> bool:
    import importlib.util

    return importlib.util.find_spec("rerun") is not None


def run_demo(args: argparse.Namespace) -> int:
    """Example dataset, check, evaluation."""
    from bopsurg.cli import check_cmd, eval_cmd

    out = Path(args.out)
    ex = write_example_dataset(out / "data", _spec(args))
    print(f"[1/3] example dataset: {ex.root}\n      results: {ex.results}")
    print("[2/3] bopsurg check")
    status = check_cmd.run(
        argparse.Namespace(
            dataset=str(ex.root),
            split=ex.split,
            split_type=None,
            no_images=False,
            max_problems=None,
        )
    )
    if status:
        return status
    print("[3/3] bopsurg eval\n")
    return eval_cmd.run(
        argparse.Namespace(
            dataset=str(ex.root),
            results=str(ex.results),
            out=str(out / "eval"),
            split=ex.split,
            split_type=None,
            targets=None,
            min_visib=0.3,
            renderer="auto",
            vsd_delta=15.0,
            metrics=",".join(INSTANCE_METRICS),
            rerun=str(out / "eval" / "demo.rrd") if _has_rerun() else None,
            executor="local",
            workers=1,
            ray_address=None,
            no_progress=False,
        )
    )
