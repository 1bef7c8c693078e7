"""``bopsurg recipes``: the training recipes shipped in the package (``bopsurg/recipes``).

The README and the model card fine-tune with ``bopsurg train ... --config RECIPE``; an installed
bopsurg has no checkout to take those files from, so they ship as package data and this command
lists them, prints one, or gives its path.
"""

from __future__ import annotations

import argparse
import sys
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of
from bopsurg.errors import BopsurgError

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers

HELP = help_of("recipes")

DESCRIPTION = """\
List the training recipes shipped with bopsurg (the model card's fine-tunes), print one, or
give its path, to pass to 'bopsurg train ... --config':

  bopsurg recipes                                   # name and first comment line of each
  bopsurg recipes finetune_wide_pose > wide.yaml    # a copy to edit
  bopsurg train pose DATA --out runs/p --config "$(bopsurg recipes --path finetune_wide_pose)"
"""


def recipes_dir() -> Path:
    """The folder of the shipped recipes (inside the installed package)."""
    return Path(str(resources.files("bopsurg") / "recipes"))


def shipped_recipes() -> dict[str, Path]:
    """Name (file stem) → path of every shipped recipe, in name order."""
    return {p.stem: p for p in sorted(recipes_dir().glob("*.yaml"))}


def recipe_path(name: str) -> Path:
    """The path of recipe ``name`` (with or without ``.yaml``).

    Raises:
        BopsurgError: No such recipe; the message lists the shipped ones.
    """
    recipes = shipped_recipes()
    stem = name.removesuffix(".yaml")
    if stem not in recipes:
        raise BopsurgError(f"no recipe {name!r}; shipped: {', '.join(recipes) or 'none'}")
    return recipes[stem]


def _summary(path: Path) -> str:
    """A recipe's first comment line, its comment marker dropped."""
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("#"):
            return line.lstrip("#").strip()
    return ""


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "recipes",
        help=HELP,
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("name", nargs="?", help="a recipe to print (default: list them all)")
    p.add_argument("--path", action="store_true", help="print the recipe's file path instead")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """List the recipes, or print one (its text or its path)."""
    if args.name is None:
        recipes = shipped_recipes()
        width = max((len(n) for n in recipes), default=0)
        for name, path in recipes.items():
            print(f"{name:<{width}}  {_summary(path)}")
        print(f"\n{len(recipes)} recipes in {recipes_dir()}")
        return 0
    path = recipe_path(args.name)
    if args.path:
        print(path)
    else:
        sys.stdout.write(path.read_text(encoding="utf-8"))
    return 0
