"""Ambiguity analysis: view angle, tip/tail visibility, split tables."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.images import save_mask
from bopsurg.bop.results import load_results
from bopsurg.evaluation.ambiguity import (
    _ends_on_mask,
    ambiguity_splits,
    model_keypoints,
    model_plane_normal,
    view_angle_deg,
)
from bopsurg.evaluation.runner import evaluate
from bopsurg.example import ExampleSpec, write_example_dataset
from bopsurg.needle import needle_mesh


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def test_view_angle_face_on_and_edge_on():
    n = np.array([0.0, 0.0, 1.0])
    t = np.array([[0.0, 0.0, 100.0], [0.0, 0.0, 100.0], [0.0, 0.0, 100.0]])
    R = np.stack([np.eye(3), rot_x(np.pi / 2), rot_x(np.pi / 6)])
    np.testing.assert_allclose(view_angle_deg(R, t, n), [90.0, 0.0, 60.0], atol=1e-9)


def test_needle_plane_and_keypoints_without_models_info_extras():
    m = needle_mesh()
    n = model_plane_normal({}, m.pts)
    np.testing.assert_allclose(np.abs(n), [0.0, 0.0, 1.0], atol=1e-9)
    tip, tail = model_keypoints({}, m.pts)
    # the diameter's ends are the needle's two ends: the tail cap and the tip region
    assert np.linalg.norm(tail[:2] - m.pts[0, :2]) < 1.0
    assert np.linalg.norm(tip[:2] - m.pts[-1, :2]) < 1.5
    given = model_keypoints({"keypoints": {"tip": [1, 2, 3], "tail": [4, 5, 6]}}, m.pts)
    np.testing.assert_array_equal(given[0], [1, 2, 3])


def _on_full_mask(mask: np.ndarray, uv: np.ndarray) -> bool:
    """The definition on the whole mask: any pixel of the 3x3 neighbourhood of rint(uv)."""
    if not np.all(np.isfinite(uv)):
        return False
    u, v = int(np.rint(uv[0])), int(np.rint(uv[1]))
    h, w = mask.shape
    r0, r1, c0, c1 = max(v - 1, 0), min(v + 2, h), max(u - 1, 0), min(u + 2, w)
    return r0 < r1 and c0 < c1 and bool(mask[r0:r1, c0:c1].any())


def test_keypoint_on_mask_tolerates_one_pixel(tmp_path):
    mask = np.zeros((10, 10), bool)
    mask[5, 5] = True
    path = tmp_path / "m.png"
    save_mask(path, mask)
    assert _ends_on_mask(path, np.array([[6.4, 4.0], [8.0, 8.0]])) == (True, False)
    assert _ends_on_mask(path, np.array([[np.nan, 1.0], [-5.0, 5.0]])) == (False, False)
    assert _ends_on_mask(path, np.array([[1e30, 5.0], [5.0, 6.0]])) == (False, True)


def test_ends_on_mask_equal_the_full_mask_definition(tmp_path):
    rng = np.random.default_rng(7)
    mask = rng.random((37, 53)) < 0.05
    path = tmp_path / "m.png"
    save_mask(path, mask)
    for _ in range(300):
        uv = rng.uniform([-4.0, -4.0], [57.0, 41.0], size=(2, 2))
        want = (_on_full_mask(mask, uv[0]), _on_full_mask(mask, uv[1]))
        assert _ends_on_mask(path, uv) == want, uv


def test_splits_count_each_group():
    rows = pd.DataFrame(
        {
            "re": [1.0, 2.0, 30.0, np.nan],
            "te": [1.0, 1.0, 5.0, np.nan],
            "mssd": [1.0, 1.5, 9.0, np.nan],
            "tip_visible": [1.0, 1.0, 0.0, 1.0],
            "tail_visible": [1.0, 0.0, 0.0, 1.0],
            "view_angle_deg": [80.0, 30.0, 5.0, 50.0],
            "visib_fract": [0.9, 0.6, 0.4, 0.9],
        }
    )
    s = ambiguity_splits(rows)
    assert {k: v["n"] for k, v in s["ends_visible"].items()} == {"both": 1, "one": 1, "none": 1}
    assert s["view_angle"]["edge-on <15°"]["mssd_median"] == 9.0
    assert s["visibility"]["visib >=0.8"]["n"] == 1  # the row without estimate is left out


def test_eval_reports_ambiguity_columns_and_splits(tmp_path):
    ex = write_example_dataset(tmp_path, ExampleSpec(seed=2, scenes=1, images_per_scene=10))
    res = evaluate(BopDataset(ex.root, ex.split), load_results(ex.results))
    cols = res.errors[["tip_visible", "tail_visible", "view_angle_deg"]]
    matched = res.errors["gt_id"] >= 0
    assert cols[matched].notna().all().all()
    assert set(np.unique(cols["tip_visible"].dropna())) <= {0.0, 1.0}
    assert (cols["view_angle_deg"].dropna().between(0, 90)).all()
    assert (
        sum(g["n"] for g in res.summary["splits"]["view_angle"].values())
        == res.summary["with_estimate"]
    )


@pytest.mark.parametrize("angle", [0.0, np.pi / 3])
def test_view_angle_is_symmetric_in_the_normal_sign(angle):
    R = rot_x(angle)[None]
    t = np.array([[10.0, -5.0, 80.0]])
    a = view_angle_deg(R, t, np.array([0.0, 0.0, 1.0]))
    b = view_angle_deg(R, t, np.array([0.0, 0.0, -1.0]))
    np.testing.assert_allclose(a, b)
