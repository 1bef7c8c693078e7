"""``bopsurg example``: write the embedded example dataset and its results CSV."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers
    from bopsurg.example import ExampleSpec

EXAMPLE_HELP = help_of("example")

#: Defaults of bopsurg.example.ExampleSpec (a test keeps them equal; importing it here would
#: load numpy, OpenCV and scipy just to build the parser).
SPEC_DEFAULTS = {"seed": 0, "scenes": 3, "images_per_scene": 12}


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    p = sub.add_parser("example", help=EXAMPLE_HELP, description=EXAMPLE_HELP)
    p.add_argument("--out", required=True, help="output folder (created)")
    spec_args(p)
    p.set_defaults(func=run_example)


def spec_args(p: argparse.ArgumentParser) -> None:
    """``--seed --scenes --images`` of the example."""
    d = SPEC_DEFAULTS
    p.add_argument("--seed", type=int, default=d["seed"], help="random seed (default: 0)")
    p.add_argument("--scenes", type=int, default=d["scenes"], help="number of scenes")
    p.add_argument("--images", type=int, default=d["images_per_scene"], help="images per scene")


def spec(args: argparse.Namespace) -> ExampleSpec:
    """The :class:`ExampleSpec` the arguments describe."""
    from bopsurg.example import ExampleSpec

    return ExampleSpec(seed=args.seed, scenes=args.scenes, images_per_scene=args.images)


def run_example(args: argparse.Namespace) -> int:
    """Write the example and say where it is."""
    from bopsurg.example import write_example_dataset

    ex = write_example_dataset(args.out, spec(args))
    print(f"dataset: {ex.root} (split {ex.split})\nresults: {ex.results}")
    return 0
