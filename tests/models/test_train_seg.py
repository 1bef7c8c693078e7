"""``bopsurg train seg``: the needle segmenter on the shared epoch loop. Seeded, reads several
splits, augments on request, resumes to the same weights, fine-tunes from a segmenter, and
fails in one line on a bad split or setting."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import yaml

torch = pytest.importorskip("torch")

from bopsurg.cli.main import main  # noqa: E402
from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.models.checkpoint import load_checkpoint  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("seg")
    ds = write_example_dataset(root, ExampleSpec(seed=4, scenes=2, images_per_scene=3))
    shutil.copytree(ds.root / "test", ds.root / "train")
    shutil.copytree(ds.root / "test", ds.root / "wide")
    return ds.root


def _train(dataset, out, *extra: str, epochs: int = 1) -> int:
    args = ["train", "seg", str(dataset), "--out", str(out), "--preset", "test"]
    tiny = ["--epochs", str(epochs), "--batch-size", "2", "--set", "recipe.steps_per_epoch=2"]
    return main([*args, *tiny, "--no-progress", *extra])


def _error(capsys, dataset, out, *extra: str) -> str:
    capsys.readouterr()
    assert _train(dataset, out, *extra) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    assert err.startswith("bopsurg: error: ")
    return err


def _weights(path):
    return load_checkpoint(path, "needle_seg")


def _same(a, b) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_seeded_two_splits_and_augmentation_recorded(dataset, tmp_path):
    both = ("--split", "train,wide", "--set", "augment.preset=domain")
    for name in ("a", "b"):
        assert _train(dataset, tmp_path / name, *both) == 0
    assert _train(dataset, tmp_path / "plain") == 0
    a, info = _weights(tmp_path / "a" / "needle_seg.pt")
    b, _ = _weights(tmp_path / "b" / "needle_seg.pt")
    plain, plain_info = _weights(tmp_path / "plain" / "needle_seg.pt")
    assert _same(a, b)
    assert not _same(a, plain)
    settings = info["meta"]["settings"]
    assert settings["split"] == "train,wide"
    assert settings["recipe"]["augment"]["jpeg_p"] > 0
    assert info["meta"]["instances"] > plain_info["meta"]["instances"]  # both splits read
    assert info["meta"]["arc"]["radius"] > 0  # what the estimator reads
    assert set(info["meta"]["validation"]) == {"val_iou_visib"}
    log = [json.loads(x) for x in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert np.isfinite(log[-1]["loss_total"])
    conf = yaml.safe_load((tmp_path / "a" / "config.yaml").read_text())
    assert conf["seg"]["roi"] == 64
    assert conf["recipe"]["steps_per_epoch"] == 2


def test_a_killed_run_resumes_to_the_weights_of_an_uninterrupted_one(
    dataset, tmp_path, kill_in_epoch
):
    extra = ("--set", "recipe.hue_whole=0.5", "--set", "augment.preset=domain")
    assert _train(dataset, tmp_path / "full", *extra, epochs=3) == 0
    with pytest.raises(kill_in_epoch(1)):
        _train(dataset, tmp_path / "part", *extra, epochs=3)
    kill_in_epoch(None)
    state = torch.load(tmp_path / "part" / "train_state.pt", weights_only=True)
    assert state["epoch"] == 0
    assert _train(dataset, tmp_path / "part", *extra, epochs=3) == 0  # resumes after epoch 0
    a, _ = _weights(tmp_path / "full" / "needle_seg.pt")
    b, _ = _weights(tmp_path / "part" / "needle_seg.pt")
    assert _same(a, b)


@pytest.mark.parametrize(
    ("setting", "needle"),
    [
        ("recipe.hue=0.7", "hue must lie in [0, 0.5] turns"),
        ("recipe.hue_whole=1.5", "hue_whole is a share of the crops"),
        ("seg.frame=whole", "frame 'whole' needs the full (amodal) mask"),
        ("seg.roi=100", "roi must be a positive multiple of 8"),
        ("seg.stagez=4", "seg: unknown key 'stagez'"),
        ("pose.roi_in=64", "section 'pose' configures a pose model, not a seg run"),
    ],
)
def test_bad_settings_are_one_line_errors(dataset, tmp_path, capsys, setting, needle):
    err = _error(capsys, dataset, tmp_path / "bad", "--set", setting)
    assert needle in err
    assert not (tmp_path / "bad").exists()


def test_a_missing_split_is_one_line(dataset, tmp_path, capsys):
    err = _error(capsys, dataset, tmp_path / "x", "--split", "train,nope")
    assert "nope" in err
    assert "split folder not found" in err


def test_the_former_entry_point_points_to_the_command(capsys):
    from bopsurg.models.refine.train_seg import main as former

    assert former(["data", "--out", "x"]) == 2
    assert "bopsurg train seg" in capsys.readouterr().err


def test_amodal_fine_tune_from_a_visible_mask_segmenter(dataset, tmp_path):
    """``recipe.init``: two output channels, both started from the one-channel checkpoint's
    output layer; the full-mask targets hold the visible; a deeper net keeps the rest."""
    from bopsurg.bop.dataset import BopDataset
    from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig
    from bopsurg.models.refine.train_seg import init_weights, load_contexts

    assert _train(dataset, tmp_path / "plain") == 0
    init = tmp_path / "plain" / "needle_seg.pt"
    amodal = ("--set", "seg.amodal=true", "--set", f"recipe.init={init}")
    assert _train(dataset, tmp_path / "am", *amodal) == 0
    state, info = _weights(tmp_path / "am" / "needle_seg.pt")
    assert info["config"]["amodal"] is True
    assert info["meta"]["settings"]["recipe"]["init"] == str(init)
    assert state["out.weight"].shape[0] == 2
    assert "val_iou_full" in info["meta"]["validation"]
    start = NeedleSegNet(SegConfig(roi=64, width=4, amodal=True))
    init_weights(start, init)
    plain, _ = _weights(init)
    for key in ("out.weight", "out.bias"):
        assert all(torch.equal(start.state_dict()[key][c], plain[key][0]) for c in (0, 1))
    ds = BopDataset(dataset, "train")
    masks = [m for _rgb, m, _box in load_contexts(ds, ds.scene_ids, 1, amodal=True)]
    assert all(m.shape[2] == 2 for m in masks)
    assert all((m[..., 1] >= m[..., 0]).all() for m in masks)  # full ⊇ visible
    assert sum(int(m[..., 1].sum() - m[..., 0].sum()) for m in masks) > 0  # some hidden wire
    deep = NeedleSegNet(SegConfig(roi=64, width=4, amodal=True, stages=4))
    init_weights(deep, tmp_path / "am" / "needle_seg.pt")  # the new stage starts afresh
    assert torch.equal(deep.state_dict()["enc3.0.weight"], state["enc3.0.weight"])
    assert _train(dataset, tmp_path / "bad", "--set", f"recipe.init={tmp_path / 'none.pt'}") == 2


def test_whole_frame_contexts_hold_the_full_mask(dataset, tmp_path):
    """``seg.frame: whole``: each context is cut around the visible box grown to the full
    mask's box, recorded in the config."""
    from bopsurg.bop.dataset import BopDataset
    from bopsurg.models.refine.train_seg import load_contexts

    ds = BopDataset(dataset, "train")
    for rgb, mask, box in load_contexts(ds, ds.scene_ids, 1, amodal=True, whole=True):
        rows, cols = np.nonzero(mask[..., 1])
        x, y, w, h = box
        assert rgb.shape[:2] == mask.shape[:2]
        assert x <= cols.min()
        assert y <= rows.min()
        assert x + w >= cols.max()
        assert y + h >= rows.max()
    whole = ("--set", "seg.amodal=true", "--set", "seg.frame=whole")
    assert _train(dataset, tmp_path / "w", *whole) == 0
    assert _weights(tmp_path / "w" / "needle_seg.pt")[1]["config"]["frame"] == "whole"
    with pytest.raises(ValueError, match="amodal"):
        load_contexts(ds, ds.scene_ids, 1, whole=True)


def test_the_recipe_of_the_shipped_segmenter_builds_its_network():
    """bopsurg/recipes/seg.yaml resolves to the shipped checkpoint's config, and the shipped
    weights load into the network the trainer builds from it."""
    from pathlib import Path

    from bopsurg.models.checkpoint import load_weights
    from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig

    root = Path(__file__).resolve().parents[2]
    recipe = root / "bopsurg" / "recipes" / "seg.yaml"
    conf = _dump(["train", "seg", "--config", str(recipe), "--dump-config"])
    state, info = _weights(root / "models" / "weights" / "needle_seg.pt")
    assert conf["seg"] == info["config"]
    shipped = info["meta"]["recipe"]
    steps = conf["recipe"]["epochs"] * conf["recipe"]["steps_per_epoch"]
    assert (steps, conf["recipe"]["batch_size"]) == (shipped["steps"], shipped["batch"])
    assert conf["recipe"]["hue_whole"] == info["meta"]["hue_whole"]
    load_weights(NeedleSegNet(SegConfig.from_dict(conf["seg"])), state, "needle_seg.pt")


def _dump(args: list[str]) -> dict:
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(args) == 0
    return yaml.safe_load(out.getvalue())
