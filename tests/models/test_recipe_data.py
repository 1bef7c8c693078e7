"""A recipe's ``data:`` section (``bopsurg train --config``): its splits are the run's default
``--split`` / ``--val-split``, a missing one stops the run with the command that makes it,
and a bad section is one line per bad field."""

from __future__ import annotations

import json
import shutil

import pytest
import yaml

pytest.importorskip("torch")

from bopsurg.cli.main import main
from bopsurg.data_spec import mark_made, parse_data_spec
from bopsurg.example import ExampleSpec, write_example_dataset

pytestmark = pytest.mark.usefixtures("one_thread")

DATA = {
    "splits": {
        "train_x": {"domain": "wide", "bags": [901], "duration": 4, "replays": 1, "seed": 91},
        "val_x": {"domain": "paper", "bags": [902], "duration": 4, "replays": 1, "seed": 92},
    },
    "train": ["train_x"],
    "val": ["val_x"],
}
TINY = ["--preset", "test", "--epochs", "1", "--batch-size", "2", "--no-progress",
        "--set", "recipe.steps_per_epoch=2"]  # fmt: skip


def _recipe(tmp_path, data=DATA) -> str:
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump({"recipe": {"lr": 1.0e-3}, "data": data}), encoding="utf-8")
    return str(path)


def test_missing_splits_stop_the_run_naming_the_command(tmp_path, capsys):
    recipe = _recipe(tmp_path)
    root = tmp_path / "data"
    root.mkdir()
    assert main(["train", "ends", str(root), "--out", str(tmp_path / "run"), "--config", recipe,
                 *TINY]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"bopsurg: error: {root}: splits train_x, val_x of {recipe} missing or unfinished; "
        f"make them with: bopsurg data {recipe} --root {root} --only train_x,val_x"
    ]
    assert not (tmp_path / "run").exists()


def test_the_recipes_splits_are_the_runs_defaults(tmp_path, capsys):
    """Made splits (the marker of 'bopsurg data') train and validate without --split."""
    example = write_example_dataset(tmp_path / "ex", ExampleSpec(seed=1, scenes=2,
                                                                  images_per_scene=3))  # fmt: skip
    root = example.root
    spec = parse_data_spec(DATA)
    for name in ("train_x", "val_x"):
        shutil.copytree(root / example.split, root / name)
        mark_made(root, spec.splits[name])
    out = tmp_path / "run"
    argv = ["train", "ends", str(root), "--out", str(out), "--config", _recipe(tmp_path), *TINY]
    assert main(argv) == 0
    state = json.loads((out / "train_state.json").read_text())
    assert state["split"] == "train_x"
    assert state["extra"]["val_split"] == "val_x"
    conf = yaml.safe_load((out / "config.yaml").read_text())
    assert conf["recipe"]["lr"] == 1.0e-3
    # a flag still wins over the recipe, and the split it names is checked as well
    (root / "val_x" / "bopsurg_data.json").unlink()
    assert main([*argv, "--split", "train_x", "--restart"]) == 2
    assert "split val_x of" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("data", "needle"),
    [
        ({**DATA, "tests": []}, "recipe.yaml: data.tests: unknown key"),
        ({**DATA, "splits": {**DATA["splits"], "val_x": {**DATA["splits"]["val_x"],
                                                         "domain": "any"}}},
         "recipe.yaml: data.splits.val_x.domain: must be one of paper, wide, got 'any'"),
        ({**DATA, "val": ["train_x"]}, "data.val: 'train_x' is also a train split"),
    ],
)  # fmt: skip
def test_a_bad_data_section_is_one_line(tmp_path, capsys, data, needle):
    recipe = _recipe(tmp_path, data)
    capsys.readouterr()
    assert main(["train", "pose", "--config", recipe, "--dump-config"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert needle in err[0]
