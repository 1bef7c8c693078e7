"""JSON reading and writing in the reference toolkit's layout."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest

from bopsurg.bop import load_json, save_json
from bopsurg.errors import DatasetError


def test_dict_layout_is_byte_exact(tmp_path: Path) -> None:
    path = tmp_path / "a.json"
    # Integer keys sort numerically (2 before 10), as the reference sorts the dict keys.
    save_json(path, {10: {"b": 1, "a": [1.0, 2]}, 2: 0.5, 3: "x"})
    expected = '{\n  "2": 0.5,\n  "3": "x",\n  "10": {"a": [1.0, 2], "b": 1}\n}'
    assert path.read_text(encoding="utf-8") == expected


def test_list_layout_is_byte_exact(tmp_path: Path) -> None:
    path = tmp_path / "a.json"
    save_json(path, [{"scene_id": 1, "im_id": 2}, {"b": 2.5}])
    expected = '[\n  {"im_id": 2, "scene_id": 1},\n  {"b": 2.5}\n]'
    assert path.read_text(encoding="utf-8") == expected


def test_empty_containers_and_scalars(tmp_path: Path) -> None:
    for content, text in (({}, "{\n}"), ([], "[\n]"), (3, "3")):
        save_json(tmp_path / "e.json", content)
        assert (tmp_path / "e.json").read_text() == text


def test_numpy_values_are_converted(tmp_path: Path) -> None:
    path = tmp_path / "n.json"
    save_json(path, {np.int64(1): {"v": np.arange(3), "s": np.float32(0.5), "i": np.int32(4)}})
    assert path.read_text() == '{\n  "1": {"i": 4, "s": 0.5, "v": [0, 1, 2]}\n}'


def test_keys_to_int_recursive_and_reference_rule(tmp_path: Path) -> None:
    path = tmp_path / "k.json"
    path.write_text('{"1": {"-2": 3, "a": {"07": 1}}, "x1": 2, "-": 0, "²": 5}')
    out = load_json(path, keys_to_int=True)
    assert out == {1: {-2: 3, "a": {7: 1}}, "x1": 2, "-": 0, "²": 5}
    assert load_json(path) == {"1": {"-2": 3, "a": {"07": 1}}, "x1": 2, "-": 0, "²": 5}


def test_round_trip_with_infinity(tmp_path: Path) -> None:
    path = tmp_path / "i.json"
    save_json(path, {"e": [float("inf"), 1.5]})
    assert path.read_text() == '{\n  "e": [Infinity, 1.5]\n}'
    assert load_json(path) == {"e": [float("inf"), 1.5]}


def test_gzip_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "g.json.gz"
    save_json(path, {1: [1, 2]})
    assert gzip.decompress(path.read_bytes()) == b'{\n  "1": [1, 2]\n}'
    assert load_json(path, keys_to_int=True) == {1: [1, 2]}


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="file not found") as e:
        load_json(tmp_path / "nope.json")
    assert str(tmp_path / "nope.json") in str(e.value)


def test_malformed_json_names_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text('{\n  "1": [1, 2],\n  "2": [3 4]\n}')
    with pytest.raises(DatasetError) as e:
        load_json(path)
    assert e.value.line == 3
    assert str(e.value).startswith(f"{path}:3: malformed JSON (")
    assert "\n" not in str(e.value)


def test_save_is_atomic_and_creates_parents(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "c.json"
    save_json(path, [1])
    assert path.read_text() == "[\n  1\n]"
    assert sorted(p.name for p in path.parent.iterdir()) == ["c.json"]


def test_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "e.json"
    path.write_text("  \n")
    with pytest.raises(DatasetError, match="empty file"):
        load_json(path)
