"""The `bopsurg` command: exit codes, one-line errors, outputs."""

from __future__ import annotations

import io
import json
import logging
import sys

import pytest

from bopsurg.cli.main import main
from bopsurg.example import ExampleSpec, write_example_dataset


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    return write_example_dataset(
        tmp_path_factory.mktemp("cli"), ExampleSpec(seed=1, scenes=1, images_per_scene=6)
    )


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("bopsurg: error: ")
    assert "\n" not in err
    assert "Traceback" not in err
    return err


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("bopsurg ")


def test_help_teaches(capsys):
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    out = capsys.readouterr().out
    assert "errors.csv" in out
    assert "--min-visib" in out
    assert "bop19_average_recall" in out


def test_eval_writes_outputs(example, tmp_path, capsys):
    assert main(["eval", str(example.root), str(example.results), "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "MSSD [mm]" in out
    assert "bop19_average_recall_mssd" in out
    assert (tmp_path / "errors.csv").exists()
    assert "bop19_average_recall_mspd" in json.loads((tmp_path / "scores.json").read_text())


def test_eval_bad_results_is_one_line_exit_2(example, tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    lines = example.results.read_text().splitlines()
    fields = lines[2].split(",")
    fields[3] = "nan"
    lines[2] = ",".join(fields)
    bad.write_text("\n".join(lines))
    assert main(["eval", str(example.root), str(bad), "--out", str(tmp_path / "o")]) == 2
    err = _one_line_error(capsys)
    assert "bad.csv:3" in err
    assert "score" in err


def test_eval_unknown_image_is_one_line_exit_2(example, tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    lines = example.results.read_text().splitlines()
    fields = lines[1].split(",")
    fields[1] = "999"
    lines[1] = ",".join(fields)
    bad.write_text("\n".join(lines))
    assert main(["eval", str(example.root), str(bad), "--out", str(tmp_path / "o")]) == 2
    err = _one_line_error(capsys)
    assert "bad.csv:2" in err


def test_eval_missing_dataset_is_one_line_exit_2(tmp_path, capsys):
    code = main(["eval", str(tmp_path / "nope"), str(tmp_path / "r.csv"), "--out", str(tmp_path)])
    assert code == 2
    _one_line_error(capsys)


def test_check_ok_and_problems(example, capsys):
    assert main(["check", str(example.root)]) == 0
    assert "OK" in capsys.readouterr().out
    gt = example.root / "test" / "000001" / "scene_gt.json"
    original = gt.read_text()
    try:
        gt.write_text(original.replace('"obj_id": 1', '"obj_id": 7', 1))
        assert main(["check", str(example.root)]) == 1
        out = capsys.readouterr().out
        assert "scene_gt.json" in out
        assert "obj_id" in out
    finally:
        gt.write_text(original)


def test_example_demo_runs(tmp_path, capsys):
    assert (
        main(["demo", "--example", "--out", str(tmp_path), "--scenes", "1", "--images", "4"]) == 0
    )
    out = capsys.readouterr().out
    assert "[3/3] bopsurg eval" in out
    assert "RE [deg]" in out
    assert (tmp_path / "eval" / "summary.json").exists()


def test_ray_executor_without_ray_is_a_one_line_hint(example, tmp_path, capsys, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    args = ["-q", "eval", str(example.root), str(example.results), "--out", str(tmp_path)]
    assert main([*args, "--executor", "ray"]) == 2
    assert "pip install 'bopsurg[ray]'" in _one_line_error(capsys)


def test_help_loads_no_command_module():
    """`bopsurg --help` and `bopsurg eval --help` import neither torch nor the plugins, nor
    even pandas or scipy: building the parser loads only the chosen command's module."""
    import subprocess

    code = (
        "import sys\n"
        "from bopsurg.cli.main import main\n"
        "for argv in (['--help'], ['eval', '--help'], ['check', '--help'],\n"
        "             ['compare', '--help'], ['import', '--help']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "heavy = ('torch', 'pybullet', 'rosbags', 'rerun', 'ray', 'pandas', 'scipy', 'cv2',\n"
        "         'bopsurg.generators', 'bopsurg.models')\n"
        "print('LOADED', ','.join(m for m in heavy if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "usage: bopsurg" in out.stdout
    assert out.stdout.strip().splitlines()[-1] == "LOADED"


def test_literal_defaults_and_help_lines_match_the_code():
    """The CLI keeps a few values as literals so that building the parser stays light; they
    must say what the code does."""
    import dataclasses
    import importlib

    from bopsurg.ambf_import import AMBF_DELTA_MM
    from bopsurg.cli import annotate_cmd, example_cmd, import_cmd, viz_cmd
    from bopsurg.cli.commands import PLUGIN_HELP
    from bopsurg.example import ExampleSpec
    from bopsurg.plugins import available_plugins
    from bopsurg.visibility import DEFAULT_DELTA_MM
    from bopsurg.viz.rerun_log import DEFAULT_IMAGE_FRAMES

    assert annotate_cmd.DEFAULT_DELTA_MM == DEFAULT_DELTA_MM
    assert import_cmd.AMBF_DELTA_MM == AMBF_DELTA_MM
    fields = {f.name: f.default for f in dataclasses.fields(ExampleSpec)}
    assert {k: fields[k] for k in example_cmd.SPEC_DEFAULTS} == example_cmd.SPEC_DEFAULTS
    assert f"up to {DEFAULT_IMAGE_FRAMES} frames" in viz_cmd.DESCRIPTION
    assert f"the {DEFAULT_IMAGE_FRAMES} worst" in viz_cmd.DESCRIPTION
    commands = available_plugins("command")
    for name, line in PLUGIN_HELP.items():
        try:
            module = importlib.import_module(commands[name].value)
        except ImportError:  # that extra is not installed here
            continue
        assert line == module.HELP, name


def test_plugin_command_with_missing_dependency_is_a_one_line_hint(capsys, monkeypatch):
    from importlib.metadata import EntryPoint

    from bopsurg.cli import commands

    broken = EntryPoint(name="broken", value="bopsurg_no_such_module", group="bopsurg.commands")
    real = commands.available_plugins

    def plugins(kind: str):
        return {**real(kind), "broken": broken} if kind == "command" else real(kind)

    monkeypatch.setattr(commands, "available_plugins", plugins)
    # a built-in plugin whose extra is missing is marked in the listing, nothing imported
    monkeypatch.setitem(commands.EXTRA_MODULES, "sim", ("bopsurg_no_such_module",))
    monkeypatch.setenv("COLUMNS", "250")  # one help line per command
    with pytest.raises(SystemExit):
        main(["--help"])
    listing = capsys.readouterr().out
    assert "broken" in listing
    assert "pip install 'bopsurg[sim]'" in listing
    assert main(["broken", "--any", "argument"]) == 2
    err = _one_line_error(capsys)
    assert "'broken' is unavailable" in err
    assert "pip install 'bopsurg[all]'" in err


def test_run_command_rejects_unknown_options(tmp_path):
    from bopsurg.cli.commands import run_command
    from bopsurg.errors import BopsurgError

    with pytest.raises(BopsurgError, match="no option"):
        run_command("example", out=str(tmp_path), scene=2)
    with pytest.raises(BopsurgError, match="needs"):
        run_command("example", scenes=1)
    assert run_command("example", out=str(tmp_path), scenes=1, images=2) == 0
    assert any(tmp_path.rglob("camera.json"))


def test_the_log_follows_stderr_when_a_program_swaps_it(monkeypatch, capsys, tmp_path):
    """A program that swaps sys.stderr after calling main (pytest's capture, a notebook)
    still gets the log on the stream of the moment, not on the one of the call."""
    assert main(["check", str(tmp_path / "none")]) == 1  # sets the log up; "no dataset"
    capsys.readouterr()
    swapped = io.StringIO()
    monkeypatch.setattr(sys, "stderr", swapped)
    logging.getLogger("bopsurg.test").warning("after the swap")
    assert swapped.getvalue() == "WARNING: after the swap\n"
