"""When the commands draw progress bars: ``--no-progress``, a terminal, ``TQDM_DISABLE``.

A progress bar redraws itself with carriage returns; written into a log file or a CI log (stderr
not a terminal) it leaves one long line of bars joined by them. So bars are drawn only when
stderr is a terminal, ``TQDM_DISABLE`` is unset or empty (tqdm's own rule: any other value
disables) and ``--no-progress`` is not given. :func:`apply_progress_policy` folds the first two
into ``args.no_progress`` before a command runs (``bopsurg`` itself and
:func:`bopsurg.cli.commands.run_command`), so every command with a ``--no-progress`` option,
plugin commands included, follows it.
"""

from __future__ import annotations

import argparse
import os
import sys


def add_progress_arg(p: argparse.ArgumentParser) -> None:
    """``--no-progress``, the option of every command that runs long enough to show a bar."""
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="hide progress bars (also hidden when stderr is not a terminal or TQDM_DISABLE "
        "is set)",
    )


def progress_allowed() -> bool:
    """Whether progress bars may be drawn: stderr is a terminal and ``TQDM_DISABLE`` is unset
    or empty."""
    if os.environ.get("TQDM_DISABLE", ""):
        return False
    isatty = getattr(sys.stderr, "isatty", None)
    try:
        return bool(isatty and isatty())
    except ValueError:  # a closed stream
        return False


def apply_progress_policy(args: argparse.Namespace) -> None:
    """Set ``args.no_progress`` when bars may not be drawn (commands without the option are
    left alone)."""
    if hasattr(args, "no_progress") and not progress_allowed():
        args.no_progress = True
