"""The needle segmenter's trainer (``python -m bopsurg.models.refine.train_seg``): seeded,
reads several splits, augments on request, and fails in one line on a bad split."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.models.checkpoint import load_checkpoint  # noqa: E402
from bopsurg.models.refine.train_seg import main  # noqa: E402
from tests.models.cli_errors import one_line_error  # noqa: E402

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


def _seeded_pair_and_plain(dataset, tmp_path, *extra: str):
    """Two runs with ``extra`` (asserted equal) and one without (asserted different): the
    checkpoint info of the first and of the plain run."""
    for name in ("a", "b"):
        assert _train(dataset, tmp_path / name, *extra) == 0
    assert _train(dataset, tmp_path / "plain") == 0
    a, info = load_checkpoint(tmp_path / "a" / "needle_seg.pt", "needle_seg")
    b, _ = load_checkpoint(tmp_path / "b" / "needle_seg.pt", "needle_seg")
    plain, plain_info = load_checkpoint(tmp_path / "plain" / "needle_seg.pt", "needle_seg")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], plain[k]) for k in a)
    return info, plain_info


def test_seeded_two_splits_and_augmentation_recorded(dataset, tmp_path):
    both = ("--split", "train,wide", "--augment", "domain")
    info, plain_info = _seeded_pair_and_plain(dataset, tmp_path, *both)
    assert info["meta"]["split"] == "train,wide"
    assert info["meta"]["augment"] == "domain"
    assert info["meta"]["instances"] > plain_info["meta"]["instances"]  # both splits read
    assert "split" not in plain_info["meta"]


@pytest.mark.parametrize(
    ("flag", "key", "bad"),
    [("--hue", "hue", "0.7"), ("--hue-whole", "hue_whole", "1.5")],
    ids=["amplitude", "whole-circle share"],
)
def test_hue_shifts_are_seeded_recorded_and_checked(dataset, tmp_path, capsys, flag, key, bad):
    info, plain_info = _seeded_pair_and_plain(dataset, tmp_path, flag, "0.5")
    assert info["meta"][key] == 0.5
    assert key not in plain_info["meta"]
    assert _train(dataset, tmp_path / "bad", flag, bad) == 2
    assert flag in one_line_error(capsys)


def test_a_missing_split_is_one_line(dataset, tmp_path, capsys):
    assert _train(dataset, tmp_path / "x", "--split", "train,nope") == 2
    err = one_line_error(capsys)
    assert "nope" in err
    assert "split folder not found" in err


def test_amodal_fine_tune_from_a_visible_mask_segmenter(dataset, tmp_path):
    """``--amodal --init``: two output channels, both started from the one-channel
    checkpoint's output layer, the init recorded; the full-mask targets hold the visible."""
    from bopsurg.bop.dataset import BopDataset
    from bopsurg.models.refine.train_seg import load_contexts

    assert _train(dataset, tmp_path / "plain") == 0
    init = tmp_path / "plain" / "needle_seg.pt"
    assert _train(dataset, tmp_path / "am", "--amodal", "--init", str(init)) == 0
    state, info = load_checkpoint(tmp_path / "am" / "needle_seg.pt", "needle_seg")
    assert info["config"]["amodal"] is True
    assert info["meta"]["init"] == str(init)
    assert state["out.weight"].shape[0] == 2
    # before training, both channels are the one-channel checkpoint's output layer
    from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig
    from bopsurg.models.refine.train_seg import init_weights

    start = NeedleSegNet(SegConfig(roi=64, width=4, amodal=True))
    init_weights(start, init)
    plain, _ = load_checkpoint(init, "needle_seg")
    for key in ("out.weight", "out.bias"):
        assert all(torch.equal(start.state_dict()[key][c], plain[key][0]) for c in (0, 1))
    ds = BopDataset(dataset, "train")
    items = load_contexts(ds, ds.scene_ids, 1, False, amodal=True)
    masks = [m for _rgb, m, _box in items]
    assert all(m.shape[2] == 2 for m in masks)
    assert all((m[..., 1] >= m[..., 0]).all() for m in masks)  # full ⊇ visible
    assert sum(int(m[..., 1].sum() - m[..., 0].sum()) for m in masks) > 0  # some hidden wire
    # a deeper amodal net from it: the new stage starts afresh, the rest is loaded
    deep = ("--amodal", "--stages", "4", "--init", str(tmp_path / "am" / "needle_seg.pt"))
    assert _train(dataset, tmp_path / "deep", *deep, "--steps", "0") == 0
    deep_state, deep_info = load_checkpoint(tmp_path / "deep" / "needle_seg.pt", "needle_seg")
    assert deep_info["config"]["stages"] == 4
    assert "enc4.0.weight" in deep_state
    assert torch.equal(deep_state["enc3.0.weight"], state["enc3.0.weight"])
    # a missing init is one line
    assert _train(dataset, tmp_path / "bad", "--init", str(tmp_path / "none.pt")) == 2


def test_whole_frame_contexts_hold_the_full_mask_and_need_it(dataset, tmp_path, capsys):
    """``--frame whole``: each context is cut around the visible box grown to the full mask's
    box, recorded in the config; without ``--amodal`` it is a one-line error."""
    from bopsurg.bop.dataset import BopDataset
    from bopsurg.models.refine.train_seg import load_contexts

    ds = BopDataset(dataset, "train")
    for rgb, mask, box in load_contexts(ds, ds.scene_ids, 1, False, amodal=True, whole=True):
        rows, cols = np.nonzero(mask[..., 1])
        x, y, w, h = box
        assert rgb.shape[:2] == mask.shape[:2]
        assert x <= cols.min()
        assert y <= rows.min()
        assert x + w >= cols.max()
        assert y + h >= rows.max()
    assert _train(dataset, tmp_path / "w", "--amodal", "--frame", "whole") == 0
    _, info = load_checkpoint(tmp_path / "w" / "needle_seg.pt", "needle_seg")
    assert info["config"]["frame"] == "whole"
    with pytest.raises(ValueError, match="amodal"):
        load_contexts(ds, ds.scene_ids, 1, False, whole=True)
    assert _train(dataset, tmp_path / "bad", "--frame", "whole") == 2
    assert "amodal" in one_line_error(capsys)
