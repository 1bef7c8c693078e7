"""Training on several splits at once (``--split train,train_wide``) and fine-tuning from an
exported checkpoint (``--init PT`` / ``recipe.init``)."""

from __future__ import annotations

import json
import shutil

import pytest
import yaml

torch = pytest.importorskip("torch")

from bopsurg.bop.dataset import BopDataset  # noqa: E402
from bopsurg.cli.main import main  # noqa: E402
from bopsurg.errors import DatasetError  # noqa: E402
from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.models.checkpoint import load_checkpoint  # noqa: E402
from bopsurg.models.data import SCENE_ID_STRIDE, SplitUnion, open_split  # noqa: E402
from bopsurg.models.training import open_splits  # noqa: E402
from tests.models.plane_depth import write_plane_depth  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """An example dataset with depth (a plane at the needle, for the pose head's coordinates)
    and a second split ``extra`` (a copy of ``test``, 3 scenes)."""
    root = tmp_path_factory.mktemp("ft")
    ex = write_example_dataset(root, ExampleSpec(seed=2, scenes=3, images_per_scene=3))
    write_plane_depth(BopDataset(ex.root, ex.split))
    shutil.copytree(ex.root / "test", ex.root / "extra")
    return ex.root


def test_a_union_offsets_the_later_splits_scene_ids(dataset):
    one = BopDataset(dataset, "test")
    both = open_split(dataset, "test,extra")
    assert isinstance(both, SplitUnion)
    assert both.split == "test,extra"
    assert both.scene_ids == one.scene_ids + [SCENE_ID_STRIDE + s for s in one.scene_ids]
    sid = one.scene_ids[1]
    assert both.scene(sid).scene_dir == one.scene(sid).scene_dir
    assert both.scene(SCENE_ID_STRIDE + sid).scene_dir == dataset / "extra" / f"{sid:06d}"
    assert both.scene(SCENE_ID_STRIDE + sid).gt == one.scene(sid).gt
    assert both.models_info == one.models_info
    assert type(open_split(dataset, "test")) is BopDataset
    splits = open_splits(dataset, "test,extra", None)
    assert sorted(splits.train_ids + splits.val_ids) == both.scene_ids
    assert splits.val_ids == both.scene_ids[-1:]  # fewer than 10 scenes: the last held out


@pytest.mark.parametrize(
    ("names", "needle"),
    [("test,nope", "split folder not found"), ("test,test", "named twice"), ("test,", "empty")],
)
def test_bad_unions_are_dataset_errors(dataset, names, needle):
    with pytest.raises(DatasetError, match=needle):
        open_split(dataset, names)
    with pytest.raises(DatasetError, match="no scene"):
        SplitUnion(dataset, ["test", "extra"]).scene(5 * SCENE_ID_STRIDE + 1)


def _train(dataset, out, *extra: str) -> int:
    args = ["train", "detector", str(dataset), "--split", "test,extra", "--out", str(out)]
    return main([*args, "--preset", "test", "--batch-size", "2", "--no-progress", *extra])


def _distance(a, b) -> float:
    """L1 distance of the learnt weights (batch-norm statistics move even without learning)."""
    keys = [k for k in a if a[k].is_floating_point() and "running" not in k]
    return sum(float((a[k] - b[k]).abs().sum()) for k in keys)


def test_init_starts_from_the_checkpoint_and_is_recorded(dataset, tmp_path):
    assert _train(dataset, tmp_path / "a", "--epochs", "1") == 0
    start = tmp_path / "a" / "detector.pt"
    a, _ = load_checkpoint(start, "detector")
    # with a vanishing learning rate, a fine-tuned run stays at its start; a fresh one does not
    frozen = ("--epochs", "1", "--lr", "1e-12", "--seed", "5")
    assert _train(dataset, tmp_path / "ft", *frozen, "--init", str(start)) == 0
    assert _train(dataset, tmp_path / "fresh", *frozen) == 0
    ft, info = load_checkpoint(tmp_path / "ft" / "detector.pt", "detector")
    fresh, _ = load_checkpoint(tmp_path / "fresh" / "detector.pt", "detector")
    assert _distance(ft, a) < 1e-3 * _distance(fresh, a)
    assert info["meta"]["settings"]["recipe"]["init"] == str(start)
    assert info["meta"]["settings"]["split"] == "test,extra"
    written = yaml.safe_load((tmp_path / "ft" / "config.yaml").read_text())
    assert written["recipe"]["init"] == str(start)
    log = [json.loads(x) for x in (tmp_path / "ft" / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in log] == [0]


def test_an_init_of_another_model_is_a_one_line_error(dataset, tmp_path, capsys):
    assert _train(dataset, tmp_path / "a", "--epochs", "1") == 0
    start = str(tmp_path / "a" / "detector.pt")
    other = tmp_path / "w.yaml"
    other.write_text("detector: {width: 0.25}\n")
    for extra, needle in (
        (("--config", str(other)), "config differs from this run's (width"),
        ((), "not found"),
    ):
        capsys.readouterr()
        init = start if extra else str(tmp_path / "missing.pt")
        assert _train(dataset, tmp_path / "b", "--epochs", "1", "--init", init, *extra) == 2
        errors = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
        assert len(errors) == 1, errors
        assert needle in errors[0]
    capsys.readouterr()
    args = ["train", "pose", str(dataset), "--split", "test", "--out", str(tmp_path / "p")]
    assert main([*args, "--preset", "test", "--init", start, "--no-progress"]) == 2
    assert "holds a 'detector' model, expected 'pose'" in capsys.readouterr().err


def test_a_detector_fine_tunes_at_another_input_size(dataset, tmp_path):
    """The input size is no part of the weights: a detector trained small trains on larger."""
    assert _train(dataset, tmp_path / "a", "--epochs", "1") == 0
    start = tmp_path / "a" / "detector.pt"
    larger = tmp_path / "hw.yaml"
    larger.write_text("detector: {input_hw: [96, 128]}\n")
    assert _train(dataset, tmp_path / "b", "--epochs", "1", "--init", str(start), "--config",
                  str(larger)) == 0  # fmt: skip
    _, info = load_checkpoint(tmp_path / "b" / "detector.pt", "detector")
    assert info["config"]["input_hw"] == [96, 128]
    assert info["meta"]["settings"]["recipe"]["init"] == str(start)


def test_a_pose_head_fine_tunes_with_other_loss_weights_not_other_sizes(dataset, tmp_path, capsys):
    args = ["train", "pose", str(dataset), "--split", "test,extra", "--preset", "test"]
    args += ["--batch-size", "2", "--epochs", "1", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    start = str(tmp_path / "a" / "pose.pt")
    weights = tmp_path / "wz.yaml"
    weights.write_text("pose: {w_z: 10.0, dzi_shift: 0.1}\n")  # training only: accepted
    assert (
        main([*args, "--out", str(tmp_path / "b"), "--init", start, "--config", str(weights)]) == 0
    )
    sizes = tmp_path / "roi.yaml"
    sizes.write_text("pose: {z_unit_mm: 100.0}\n")  # changes what the output means: refused
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "c"), "--init", start, "--config", str(sizes)]) == 2
    errors = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
    assert len(errors) == 1, errors
    assert "config differs from this run's (z_unit_mm;" in errors[0]
    # a head trained for another object's normaliser would predict mislabelled coordinates
    info_path = tmp_path / "a" / "pose.json"
    info = json.loads(info_path.read_text())
    info["meta"]["xyz_scale"] *= 2
    info_path.write_text(json.dumps(info))
    assert main([*args, "--out", str(tmp_path / "d"), "--init", start]) == 2
    errors = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
    assert len(errors) == 1, errors
    assert "its meta 'xyz_scale' differs from this dataset's object" in errors[0]
