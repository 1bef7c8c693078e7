"""``bopsurg train ends`` on the shared epoch loop: a killed run resumes to the weights of an
uninterrupted one, the shipped classifier's recipe builds its network, and the former entry
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


def test_the_recipe_of_the_shipped_classifier_builds_its_network():
    from bopsurg.models.refine.ends import EndConfig, EndNet

    out = io.StringIO()
    recipe = ROOT / "bopsurg" / "recipes" / "ends.yaml"
    with contextlib.redirect_stdout(out):
        assert main(["train", "ends", "--config", str(recipe), "--dump-config"]) == 0
    conf = yaml.safe_load(out.getvalue())
    state, info = load_checkpoint(ROOT / "models" / "weights" / "needle_ends.pt", "needle_ends")
    assert conf["ends"] == info["config"]
    shipped = info["meta"]["recipe"]
    steps = conf["recipe"]["epochs"] * conf["recipe"]["steps_per_epoch"]
    assert (steps, conf["recipe"]["batch_size"]) == (shipped["steps"], shipped["batch"])
    assert conf["recipe"]["margin"] == info["meta"]["margin"]
    assert conf["recipe"]["turn_deg"] == shipped["turn_deg"]
    load_weights(EndNet(EndConfig.from_dict(conf["ends"])), state, "needle_ends.pt")


def test_the_former_entry_point_points_to_the_command(capsys):
    from bopsurg.models.refine.train_ends import main as former

    assert former(["data", "--out", "x"]) == 2
    assert "bopsurg train ends" in capsys.readouterr().err
