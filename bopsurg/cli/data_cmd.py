"""``bopsurg data SPEC --root DATA``: make the splits a recipe (or a file of splits) names.

Each split is ``bopsurg record`` (its episodes, kept once in ``--bags``) then ``bopsurg
generate``, both run through their plugin commands as a user would type them; a split that
``generate`` finished gets the spec it was made from (:data:`bopsurg.data_spec.MARKER`), so a
rerun skips it, and an interrupted one resumes (existing bags are kept, ``generate`` resumes
itself).
"""

from __future__ import annotations

import argparse
import shlex
import time
from pathlib import Path
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of
from bopsurg.errors import BopsurgError

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers
    from bopsurg.data_spec import DataSpec, SplitSpec

HELP = help_of("data")

DESCRIPTION = """\
Make the splits of a data spec: a recipe's 'data:' section (bopsurg/recipes/robust_*.yaml;
a shipped recipe by name or any file) or a file of splits (bench/robust_splits.yaml). For
each split: 'bopsurg record' of every episode it names that --bags lacks, then 'bopsurg
generate' into --root; a finished split records its spec in SPLIT/bopsurg_data.json and is
skipped next time. Interrupted? Run the same command again: it resumes. A split in --root
made from another spec is refused (one line naming the fields that differ).

  bopsurg data robust_pose --root data --dry-run       # the commands, nothing run
  bopsurg data robust_pose --root data --workers 2     # every split the recipe names
  bopsurg data bench/robust_splits.yaml --root data --only val_paper,val_wide
"""


def register(sub: Subparsers) -> None:
    """Add the subcommand."""
    p = sub.add_parser(
        "data", help=HELP, description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument("spec", help="a recipe (file or shipped name) with a data: section, or a "
                   "file of splits")  # fmt: skip
    p.add_argument("--root", required=True, type=Path, help="BOP dataset root (created)")
    p.add_argument(
        "--bags", type=Path, default=None, help="where the episodes are kept (default: "
        "ROOT/../bags, shared by the roots beside it)",
    )  # fmt: skip
    p.add_argument("--only", default=None, metavar="SPLIT[,SPLIT...]", help="these splits only")
    p.add_argument(
        "--role", choices=("train", "val", "test"), default=None,
        help="the splits of one role only (default: every split of the spec)",
    )  # fmt: skip
    p.add_argument("--workers", type=int, default=1, help="generate's worker processes")
    p.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p.set_defaults(func=run)


def read_spec(text: str) -> tuple[Path, DataSpec]:
    """The file named by ``text`` (a path, else a shipped recipe's name) and its data spec.

    Raises:
        BopsurgError: No such file or recipe, or a bad spec (one line per bad field).
    """
    from bopsurg.cli.recipes_cmd import recipe_path
    from bopsurg.data_spec import spec_of_file
    from bopsurg.options import read_mapping

    path = Path(text)
    if not path.exists() and "/" not in text:
        path = recipe_path(text)
    return path, spec_of_file(read_mapping(path), path)


def _selected(spec: DataSpec, args: argparse.Namespace) -> tuple[str, ...] | None:
    names = tuple(n for n in args.only.split(",") if n) if args.only else None
    if args.role is not None:
        in_role = getattr(spec, args.role)
        names = tuple(n for n in (names or in_role) if n in in_role)
    return names


def run(args: argparse.Namespace) -> int:
    """Record and generate what is missing, split by split."""
    from bopsurg.data_spec import check_revision, made_from_other, mark_made

    if args.workers < 1:
        raise BopsurgError(f"--workers must be >= 1, got {args.workers}")
    path, spec = read_spec(args.spec)
    root: Path = args.root
    bags: Path = args.bags if args.bags is not None else root.parent / "bags"
    todo = spec.selected(_selected(spec, args))
    for s in todo:
        other = made_from_other(root, s)
        if other:
            raise BopsurgError(
                f"{root / s.name}: made from another spec of split {s.name!r} (differs in "
                f"{other}); remove it or choose another --root"
            )
    t0 = time.perf_counter()
    for s in todo:
        _make(s, root, bags, args)
        if not args.dry_run:
            check_revision(root, s)
            mark_made(root, s)
    verb = "would make" if args.dry_run else "made"
    print(f"{verb} {len(todo)} split(s) of {path} in {root} ({time.perf_counter() - t0:.0f} s)")
    return 0


def _make(s: SplitSpec, root: Path, bags: Path, args: argparse.Namespace) -> None:
    """One split: its missing bags, then generate (which skips finished scenes)."""
    from bopsurg.data_spec import is_made

    if is_made(root, s):
        print(f"{s.name}: made already ({root / s.name})")
        return
    for seed in s.bags:
        if not s.bag_path(bags, seed).exists():
            if not args.dry_run:
                bags.mkdir(parents=True, exist_ok=True)
            _command("record", s.record_argv(bags, seed), args.dry_run)
    progress = ["--no-progress"] if args.no_progress else []
    argv = [*s.generate_argv(root, bags), "--workers", str(args.workers), *progress]
    _command("generate", argv, args.dry_run)


def _command(name: str, argv: list[str], dry_run: bool) -> None:
    """Print ``bopsurg NAME ARGV`` and run it in this process (its plugin's command)."""
    from bopsurg.cli.commands import command_parser
    from bopsurg.cli.progress import apply_progress_policy

    print("$ " + shlex.join(["bopsurg", name, *argv]), flush=True)
    if dry_run:
        return
    args = command_parser(name).parse_args(argv)
    apply_progress_policy(args)
    code = int(args.func(args) or 0)
    if code:
        raise BopsurgError(f"bopsurg {name} failed with exit code {code}")
