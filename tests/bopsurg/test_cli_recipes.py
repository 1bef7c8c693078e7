"""``bopsurg recipes``: the training recipes an installed bopsurg ships (package data)."""

from __future__ import annotations

from pathlib import Path

import yaml

from bopsurg.cli.main import main
from bopsurg.cli.recipes_cmd import recipes_dir, shipped_recipes


def test_lists_prints_and_locates_the_shipped_recipes(capsys):
    assert main(["recipes"]) == 0
    listing = capsys.readouterr().out
    names = list(shipped_recipes())
    assert len(names) >= 10
    for name in names:
        assert name in listing
    assert f"{len(names)} recipes in {recipes_dir()}" in listing
    assert main(["recipes", "finetune_wide_pose"]) == 0
    text = capsys.readouterr().out
    assert text == (recipes_dir() / "finetune_wide_pose.yaml").read_text(encoding="utf-8")
    assert yaml.safe_load(text)["recipe"]  # a --config file as it is
    assert main(["recipes", "--path", "finetune_wide_detector.yaml"]) == 0
    path = Path(capsys.readouterr().out.strip())
    assert path.is_file()
    assert path.name == "finetune_wide_detector.yaml"


def test_an_unknown_recipe_is_one_line_exit_2(capsys):
    assert main(["recipes", "finetune_nothing"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "no recipe 'finetune_nothing'" in err
    assert "finetune_wide_pose" in err  # says which exist
