"""``bopsurg train ends`` on the shared epoch loop: a killed run resumes to the weights of an
uninterrupted one, the shipped classifier is its recipe's run, and the former entry
point says where the trainer went. (Seeding, the margin and errors: ``test_ends.py``.)"""

from __future__ import annotations

import contextlib
import io
import shutil
from pathlib import Path

import pytest
import yaml

torch = pytest.importorskip("torch")

from bopsurg.cli.main import main  # noqa: E402
from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.models.checkpoint import load_checkpoint, load_weights  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ends")
    ds = write_example_dataset(root, ExampleSpec(seed=4, scenes=3, images_per_scene=3))
    shutil.copytree(ds.root / "test", ds.root / "train")
    return ds.root


def _train(dataset, out, epochs: int) -> int:
    args = ["train", "ends", str(dataset), "--out", str(out), "--preset", "test"]
    tiny = ["--epochs", str(epochs), "--batch-size", "8", "--set", "recipe.steps_per_epoch=3"]
    return main([*args, *tiny, "--no-progress"])


def test_a_killed_run_resumes_to_the_weights_of_an_uninterrupted_one(
    dataset, tmp_path, kill_in_epoch
):
    assert _train(dataset, tmp_path / "full", 3) == 0
    with pytest.raises(kill_in_epoch(2)):
        _train(dataset, tmp_path / "part", 3)
    kill_in_epoch(None)
    assert torch.load(tmp_path / "part" / "train_state.pt", weights_only=True)["epoch"] == 1
    assert _train(dataset, tmp_path / "part", 3) == 0
    a, info = load_checkpoint(tmp_path / "full" / "needle_ends.pt", "needle_ends")
    b, _ = load_checkpoint(tmp_path / "part" / "needle_ends.pt", "needle_ends")
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    assert info["meta"]["epoch"] == 3
    assert info["meta"]["settings"]["recipe"]["augment"]["jpeg_p"] > 0  # domain by default


def test_the_shipped_classifier_is_its_recipes_run():
    """The shipped weights record the run of ``robust_ends.yaml`` as the recipe resolves
    today: network, recipe, augmentations, seed, preset, training and validation splits."""
    from bopsurg.models.refine.ends import EndConfig, EndNet

    out = io.StringIO()
    recipe = ROOT / "bopsurg" / "recipes" / "robust_ends.yaml"
    with contextlib.redirect_stdout(out):
        assert main(["train", "ends", "--config", str(recipe), "--dump-config"]) == 0
    conf = yaml.safe_load(out.getvalue())
    state, info = load_checkpoint(ROOT / "models" / "weights" / "needle_ends.pt", "needle_ends")
    run = info["meta"]["settings"]
    assert conf["ends"] == info["config"]
    assert run["recipe"] == {**conf["recipe"], "augment": conf["augment"]}
    assert (run["seed"], run["preset"]) == (conf["seed"], conf["preset"])
    assert run["split"] == ",".join(conf["data"]["train"])
    assert run["extra"]["val_split"] == ",".join(conf["data"]["val"])
    assert info["meta"]["epoch"] == conf["recipe"]["epochs"]  # its last epoch, not a pick
    load_weights(EndNet(EndConfig.from_dict(conf["ends"])), state, "needle_ends.pt")


def test_the_former_entry_point_points_to_the_command(capsys):
    from bopsurg.models.refine.train_ends import main as former

    assert former(["data", "--out", "x"]) == 2
    assert "bopsurg train ends" in capsys.readouterr().err
