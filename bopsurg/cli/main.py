"""The ``bopsurg`` command: subcommands, logging set-up and one-line errors.

Every user mistake (bad file, bad argument) ends as ``bopsurg: error: <one line>`` on stderr
and exit code 2, never a traceback. ``bopsurg check`` exits 1 when it finds problems.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from bopsurg._version import __version__
from bopsurg.cli import (
    annotate_cmd,
    check_cmd,
    demo_cmd,
    eval_cmd,
    example_cmd,
    import_cmd,
    predict_cmd,
    viz_cmd,
)
from bopsurg.errors import BopsurgError
from bopsurg.plugins import available_plugins

DESCRIPTION = """\
bopsurg: BOP metrics, formats and synthetic data for 6D pose of surgical instruments.

Evaluate pose estimates the way the BOP toolkit does (same numbers), much faster, with the
error tables of the needle-pose paper; validate BOP datasets; make a small example dataset.
"""

EPILOG = """\
examples:
  bopsurg demo                                   # example dataset -> evaluation, in ./demo_out
  bopsurg example --out data/                    # write the embedded example dataset
  bopsurg check data/needle --split test         # validate a BOP dataset
  bopsurg eval data/needle data/bopsurgsim_needle-test.csv --out eval/

Run 'bopsurg COMMAND --help' for the options of each command.
"""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="bopsurg",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"bopsurg {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    verbosity.add_argument("-q", "--quiet", action="store_true", help="log warnings only")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in (
        demo_cmd, predict_cmd, eval_cmd, viz_cmd, check_cmd, annotate_cmd, import_cmd, example_cmd
    ):  # fmt: skip
        module.register(sub)
    _register_plugin_commands(sub)
    return parser


def _register_plugin_commands(sub: argparse._SubParsersAction) -> None:
    """Subcommands that plugins (e.g. bopsurg.generators: record, generate) contribute.

    A plugin whose optional dependencies are missing still shows up, with a command that
    says which extra to install, instead of breaking the whole CLI.
    """
    for name, ep in sorted(available_plugins("command").items()):
        if name in sub.choices:
            continue
        try:
            module = ep.load()
            module.register(sub)
        except ImportError as err:
            missing = str(err)
            extra = _EXTRAS.get(name, "all")
            p = sub.add_parser(
                name, help=f"(unavailable: {missing}; pip install 'bopsurg[{extra}]')"
            )
            p.set_defaults(func=_unavailable(name, missing, extra))


#: The extra that brings each built-in plugin command's dependencies.
_EXTRAS = {"record": "sim", "generate": "sim", "train": "torch"}


def _unavailable(name: str, reason: str, extra: str):
    def run(args: argparse.Namespace) -> int:
        raise BopsurgError(f"'{name}' is unavailable ({reason}); install 'bopsurg[{extra}]'")

    return run


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 problems found, 2 user error)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s: %(message)s", force=True)
    try:
        return int(args.func(args) or 0)
    except BopsurgError as err:
        print(f"bopsurg: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        where = f"{err.filename}: " if err.filename else ""
        print(f"bopsurg: error: {where}{err.strerror or err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("bopsurg: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
