"""The ``bopsurg`` command: subcommands, logging set-up and one-line errors.

Every user mistake (bad file, bad argument) ends as ``bopsurg: error: <one line>`` on stderr
and exit code 2, never a traceback. ``bopsurg check`` exits 1 when it finds problems.
Subcommand modules load lazily (see :mod:`bopsurg.cli.commands`): ``bopsurg --help`` imports
no command module, ``bopsurg eval ...`` only ``eval``'s.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, TextIO

from bopsurg._version import __version__
from bopsurg.cli.commands import add_commands, selected_command
from bopsurg.cli.progress import apply_progress_policy
from bopsurg.errors import BopsurgError

DESCRIPTION = """\
bopsurg: BOP metrics, formats and synthetic data for 6D pose of surgical instruments.

Evaluate pose estimates the way the BOP toolkit does (same numbers), much faster, with the
error tables of the needle-pose paper; validate BOP datasets; synthesise suturing episodes and
BOP datasets from them (bopsurg[sim]); train and run the built-in estimator (bopsurg[torch]).
"""

EPILOG = """\
examples:
  bopsurg demo                                   # record -> generate -> predict -> eval,
                                                 # in ./demo_out (--example: core only)
  bopsurg example --out data/                    # write the embedded example dataset
  bopsurg check data/needle --split test         # validate a BOP dataset
  bopsurg eval data/needle data/bopsurgsim_needle-test.csv --out eval/

Run 'bopsurg COMMAND --help' for the options of each command.
"""


def build_parser(argv: Sequence[str] = ()) -> argparse.ArgumentParser:
    """The argument parser for ``argv``: every subcommand listed, and the one ``argv`` names
    (if any) loaded with its arguments."""
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
    add_commands(sub, load=selected_command(argv))
    return parser


if TYPE_CHECKING:
    _StreamHandler = logging.StreamHandler[TextIO]
else:  # subscriptable at run time from Python 3.11 only
    _StreamHandler = logging.StreamHandler


class _CurrentStderr(_StreamHandler):
    """Writes each record to ``sys.stderr`` as it is when the record is emitted: a program
    that swaps ``sys.stderr`` after calling :func:`main` (pytest's capture, a notebook)
    keeps getting the log, never a closed stream's error."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr  # (emit runs under the handler's lock)
        super().emit(record)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 problems found, 2 user error)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser(argv)
    except BopsurgError as err:
        print(f"bopsurg: error: {err}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    apply_progress_policy(args)
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(
        level=level, format="%(levelname)s: %(message)s", handlers=[_CurrentStderr()], force=True
    )
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
