"""``bopsurg data``: a tiny recipe (one short episode, one replay) recorded and generated
through the plugin commands, marked made, skipped on a rerun, and ready for ``bopsurg train``."""

from __future__ import annotations

import pytest
import yaml

pytest.importorskip("pybullet")
pytest.importorskip("rosbags")

from bopsurg.bop.dataset import BopDataset
from bopsurg.cli.main import main
from bopsurg.data_spec import MARKER, is_made, spec_of_file
from bopsurg.generators.domain import DOMAIN_REVISIONS

RECIPE = {
    "recipe": {"epochs": 1},
    "data": {
        "splits": {
            "train_tiny": {"domain": "wide", "bags": [901], "duration": 2, "replays": 1,
                           "period": 1, "seed": 91, "domain_revision": DOMAIN_REVISIONS["wide"]},
        },
        "train": ["train_tiny"],
    },
}  # fmt: skip


def test_makes_a_tiny_recipe_once_and_resumes(tmp_path, capsys):
    recipe = tmp_path / "tiny.yaml"
    recipe.write_text(yaml.safe_dump(RECIPE), encoding="utf-8")
    root, bags = tmp_path / "data", tmp_path / "bags"
    argv = ["data", str(recipe), "--root", str(root), "--no-progress"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"$ bopsurg record --out {bags}/seed901_2s.bag --seed 901 --duration 2" in out
    assert "--split train_tiny --domain wide --replays 1 --period 1 --seed 91" in out
    assert (bags / "seed901_2s.bag").is_file()
    spec = spec_of_file(RECIPE, recipe).splits["train_tiny"]
    assert is_made(root, spec)
    ds = BopDataset(root, "train_tiny")
    assert ds.scene_ids == [1]
    frames = len(ds.scene(1).gt)
    assert 1 <= frames <= 3  # t = 0, 1, 2 s; frames with a hidden needle dropped
    written = (root / "train_tiny" / "bopsurg_generate.json").stat().st_mtime_ns

    assert main(argv) == 0  # made: neither recorded nor generated again
    out = capsys.readouterr().out
    assert "train_tiny: made already" in out
    assert "$ bopsurg" not in out
    assert (root / "train_tiny" / "bopsurg_generate.json").stat().st_mtime_ns == written

    # interrupted after generate, before the marker: the rerun lets generate resume (skip)
    (root / "train_tiny" / MARKER).unlink()
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "$ bopsurg record" not in out  # the episode is kept
    assert "$ bopsurg generate" in out
    assert is_made(root, spec)
    assert len(BopDataset(root, "train_tiny").scene(1).gt) == frames


def test_a_split_drawn_by_another_revision_is_refused(tmp_path, capsys):
    """The spec pins the wide draw's revision: a bopsurg whose draw differs says so and marks
    nothing (its images are not the spec's)."""
    old = {**RECIPE["data"]["splits"]["train_tiny"], "domain_revision": 1}
    data = {"splits": {"train_tiny": old}, "train": ["train_tiny"]}
    recipe = tmp_path / "old.yaml"
    recipe.write_text(yaml.safe_dump({"data": data}), encoding="utf-8")
    root = tmp_path / "data"
    assert main(["data", str(recipe), "--root", str(root), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (
        f"bopsurg: error: {root / 'train_tiny'}: drawn by --domain wide revision "
        f"{DOMAIN_REVISIONS['wide']}, the spec pins 1: this bopsurg draws other images from "
        "these seeds"
    )
    assert not (root / "train_tiny" / MARKER).exists()
