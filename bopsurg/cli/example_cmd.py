"""``bopsurg example``: write the embedded example dataset and its results CSV."""

from __future__ import annotations

import argparse

from bopsurg.example import ExampleSpec, write_example_dataset

EXAMPLE_HELP = "write the embedded example: a needle BOP dataset and a results CSV"


def register(sub: argparse._SubParsersAction) -> None:
    """Add the subcommand."""
    p = sub.add_parser("example", help=EXAMPLE_HELP, description=EXAMPLE_HELP)
    p.add_argument("--out", required=True, help="output folder (created)")
    spec_args(p)
    p.set_defaults(func=run_example)


def spec_args(p: argparse.ArgumentParser) -> None:
    """``--seed --scenes --images`` of the example."""
    defaults = ExampleSpec()
    p.add_argument("--seed", type=int, default=defaults.seed, help="random seed (default: 0)")
    p.add_argument("--scenes", type=int, default=defaults.scenes, help="number of scenes")
    p.add_argument("--images", type=int, default=defaults.images_per_scene, help="images per scene")


def spec(args: argparse.Namespace) -> ExampleSpec:
    """The :class:`ExampleSpec` the arguments describe."""
    return ExampleSpec(seed=args.seed, scenes=args.scenes, images_per_scene=args.images)


def run_example(args: argparse.Namespace) -> int:
    """Write the example and say where it is."""
    ex = write_example_dataset(args.out, spec(args))
    print(f"dataset: {ex.root} (split {ex.split})\nresults: {ex.results}")
    return 0
