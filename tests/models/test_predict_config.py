"""The prediction path's one typed configuration: defaults, overrides, errors, YAML back."""

from __future__ import annotations

import dataclasses

import pytest
import yaml

from bopsurg.errors import BopsurgError
from bopsurg.models.config_tree import from_mapping, to_dict, to_yaml
from bopsurg.models.predict_config import (
    SHIPPED_DIR,
    SHIPPED_FILES,
    FitSettings,
    PredictConfig,
    weight_file,
)
from bopsurg.options import merge, nest, parse_value, plugin_options, read_mapping


def _config(*pairs: str, base: dict | None = None) -> PredictConfig:
    return from_mapping(
        PredictConfig, plugin_options(None, [p.split("=", 1) for p in pairs], base or {})
    )


def test_no_options_give_the_one_default():
    assert _config() == PredictConfig()
    # the estimator and a bare refiner share one fit default (no second, generic one)
    assert PredictConfig().refine.fit == FitSettings()


def test_dotted_options_reach_nested_settings_with_yaml_values():
    cfg = _config(
        "refine.depth.weight=8",
        "head.zoom=[1]",
        "ends.classifier=none",
        "detect.input_hw=[384, 512]",
        "refine.recrop.passes=2",
        "refine.fit.prior_mm=[1, 2, 3]",
        "refine.depth.mode=none",
    )
    assert cfg.refine.depth.mode == "none"  # 'none' is null, and null the mode "none"
    assert cfg.refine.depth.weight == 8.0
    assert isinstance(cfg.refine.depth.weight, float)  # YAML's 8 is an int; a float is asked
    assert cfg.head.zoom == (1.0,)
    assert cfg.ends.classifier is None
    assert cfg.detect.input_hw == (384, 512)
    assert cfg.refine.recrop.passes == 2
    assert cfg.refine.fit.prior_mm == (1.0, 2.0, 3.0)
    # untouched siblings keep their defaults
    assert cfg.refine.depth.scale_mm == PredictConfig().refine.depth.scale_mm


@pytest.mark.parametrize(
    ("pair", "message"),
    [
        ("refine.depth.wieght=8", r"^gdrnet: refine\.depth\.wieght: unknown setting; known here: "),
        ("refine.fit.iterations=abc", r"refine\.fit\.iterations"),
        ("head.decode=icp", r"head\.decode"),
        ("refine=none", r"refine: is a section"),
        ("detect.max_per_object=0", r"detect\.max_per_object must be >= 1"),
        ("head.zoom=[0]", r"head\.zoom must be positive"),
        ("refine.recrop.growth=0.5", r"refine\.recrop\.growth"),
        ("ends.margin=.nan", r"ends\.margin must be a finite"),
        ("detect.input_hw=[100, 512]", r"multiples of 32"),
        ("detect.conf=true", r"detect\.conf"),
        # rules found on the AMBF frames, removed: a file that still sets one is refused
        ("refine.depth.unheld=true", r"^gdrnet: refine\.depth\.unheld: unknown setting"),
        ("refine.depth.lost_share=0.05", r"^gdrnet: refine\.depth\.lost_share: unknown"),
        ("ends.unheld_margin=0", r"^gdrnet: ends\.unheld_margin: unknown setting"),
        ("refine.fit.min_explained=0.7", r"^gdrnet: refine\.fit\.min_explained: unknown"),
        ("refine.recrop.undo_unimproved=true", r"refine\.recrop\.undo_unimproved: unknown"),
    ],
)
def test_bad_settings_are_one_line_errors_naming_the_key(pair, message):
    with pytest.raises(BopsurgError, match=message) as err:
        from_mapping(
            PredictConfig, nest([(pair.split("=")[0], parse_value(pair.split("=")[1]))]), "gdrnet"
        )
    assert "\n" not in str(err.value)


def test_the_resolved_config_is_a_config_file_that_reproduces_it(tmp_path):
    cfg = _config("refine.depth.weight=4", "head.zoom=[0.9, 1.1]", "ends.margin=0")
    path = tmp_path / "run.config.yaml"
    path.write_text(to_yaml(cfg))
    again = from_mapping(PredictConfig, read_mapping(path))
    assert again == cfg
    data = yaml.safe_load(path.read_text())
    assert list(data) == [f.name for f in dataclasses.fields(PredictConfig)]  # field order
    assert data == to_dict(cfg)


def test_file_then_options_then_flags_in_that_order(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("device: cuda\nrefine: {depth: {weight: 4, scale_mm: 0.3}}\n")
    data = plugin_options(path, [("refine.depth.weight", "8")], {"device": "auto", "x": 1})
    assert data == {"device": "cuda", "x": 1, "refine": {"depth": {"weight": 8, "scale_mm": 0.3}}}
    assert merge({"a": {"b": 1}}, {"a": {"c": 2}}) == {"a": {"b": 1, "c": 2}}
    with pytest.raises(BopsurgError, match="not a section"):
        nest([("a.b", 1)], {"a": 3})
    with pytest.raises(BopsurgError, match="empty part"):
        nest([("a..b", 1)])
    bad = tmp_path / "bad.yaml"
    bad.write_text("- a list\n")
    with pytest.raises(BopsurgError, match=r"bad\.yaml: expected a mapping"):
        read_mapping(bad)
    bad.write_text("a: [1\n")
    with pytest.raises(BopsurgError, match=r"bad\.yaml: not valid YAML"):
        read_mapping(bad)


def test_weight_files_are_named_never_guessed(tmp_path):
    for role, name in SHIPPED_FILES.items():
        assert weight_file(role, "shipped") == SHIPPED_DIR / name
    with pytest.raises(BopsurgError, match=r"mine\.pt: the segmenter weights file does not exist "
                       r"\(train it: bopsurg train seg"):  # fmt: skip
        weight_file("segmenter", str(tmp_path / "mine.pt"))


def test_a_missing_shipped_file_is_an_error_not_another_method(tmp_path, monkeypatch):
    pytest.importorskip("torch")
    from bopsurg.models import predict_config
    from bopsurg.models.estimator import create

    monkeypatch.setattr(predict_config, "SHIPPED_DIR", tmp_path)
    with pytest.raises(BopsurgError, match=r"needle_seg\.pt: .*reinstall bopsurg"):
        create({"detector": None, "pose": str(SHIPPED_DIR / "pose.pt"), "device": "cpu"})
