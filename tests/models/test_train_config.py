"""``bopsurg train --config FILE``: every field of the model, recipe, augment and loader
settings from a YAML/JSON file, flags on top, the resolved file written into the run folder,
and a resume with another configuration refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

torch = pytest.importorskip("torch")

from bopsurg.cli.main import main  # noqa: E402
from bopsurg.example import ExampleSpec, write_example_dataset  # noqa: E402
from bopsurg.models.checkpoint import load_tensors  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("cfg")
    return write_example_dataset(root, ExampleSpec(seed=1, scenes=2, images_per_scene=4)).root


def _dump(capsys, *args: str) -> dict:
    capsys.readouterr()
    assert main(["train", *args, "--dump-config"]) == 0
    return yaml.safe_load(capsys.readouterr().out)


def _write(path, text: str):
    path.write_text(text, encoding="utf-8")
    return str(path)


def _error(capsys, args: list[str]) -> str:
    capsys.readouterr()
    assert main(["train", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    return err


def test_dump_config_gives_every_field_and_round_trips(tmp_path, capsys):
    conf = _dump(capsys, "pose", "--preset", "test")
    assert set(conf) == {"preset", "seed", "pose", "recipe", "augment", "loader"}
    assert conf["pose"]["roi_in"] == 64
    assert conf["pose"]["w_region"] == 1.0
    assert conf["recipe"]["epochs"] == 40
    assert conf["augment"]["jpeg_p"] == 0.0
    assert conf["loader"] == {
        "num_workers": 0, "cache_mb": 4096, "cache_items": None, "shared_cache": True,
    }  # fmt: skip
    again = _dump(capsys, "pose", "--config", _write(tmp_path / "c.yaml", yaml.safe_dump(conf)))
    assert again == conf
    det = _dump(capsys, "detector", "--preset", "s")
    assert det["detector"]["input_hw"] == [480, 640]
    assert "pose" not in det


def test_the_file_sets_fields_and_flags_override_it(tmp_path, capsys):
    path = _write(
        tmp_path / "pose.yaml",
        "preset: test\nseed: 3\npose: {z_unit_mm: 100, roi_in: 160}\n"
        "recipe: {epochs: 9, lr: 1e-3, hsv: [0.0, 0.1, 0.2]}\n"
        "augment: {preset: domain, blur_sigma: [1, 2]}\nloader: {num_workers: 1}\n",
    )
    conf = _dump(capsys, "pose", "--config", path)
    assert conf["preset"] == "test"
    assert conf["seed"] == 3
    assert conf["pose"]["z_unit_mm"] == 100.0
    assert conf["pose"]["roi_in"] == 160
    assert conf["pose"]["num_regions"] == 8  # the rest from the test preset
    assert conf["recipe"]["lr"] == 0.001
    assert conf["recipe"]["hsv"] == [0.0, 0.1, 0.2]
    assert conf["augment"]["blur_p"] == 0.3
    assert conf["augment"]["blur_sigma"] == [1.0, 2.0]
    assert conf["loader"]["num_workers"] == 1
    old = _write(tmp_path / "old.yaml", "loader: {num_workers: 0, cache_items: 0}\n")
    assert _dump(capsys, "pose", "--config", old)["loader"]["cache_items"] == 0  # still no cache
    flags = ["--epochs", "2", "--lr", "0.5", "--seed", "0", "--workers", "0", "--symmetric"]
    conf = _dump(capsys, "pose", "--config", path, *flags)
    assert conf["recipe"]["epochs"] == 2
    assert conf["recipe"]["lr"] == 0.5
    assert conf["seed"] == 0
    assert conf["loader"]["num_workers"] == 0
    assert conf["recipe"]["symmetric"] is True
    assert conf["pose"]["symmetric"] is True
    jpath = _write(tmp_path / "det.json", json.dumps({"detector": {"width": 0.5}}))
    assert _dump(capsys, "detector", "--config", jpath)["detector"]["width"] == 0.5


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("pose: {roi_inn: 160}\n", "pose: unknown key 'roi_inn'"),
        ("augmnt: {blur_p: 1}\n", "unknown key 'augmnt'"),
        ("augment: {blur_q: 1}\n", "augment: unknown key 'blur_q'"),
        ("recipe: {lr: fast}\n", "recipe.lr: expected a number"),
        ("recipe: {epochs: 2.5}\n", "recipe.epochs: expected an integer"),
        ("pose: {roi_in: 100}\n", "roi_in must be a positive multiple of 32"),
        ("detector: {width: 1}\n", "section 'detector' configures a detector"),
        ("recipe: {augment: {blur_p: 1}}\n", "use the top-level 'augment' section"),
        ("augment: {preset: heavy}\n", "unknown augment preset"),
        ("[1, 2]\n", "expected a mapping"),
        ("pose: {roi_in: [\n", "not valid YAML"),
        ("loader: {cache_mb: -1}\n", "loader.num_workers and loader.cache_mb must be >= 0"),
        ("loader: {cache_mb: 1.5}\n", "loader.cache_mb: expected an integer"),
        ("loader: {cache_items: many}\n", "loader.cache_items must be null or an integer"),
        ("loader: {cache_items: -2}\n", "loader.cache_items must be >= 0"),
        ("recipe: {hue_whole: 1.5}\n", "recipe: hue_whole is a share of the samples, in [0, 1]"),
        ("recipe: {mirror: -0.1}\n", "recipe: mirror is a share of the samples, in [0, 1]"),
        ("recipe: {roll: 2}\n", "recipe: roll is a share of the samples, in [0, 1]"),
        ("recipe: {roll_deg: 270}\n", "recipe: roll_deg is the largest turn, in [0, 180] deg"),
    ],
)
def test_bad_files_are_one_line_errors_naming_file_and_key(tmp_path, capsys, text, needle):
    path = _write(tmp_path / "bad.yaml", text)
    err = _error(capsys, ["pose", "--config", path, "--dump-config"])
    assert err.startswith("bopsurg: error: --config ")
    assert str(path) in err
    assert needle in err


def test_a_configured_run_writes_its_config_and_refuses_another_on_resume(
    dataset, tmp_path, capsys
):
    out = tmp_path / "run"
    path = _write(
        tmp_path / "det.yaml",
        "preset: test\ndetector: {width: 0.125, depth: 0.25}\n"
        "recipe: {epochs: 1, batch_size: 2, val_every: 1}\naugment: {preset: domain}\n",
    )
    common = ["detector", str(dataset), "--split", "test", "--out", str(out), "--no-progress"]
    assert main(["train", *common, "--config", path]) == 0
    written = yaml.safe_load((out / "config.yaml").read_text())
    assert written["detector"]["depth"] == 0.25
    assert written["augment"]["gamma_p"] == 0.5
    info = json.loads((out / "detector.json").read_text())
    assert info["config"]["depth"] == 0.25
    assert info["meta"]["settings"]["recipe"]["augment"]["jpeg_p"] == 0.3
    # the written file reproduces the run: a resume from it (with more epochs) is accepted
    resumed = ["train", *common, "--config", str(out / "config.yaml"), "--epochs", "2"]
    assert main(resumed) == 0
    assert [json.loads(x)["epoch"] for x in (out / "log.jsonl").read_text().splitlines()] == [0, 1]
    changed = _write(tmp_path / "other.yaml", (out / "config.yaml").read_text().replace(
        "depth: 0.25", "depth: 0.5"))  # fmt: skip
    err = _error(capsys, [*common, "--config", changed, "--epochs", "3"])
    assert "other settings (model.depth)" in err
    assert "0.25 -> 0.5" in err
    err = _error(capsys, [*common, "--config", str(out / "config.yaml"), "--lr", "0.1"])
    assert "recipe.lr" in err


def test_a_run_of_an_older_bopsurg_resumes(dataset, tmp_path):
    """train_state.json written before model configs and augmentations were recorded."""
    out = tmp_path / "old"
    common = ["train", "detector", str(dataset), "--split", "test", "--out", str(out)]
    args = [*common, "--preset", "test", "--batch-size", "2", "--no-progress"]
    assert main([*args, "--epochs", "1"]) == 0
    settings = json.loads((out / "train_state.json").read_text())
    del settings["model"], settings["recipe"]["augment"], settings["recipe"]["hsv"]
    del settings["recipe"]["hue_whole"]
    (out / "train_state.json").write_text(json.dumps(settings))
    assert main([*args, "--epochs", "2"]) == 0
    assert load_tensors(out / "detector.pt")  # resumed, not refused


def test_the_detector_recipe_sets_its_colour_jitter(dataset, tmp_path, capsys):
    """``recipe.hsv``: the old fixed jitter by default; a full hue circle trains otherwise,
    for every image or (``hue_whole``) for a share of them."""
    dumped = _dump(capsys, "detector", "--preset", "test")["recipe"]
    assert dumped["hsv"] == [0.015, 0.7, 0.4]
    assert dumped["hue_whole"] == 0.0
    bad = _write(tmp_path / "bad.yaml", "recipe: {hue_whole: 2}\n")
    err = _error(capsys, ["detector", "--config", bad, "--dump-config"])
    assert "recipe: hue_whole is a share of the images, in [0, 1], got 2" in err
    weights = {}
    for name, recipe in (
        ("a", "hsv: [0.5, 0.7, 0.4]"),
        ("b", "hsv: [0.5, 0.7, 0.4]"),
        ("old", "hsv: [0.015, 0.7, 0.4]"),
        ("share", "hsv: [0.015, 0.7, 0.4], hue_whole: 1.0"),
    ):
        cfg = _write(tmp_path / f"{name}.yaml", f"preset: test\nrecipe: {{epochs: 1, {recipe}}}\n")
        out = tmp_path / name
        args = ["train", "detector", str(dataset), "--split", "test", "--out", str(out)]
        assert main([*args, "--config", cfg, "--batch-size", "2", "--no-progress"]) == 0
        written = yaml.safe_load((out / "config.yaml").read_text())["recipe"]
        asked = yaml.safe_load(f"{{{recipe}}}")
        assert {k: written[k] for k in asked} == asked
        weights[name] = load_tensors(out / "detector.pt")
    assert all(torch.equal(weights["a"][k], weights["b"][k]) for k in weights["a"])
    for other in ("old", "share"):
        assert any(not torch.equal(weights["a"][k], weights[other][k]) for k in weights["a"])
    assert any(not torch.equal(weights["old"][k], weights["share"][k]) for k in weights["a"])


def test_a_pose_run_from_before_the_mirror_resumes(tmp_path):
    """train_state.json written before ``recipe.mirror``, ``mirror_splits``, ``hue_whole``,
    ``roll`` and ``roll_deg``."""
    from bopsurg.bop.dataset import BopDataset
    from tests.models.plane_depth import write_plane_depth

    ex = write_example_dataset(tmp_path / "d", ExampleSpec(seed=1, scenes=2, images_per_scene=2))
    write_plane_depth(BopDataset(ex.root, ex.split))
    out = tmp_path / "old"
    common = ["train", "pose", str(ex.root), "--split", ex.split, "--out", str(out)]
    args = [*common, "--preset", "test", "--batch-size", "2", "--no-progress", "--threads", "1"]
    assert main([*args, "--epochs", "1"]) == 0
    settings = json.loads((out / "train_state.json").read_text())
    del settings["recipe"]["mirror"], settings["recipe"]["mirror_splits"]
    del settings["recipe"]["hue_whole"], settings["recipe"]["roll"], settings["recipe"]["roll_deg"]
    (out / "train_state.json").write_text(json.dumps(settings))
    assert main([*args, "--epochs", "2"]) == 0
    recipe = json.loads((out / "train_state.json").read_text())["recipe"]
    assert (recipe["mirror"], recipe["roll"]) == (0.0, 0.0)


RECIPES = sorted((Path(__file__).parents[2] / "bopsurg" / "recipes").glob("*.yaml"))


@pytest.mark.parametrize("recipe", RECIPES, ids=lambda p: p.name)
def test_shipped_recipes_resolve_and_say_what_they_set(recipe, capsys):
    """The model card's commands pass these files to ``bopsurg train --config``: each must
    still resolve (no key renamed away under it), and every value it sets must reach the run."""
    kinds = ("detector", "seg", "ends")
    kind = next((k for k in kinds if k in recipe.stem.split("_")), "pose")
    conf = _dump(capsys, kind, "--config", str(recipe))
    for section, values in yaml.safe_load(recipe.read_text(encoding="utf-8")).items():
        if not isinstance(values, dict):
            assert conf[section] == values, section
            continue
        for key, value in values.items():
            if key != "preset":  # augment's named starting set, resolved into its fields
                assert conf[section][key] == value, f"{section}.{key}"


@pytest.mark.parametrize(
    ("item", "needle"),
    [
        ("recipe.lr", "--set 'recipe.lr': expected SECTION.KEY=VALUE"),
        ("recipes.lr=1", "unknown section 'recipes'"),
        ("recipe.lr=[1", "the value is not valid YAML"),
        ("recipe.lrr=1", "recipe: unknown key 'lrr'"),
    ],
)
def test_set_overrides_one_field_after_the_file_and_flags(tmp_path, capsys, item, needle):
    path = _write(tmp_path / "c.yaml", "recipe: {lr: 0.1, epochs: 3}\nseed: 2\n")
    conf = _dump(capsys, "pose", "--config", path, "--lr", "0.2", "--set", "recipe.lr=0.3")
    assert (conf["recipe"]["lr"], conf["recipe"]["epochs"], conf["seed"]) == (0.3, 3, 2)
    assert _dump(capsys, "pose", "--set", "seed=5", "--set", "pose.roi_in=160")["seed"] == 5
    assert needle in _error(capsys, ["pose", "--set", item, "--dump-config"])


@pytest.mark.parametrize("kind", ["detector", "seg", "ends"])  # pose: needs depth
def test_every_model_trains_in_bfloat16(dataset, tmp_path, kind):
    """``recipe.precision: bf16`` (a GPU's fast path, autocast) runs on the CPU too: every
    trainer's step, its losses finite and logged with the loop's speed and wait share."""
    out = tmp_path / kind
    args = ["train", kind, str(dataset), "--split", "test", "--out", str(out), "--no-progress"]
    tiny = ["--preset", "test", "--epochs", "1", "--batch-size", "2"]
    steps = ["--set", "recipe.steps_per_epoch=2", "--set", "recipe.precision=bf16"]
    assert main([*args, *tiny, *steps]) == 0
    record = json.loads((out / "log.jsonl").read_text().splitlines()[-1])
    assert np.isfinite(record["loss_total"])
    assert record["samples_per_s"] > 0
    assert 0 <= record["data_wait"] < 1
