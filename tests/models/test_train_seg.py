"""The needle segmenter's trainer (``python -m bopsurg.models.refine.train_seg``): seeded,
reads several splits, augments on request, and fails in one line on a bad split."""

from __future__ import annotations

import shutil

import pytest

torch = pytest.importorskip("torch")

from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.models.checkpoint import load_checkpoint  # noqa: E402
from bopsurg.models.refine.train_seg import main  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("seg")
    ds = write_example_dataset(root, ExampleSpec(seed=4, scenes=2, images_per_scene=3))
    shutil.copytree(ds.root / "test", ds.root / "train")
    shutil.copytree(ds.root / "test", ds.root / "wide")
    return ds.root


def _train(dataset, out, *extra: str) -> int:
    args = [str(dataset), "--out", str(out), "--steps", "3", "--batch", "2", "--roi", "64"]
    return main([*args, "--width", "4", "--no-progress", *extra])


def test_seeded_two_splits_and_augmentation_recorded(dataset, tmp_path):
    both = ("--split", "train,wide", "--augment", "domain")
    assert _train(dataset, tmp_path / "a", *both) == 0
    assert _train(dataset, tmp_path / "b", *both) == 0
    assert _train(dataset, tmp_path / "plain") == 0
    a, info = load_checkpoint(tmp_path / "a" / "needle_seg.pt", "needle_seg")
    b, _ = load_checkpoint(tmp_path / "b" / "needle_seg.pt", "needle_seg")
    plain, plain_info = load_checkpoint(tmp_path / "plain" / "needle_seg.pt", "needle_seg")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], plain[k]) for k in a)
    assert info["meta"]["split"] == "train,wide"
    assert info["meta"]["augment"] == "domain"
    assert info["meta"]["instances"] > plain_info["meta"]["instances"]  # both splits read
    assert "split" not in plain_info["meta"]


def test_a_missing_split_is_one_line(dataset, tmp_path, capsys):
    assert _train(dataset, tmp_path / "x", "--split", "train,nope") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ")
    assert "nope" in err[-1]
    assert "split folder not found" in err[-1]
