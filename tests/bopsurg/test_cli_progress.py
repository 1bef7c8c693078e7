"""Progress bars only on a terminal: a log file gets no carriage-return-joined bars;
``--no-progress`` and ``TQDM_DISABLE`` turn them off on a terminal too."""

from __future__ import annotations

import io
import sys

import pytest

from bopsurg.cli.commands import command_parser, run_command
from bopsurg.cli.main import main
from bopsurg.cli.progress import apply_progress_policy, progress_allowed
from bopsurg.example import ExampleSpec, write_example_dataset

#: The core's commands that run long enough to draw a bar.
LONG_COMMANDS = ("demo", "predict", "eval", "check", "annotate", "import")


class _Terminal(io.StringIO):
    """A stderr that says it is a terminal."""

    def isatty(self) -> bool:
        return True


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    return write_example_dataset(
        tmp_path_factory.mktemp("progress"), ExampleSpec(seed=2, scenes=3, images_per_scene=2)
    )


def _check(example, *extra: str) -> int:
    return main(["check", str(example.root), "--split", example.split, *extra])


def _eval(example, out, *extra: str) -> int:
    args = ["eval", str(example.root), str(example.results), "--out", str(out)]
    return main([*args, "--bootstrap", "0", "--renderer", "none", *extra])


def test_no_bars_when_stderr_is_a_file(example, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("TQDM_DISABLE", raising=False)
    assert _check(example) == 0
    assert _eval(example, tmp_path / "ev", "--executor", "local", "--workers", "2") == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    assert "scene/s" not in err


def test_bars_on_a_terminal_unless_turned_off(example, tmp_path, monkeypatch):
    monkeypatch.delenv("TQDM_DISABLE", raising=False)
    terminal = _Terminal()
    monkeypatch.setattr(
        sys, "stderr", terminal
    )  # in the test: pytest's capture resumes after setup
    assert _check(example) == 0
    assert "\r" in terminal.getvalue()  # the test can see a bar when one is drawn
    assert "checking scenes" in terminal.getvalue()
    for extra, env in ((("--no-progress",), None), ((), "1")):
        terminal.seek(0)
        terminal.truncate()
        if env is not None:
            monkeypatch.setenv("TQDM_DISABLE", env)
        assert _check(example, *extra) == 0
        assert _eval(example, tmp_path / "ev", *extra) == 0
        assert "\r" not in terminal.getvalue()
        assert "checking scenes" not in terminal.getvalue()


def test_commands_run_as_functions_follow_the_same_rule(example, capsys, monkeypatch):
    monkeypatch.delenv("TQDM_DISABLE", raising=False)
    assert run_command("check", dataset=str(example.root), split=example.split) == 0
    assert "\r" not in capsys.readouterr().err


@pytest.mark.parametrize("name", LONG_COMMANDS)
def test_every_long_command_has_no_progress(name):
    parser = command_parser(name)
    assert "--no-progress" in parser.format_help()


@pytest.mark.parametrize(
    ("tty", "env", "allowed"),
    [(True, None, True), (True, "", True), (True, "1", False), (True, "True", False),
     (False, None, False)],
)  # fmt: skip
def test_progress_allowed(monkeypatch, tty, env, allowed):
    monkeypatch.setattr(sys, "stderr", _Terminal() if tty else io.StringIO())
    if env is None:
        monkeypatch.delenv("TQDM_DISABLE", raising=False)
    else:
        monkeypatch.setenv("TQDM_DISABLE", env)  # tqdm's rule: any non-empty value disables
    assert progress_allowed() is allowed
    args = command_parser("check").parse_args(["data"])
    apply_progress_policy(args)
    assert args.no_progress is not allowed
