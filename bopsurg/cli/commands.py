"""The table of ``bopsurg`` subcommands and their lazy loading.

Building the parser imports only the module of the command being run: the top-level
``bopsurg --help`` imports none (plugin commands pull torch, pybullet or rosbags; the core
ones numpy, pandas and scipy), ``bopsurg eval --help`` imports the light ``eval_cmd`` only.
A command module defines ``register(subparsers)``, which adds the subcommand with its
arguments and ``set_defaults(func=run)``, and keeps its heavy imports inside ``run``.

To add a core command: write ``bopsurg/cli/NAME_cmd.py`` and add one :class:`Command` line to
:data:`CORE`. A plugin command registers under the ``bopsurg.commands`` entry-point group
(its module path); its help line in the listing comes from :data:`PLUGIN_HELP` for the
built-in ones, else names its distribution.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any

from bopsurg.errors import BopsurgError
from bopsurg.plugins import available_plugins

if TYPE_CHECKING:
    #: What ``add_subparsers()`` returns (generic in the stubs only).
    Subparsers = argparse._SubParsersAction[argparse.ArgumentParser]


@dataclass(frozen=True)
class Command:
    """One subcommand: its name, its line in ``bopsurg --help`` and the module that adds it."""

    name: str
    help: str
    module: str


#: The core's commands, in the order ``bopsurg --help`` lists them.
CORE: tuple[Command, ...] = (
    Command(
        "demo",
        "the main job: record -> generate -> predict (shipped model) -> eval table + rerun .rrd "
        "(the embedded example without bopsurg[all])",
        "bopsurg.cli.demo_cmd",
    ),
    Command(
        "predict",
        "estimate poses in a dataset split with an estimator plugin: a BOP19 results CSV",
        "bopsurg.cli.predict_cmd",
    ),
    Command(
        "eval",
        "evaluate a BOP results CSV: errors.csv, the paper's table, BOP19 average recall",
        "bopsurg.cli.eval_cmd",
    ),
    Command(
        "compare",
        "compare evaluations: paired differences, 95%% intervals and p-values",
        "bopsurg.cli.compare_cmd",
    ),
    Command(
        "viz",
        "evaluate a BOP results CSV and write a rerun .rrd for visual error analysis",
        "bopsurg.cli.viz_cmd",
    ),
    Command(
        "check",
        "validate a BOP dataset (schemas, ids, files, rotations, masks vs gt_info)",
        "bopsurg.cli.check_cmd",
    ),
    Command(
        "annotate",
        "compute mask/, mask_visib/ and scene_gt_info.json of a dataset from poses and models",
        "bopsurg.cli.annotate_cmd",
    ),
    Command(
        "import",
        "import the AMBF pipeline's data (YAML layout, or BOP with obj_id 0) as a BOP dataset",
        "bopsurg.cli.import_cmd",
    ),
    Command(
        "example",
        "write the embedded example: a needle BOP dataset and a results CSV",
        "bopsurg.cli.example_cmd",
    ),
    Command(
        "data",
        "make the splits a training recipe names: record + generate, resumable",
        "bopsurg.cli.data_cmd",
    ),
    Command(
        "recipes",
        "list the shipped training recipes (bopsurg train --config), print one or its path",
        "bopsurg.cli.recipes_cmd",
    ),
)

#: Help lines of the built-in plugin commands (the same as their modules' ``HELP``; a test
#: keeps them equal), so that listing them imports no plugin.
PLUGIN_HELP: dict[str, str] = {
    "record": "synthesise a suturing episode (two dVRK PSMs and a needle) into a rosbag",
    "generate": "replay bags from randomised endoscope viewpoints and lighting into a BOP dataset",
    "train": "train the built-in detector, pose head, needle segmenter or end classifier",
    "inspect": "show a bag's topics, the streams generate finds in it, and the kinematics check",
}

#: The extra that brings each built-in plugin command's dependencies, and their modules.
PLUGIN_EXTRA: dict[str, str] = {
    "record": "sim",
    "generate": "sim",
    "inspect": "sim",
    "train": "torch",
}
EXTRA_MODULES: dict[str, tuple[str, ...]] = {"sim": ("pybullet", "rosbags"), "torch": ("torch",)}


def help_of(name: str) -> str:
    """The help line of core command ``name`` (what its module passes to ``add_parser``)."""
    for command in CORE:
        if command.name == name:
            return command.help
    raise KeyError(name)


def selected_command(argv: Sequence[str]) -> str | None:
    """The subcommand named in ``argv``: its first word that is not an option (the top-level
    options -h, --version, -v, -q take no value), or None."""
    return next((a for a in argv if not a.startswith("-")), None)


def _missing_modules(extra: str) -> list[str]:
    return [m for m in EXTRA_MODULES.get(extra, ()) if importlib.util.find_spec(m) is None]


def add_commands(sub: Subparsers, load: str | None) -> None:
    """Add every subcommand to ``sub``: the one called ``load`` with its module's arguments,
    the others as entries of the listing only (nothing imported); when ``load`` is a core
    command, the core ones only."""
    core = {c.name for c in CORE}
    for command in CORE:
        if command.name == load:
            load_core_module(command.name).register(sub)
        else:
            sub.add_parser(command.name, help=command.help, add_help=False)
    if load in core:  # the listing is never shown: skip reading every distribution's plugins
        return
    for name, ep in sorted(available_plugins("command").items()):
        if name in core:
            continue
        extra = PLUGIN_EXTRA.get(name, "all")
        missing = _missing_modules(extra)
        if name == load:
            _add_plugin_command(sub, name, ep.load, extra)
        elif missing:
            sub.add_parser(
                name,
                help=f"(unavailable: {', '.join(missing)} not installed; "
                f"pip install 'bopsurg[{extra}]')",
                add_help=False,
            )
        else:
            dist = ep.dist.name if ep.dist is not None else "a plugin"
            default = f"(from {dist}; see 'bopsurg {name} --help')"
            sub.add_parser(name, help=PLUGIN_HELP.get(name, default), add_help=False)


def load_core_module(name: str) -> ModuleType:
    """The module of core command ``name``."""
    for command in CORE:
        if command.name == name:
            return importlib.import_module(command.module)
    raise BopsurgError(f"no core command {name!r}")


def _add_plugin_command(sub: Subparsers, name: str, load: Callable[[], Any], extra: str) -> None:
    """Load the plugin's command module and let it register; when its optional dependencies
    are missing, add a command that says which extra to install, whatever its arguments."""
    try:
        module = load()
    except ImportError as err:
        reason = str(err)
        # No option prefix: every argument, '--help' included, lands in `rest`, so the hint
        # is what the user sees.
        p = sub.add_parser(
            name,
            help=f"(unavailable: {reason}; pip install 'bopsurg[{extra}]')",
            add_help=False,
            prefix_chars="\0",
        )
        p.add_argument("rest", nargs="*", help=argparse.SUPPRESS)
        p.set_defaults(func=_unavailable(name, reason, extra))
        return
    module.register(sub)


def _unavailable(name: str, reason: str, extra: str) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        raise BopsurgError(f"'{name}' is unavailable ({reason}); pip install 'bopsurg[{extra}]'")

    return run


def command_parser(name: str) -> argparse.ArgumentParser:
    """The parser of subcommand ``name`` alone (its module loaded)."""
    parser = argparse.ArgumentParser(prog="bopsurg")
    sub = parser.add_subparsers(dest="command")
    add_commands(sub, load=name)
    chosen = sub.choices.get(name)
    if chosen is None:
        raise BopsurgError(f"no command {name!r}")
    return chosen


def run_command(name: str, **values: Any) -> int:
    """Run subcommand ``name`` in this process with option values given as Python values
    (``dest`` names: ``out=Path(...)``, ``replays=3``); the others take their defaults.

    Raises:
        BopsurgError: ``values`` names an option the command does not have, or a required
            one is missing.
    """
    parser = command_parser(name)
    args = argparse.Namespace(**parser._defaults)  # set_defaults(func=...)
    known = set()
    for action in parser._actions:
        if action.dest in (argparse.SUPPRESS, "help"):
            continue
        known.add(action.dest)
        setattr(args, action.dest, action.default)
    unknown = sorted(set(values) - known)
    if unknown:
        raise BopsurgError(f"'bopsurg {name}' has no option(s) {unknown}")
    vars(args).update(values)
    from bopsurg.cli.progress import apply_progress_policy

    apply_progress_policy(args)
    missing = [a.dest for a in parser._actions if a.required and getattr(args, a.dest) is None]
    if missing:
        raise BopsurgError(f"'bopsurg {name}' needs {missing}")
    return int(args.func(args) or 0)
