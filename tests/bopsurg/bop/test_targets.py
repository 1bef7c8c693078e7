"""Evaluation targets: file round trip and enumeration as the reference script does it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bopsurg.bop import GtInfo, GtPose, Target, enumerate_targets, load_targets, save_targets
from bopsurg.errors import DatasetError


def test_round_trip_reference_layout(tmp_path: Path) -> None:
    path = tmp_path / "test_targets_bop19.json"
    targets = [Target(1, 0, 5, 2), Target(1, 3, 1, 1)]
    save_targets(path, targets)
    assert path.read_text() == (
        '[\n  {"im_id": 0, "inst_count": 2, "obj_id": 5, "scene_id": 1},\n'
        '  {"im_id": 3, "inst_count": 1, "obj_id": 1, "scene_id": 1}\n]'
    )
    assert load_targets(path) == targets


@pytest.mark.parametrize(
    ("entry", "field", "reason"),
    [
        ('{"im_id": 0, "inst_count": 0, "obj_id": 5, "scene_id": 1}', "1/inst_count", ">= 1"),
        ('{"im_id": 0, "inst_count": 1.5, "obj_id": 5, "scene_id": 1}', "1/inst_count", "integer"),
        ('{"im_id": 0, "inst_count": 1, "scene_id": 1}', "1/obj_id", "missing"),
    ],
)
def test_bad_targets(tmp_path: Path, entry: str, field: str, reason: str) -> None:
    path = tmp_path / "t.json"
    path.write_text(f'[{{"im_id": 0, "inst_count": 1, "obj_id": 5, "scene_id": 1}}, {entry}]')
    with pytest.raises(DatasetError, match=reason) as e:
        load_targets(path)
    assert e.value.field == field


def _info(vf: float) -> GtInfo:
    return GtInfo((0, 0, 1, 1), (0, 0, 1, 1), 100, 100, int(vf * 100), vf)


def test_enumerate_targets() -> None:
    gt = {
        7: [GtPose(obj_id, np.eye(3), [0, 0, 1]) for obj_id in (2, 1, 2, 3)],
        2: [GtPose(4, np.eye(3), [0, 0, 1])],
    }
    info = {7: [_info(0.5), _info(0.1), _info(1.0), _info(0.09)], 2: [_info(0.0)]}
    targets = enumerate_targets({1: gt}, {1: info})
    # obj 3 (0.09 < 0.1) and image 2 (nothing visible) are not targets; sorted by obj_id.
    assert targets == [Target(1, 7, 1, 1), Target(1, 7, 2, 2)]
    assert enumerate_targets({1: gt}, {1: info}, min_visib=0.0)[0] == Target(1, 2, 4, 1)


def test_enumerate_targets_needs_matching_gt_info() -> None:
    gt = {0: [GtPose(1, np.eye(3), [0, 0, 1])]}
    with pytest.raises(DatasetError, match="scene_gt_info"):
        enumerate_targets({1: gt}, {1: {0: []}})
