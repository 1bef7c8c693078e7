"""Data specs (a recipe's ``data:`` section, bench/robust_splits.yaml): parsing, one line per
bad field, independence of the roles, the finished-split marker, the data command's checks."""

from __future__ import annotations

import pytest
import yaml

from bopsurg.cli.main import main
from bopsurg.data_spec import (
    MARKER,
    is_made,
    made_from_other,
    mark_made,
    missing_splits,
    parse_data_spec,
)
from bopsurg.errors import BopsurgError

GOOD = {
    "splits": {
        "train_a": {"domain": "paper", "bags": [501, 502], "replays": 3, "seed": 51},
        "val_a": {"domain": "wide", "bags": [301], "replays": 2, "period": 1, "seed": 31},
    },
    "train": ["train_a"],
    "val": ["val_a"],
}


def test_a_good_spec_and_its_commands(tmp_path):
    spec = parse_data_spec(GOOD)
    assert spec.train == ("train_a",)
    assert spec.val == ("val_a",)
    assert spec.test == ()
    a = spec.splits["train_a"]
    assert (a.duration, a.period, a.rgb_format, a.min_visib) == (30.0, 2.0, "png", 0.1)
    assert a.record_argv(tmp_path, 501) == [
        "--out", str(tmp_path / "seed501_30s.bag"), "--seed", "501", "--duration", "30",
    ]  # fmt: skip
    argv = a.generate_argv(tmp_path / "data", tmp_path)
    assert argv[:2] == [str(tmp_path / "seed501_30s.bag"), str(tmp_path / "seed502_30s.bag")]
    assert argv[argv.index("--split") + 1] == "train_a"
    assert argv[argv.index("--domain") + 1] == "paper"
    assert argv[argv.index("--seed") + 1] == "51"
    assert [s.name for s in spec.selected(("val_a",))] == ["val_a"]
    with pytest.raises(BopsurgError, match="no split nope"):
        spec.selected(("nope",))


def test_every_bad_field_is_its_own_line():
    bad = {
        "splits": {
            "a": {"domain": "x", "bags": [1, 1], "replays": 0, "foo": 1, "period": -1},
            "b": {"domain": "wide", "bags": [2], "replays": 1, "seed": 3},
        },
        "val": ["b", "c"],
        "bar": 1,
    }
    with pytest.raises(BopsurgError) as err:
        parse_data_spec(bad, "f.yaml", "data.")
    lines = str(err.value).splitlines()
    expected = [
        "f.yaml: data.bar: unknown key",
        "f.yaml: data.splits.a.foo: unknown field",
        "f.yaml: data.splits.a.seed: missing",
        "f.yaml: data.splits.a.domain: must be one of paper, wide",
        "f.yaml: data.splits.a.bags: a seed is listed twice",
        "f.yaml: data.splits.a.replays: must be an integer >= 1",
        "f.yaml: data.splits.a.period: must be a number > 0",
        "f.yaml: data.val: 'c' is not a split",
    ]
    assert len(lines) == len(expected)
    for line, start in zip(lines, expected, strict=True):
        assert line.startswith(start), (line, start)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"val": ["train_a"]}, "'train_a' is also a train split"),
        ({"train": ["val_a"], "val": []}, "a train split's name must start with 'train'"),
        ({"splits": {**GOOD["splits"], "val_b": {**GOOD["splits"]["val_a"], "bags": [502]}},
          "val": ["val_b"]}, "bag 502 is also used by the train split 'train_a'"),
        ({"splits": {**GOOD["splits"], "val_b": {**GOOD["splits"]["val_a"], "seed": 51}},
          "val": ["val_b"]}, "generate seed 51 is also used by the train split"),
        ({"train": "train_a"}, "expected a list of split names"),
        ({"splits": {**GOOD["splits"], "val_a": {**GOOD["splits"]["val_a"], "domain": "paper",
          "domain_revision": 4}}}, "val_a.domain_revision: only the wide domain has revisions"),
        ({"splits": {**GOOD["splits"], "val_a": {**GOOD["splits"]["val_a"],
          "domain_revision": 0}}}, "val_a.domain_revision: must be an integer >= 1"),
        ({"splits": {}}, "splits: expected a mapping"),
    ],
)  # fmt: skip
def test_roles_stay_apart(change, message):
    with pytest.raises(BopsurgError, match=message):
        parse_data_spec({**GOOD, **change})


def test_the_marker_says_which_spec_made_a_split(tmp_path):
    spec = parse_data_spec(GOOD)
    a = spec.splits["train_a"]
    assert not is_made(tmp_path, a)
    assert made_from_other(tmp_path, a) is None
    (tmp_path / "train_a").mkdir()
    mark_made(tmp_path, a)
    assert (tmp_path / "train_a" / MARKER).is_file()
    assert is_made(tmp_path, a)
    assert missing_splits(tmp_path, spec.selected()) == [spec.splits["val_a"]]
    other = parse_data_spec(
        {**GOOD, "splits": {**GOOD["splits"], "train_a": {**GOOD["splits"]["train_a"],
                                                          "replays": 4}}}
    ).splits["train_a"]  # fmt: skip
    assert not is_made(tmp_path, other)
    assert made_from_other(tmp_path, other) == "replays"


def test_the_data_command_refuses_bad_specs_and_other_specs(tmp_path, capsys):
    f = tmp_path / "bad.yaml"
    f.write_text("splits:\n  val_x: {domain: paper, bags: [1], replays: 1}\nval: [val_x]\n")
    assert main(["data", str(f), "--root", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"bopsurg: error: {f}: splits.val_x.seed: missing"]
    good = tmp_path / "good.yaml"
    good.write_text(yaml.safe_dump(GOOD))
    spec = parse_data_spec({**GOOD, "splits": {**GOOD["splits"], "val_a": {
        **GOOD["splits"]["val_a"], "seed": 33}}})  # fmt: skip
    (tmp_path / "d" / "val_a").mkdir(parents=True)
    mark_made(tmp_path / "d", spec.splits["val_a"])
    assert main(["data", str(good), "--root", str(tmp_path / "d"), "--only", "val_a"]) == 2
    assert "made from another spec of split 'val_a' (differs in seed)" in capsys.readouterr().err


def test_dry_run_prints_the_commands_and_runs_none(tmp_path, capsys):
    good = tmp_path / "good.yaml"
    good.write_text(yaml.safe_dump(GOOD))
    root = tmp_path / "d"
    assert main(["data", str(good), "--root", str(root), "--role", "val", "--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    bags = tmp_path / "bags"
    assert out[0] == f"$ bopsurg record --out {bags}/seed301_30s.bag --seed 301 --duration 30"
    assert out[1].startswith(f"$ bopsurg generate {bags}/seed301_30s.bag --out {root} ")
    assert "--split val_a --domain wide --replays 2 --period 1 --seed 31" in out[1]
    assert len(out) == 3
    assert out[2].startswith("would make 1 split(s)")
    assert not root.exists()
    assert not bags.exists()
