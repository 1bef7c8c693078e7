"""VSD and the visible-surface masks: hand-built depth images and the reference loop."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bopsurg.errors import InputError, ShapeError
from bopsurg.geometry import depth_to_distance
from bopsurg.metrics import (
    estimate_visib_mask,
    estimate_visib_mask_est,
    estimate_visib_mask_gt,
    vsd,
)
from bopsurg.metrics.reference import vsd_ref
from bopsurg.metrics.vsd import vsd_in_window

from ._data import HYP

K3 = np.array([[100.0, 0.0, 1.0], [0.0, 100.0, 1.0], [0.0, 0.0, 1.0]])
BOP19_TAUS = np.arange(0.05, 0.51, 0.05)


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3×3 images: GT on columns 0-1, estimate on columns 1-2 (3 mm behind), an occluder."""
    test = np.full((3, 3), 100.0)
    test[0, 0] = 0.0  # missing measurement: visible in bop19
    test[2, 2] = 50.0  # occluder hides the estimate's pixel (2, 2)
    gt = np.zeros((3, 3))
    gt[:, :2] = 100.0
    est = np.zeros((3, 3))
    est[:, 1:] = 103.0
    return test, est, gt


def test_hand_built_masks() -> None:
    test, est, gt = _scene()
    d_test, d_est, d_gt = (depth_to_distance(x, K3) for x in (test, est, gt))
    visib_gt = estimate_visib_mask_gt(d_test, d_gt, 15.0)
    assert visib_gt.tolist() == [[True, True, False]] * 3
    visib_est = estimate_visib_mask_est(d_test, d_est, visib_gt, 15.0)
    assert visib_est.tolist() == [[False, True, True], [False, True, True], [False, True, False]]
    bop18 = estimate_visib_mask(d_test, d_gt, 15.0, mode="bop18")
    assert bop18.tolist() == [[False, True, False], [True, True, False], [True, True, False]]


def test_hand_built_vsd() -> None:
    test, est, gt = _scene()
    # ∩ = column 1 (3 px), ∪ = 8 px, so |∪| − |∩| = 5; distances on ∩ ≈ 3 mm (3.00015 off-axis)
    e = vsd(test, est, gt, K3, 15.0, [0.02, 0.05], diameter=100.0)
    np.testing.assert_allclose(e, [8 / 8, 5 / 8], rtol=0, atol=0)
    e = vsd(test, est, gt, K3, 15.0, [2.0, 3.0001, 10.0])  # τ in mm without a diameter
    np.testing.assert_allclose(e, [8 / 8, 7 / 8, 5 / 8], rtol=0, atol=0)
    e = vsd(test, est, gt, K3, 15.0, [6.0], cost="tlinear")
    assert e[0] == pytest.approx((1.5 + 5) / 8, rel=1e-4)
    for taus, diameter, cost in [([0.02, 0.05], 100.0, "step"), ([6.0], None, "tlinear")]:
        exp = vsd_ref(test, est, gt, K3, 15.0, taus, diameter is not None, diameter or 1.0, cost)
        np.testing.assert_array_equal(vsd(test, est, gt, K3, 15.0, taus, diameter, cost), exp)


def test_empty_union_gives_one_for_every_tau() -> None:
    test = np.full((4, 5), 300.0)
    empty = np.zeros((4, 5))
    assert vsd(test, empty, empty, K3, 15.0, BOP19_TAUS, 50.0).tolist() == [1.0] * 10
    # the estimate fully hidden behind the scene, GT absent: still empty
    far = np.full((4, 5), 900.0)
    assert vsd(test, far, empty, K3, 15.0, [0.1], 50.0).tolist() == [1.0]


def test_perfect_estimate_gives_zero() -> None:
    d = np.full((6, 6), 250.0)
    d[0] = 0.0
    assert vsd(d, d, d, K3, 15.0, BOP19_TAUS, 20.0).tolist() == [0.0] * 10


@HYP
@given(
    seed=st.integers(0, 2**31 - 1),
    cost=st.sampled_from(["step", "tlinear"]),
    normalized=st.booleans(),
)
def test_equals_reference_on_random_images(seed: int, cost: str, normalized: bool) -> None:
    rng = np.random.default_rng(seed)
    h, w = 24, 32
    K = np.array([[300.0, 0.0, 15.5], [0.0, 310.0, 12.0], [0.0, 0.0, 1.0]])
    test = rng.uniform(200, 400, (h, w)) * (rng.random((h, w)) > 0.1)
    gt = rng.uniform(250, 350, (h, w)) * (rng.random((h, w)) > 0.4)
    est = np.where(rng.random((h, w)) > 0.4, gt + rng.normal(0, 8, (h, w)), 0.0)
    taus = BOP19_TAUS if normalized else BOP19_TAUS * 60
    diameter = 60.0
    got = vsd(test, est, gt, K, 15.0, taus, diameter if normalized else None, cost)  # type: ignore[arg-type]
    exp = vsd_ref(test, est, gt, K, 15.0, taus, normalized, diameter, cost)
    np.testing.assert_allclose(got, exp, rtol=1e-12, atol=0)
    assert got.shape == (10,)
    assert np.all((got >= 0) & (got <= 1))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_small_object_window_equals_reference(seed: int) -> None:
    """Renderings cover a small off-centre patch (as an object in a large image): VSD works on
    their bounding window only, with the values of the full-image reference."""
    rng = np.random.default_rng(seed)
    h, w = 60, 80
    K = np.array([[300.0, 0.0, 39.5], [0.0, 310.0, 29.0], [0.0, 0.0, 1.0]])
    test = rng.uniform(200, 400, (h, w)) * (rng.random((h, w)) > 0.1)
    gt, est = np.zeros((h, w)), np.zeros((h, w))
    gt[41:50, 7:19] = rng.uniform(250, 350, (9, 12)) * (rng.random((9, 12)) > 0.3)
    est[44:53, 12:25] = rng.uniform(250, 350, (9, 13)) * (rng.random((9, 13)) > 0.3)
    got = vsd(test, est, gt, K, 15.0, BOP19_TAUS, 60.0)
    exp = vsd_ref(test, est, gt, K, 15.0, BOP19_TAUS, True, 60.0)
    np.testing.assert_allclose(got, exp, rtol=1e-12, atol=0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_window_of_the_images_gives_the_whole_images_errors(seed: int) -> None:
    """vsd_in_window on any window holding both renderings: vsd's errors, bit for bit."""
    rng = np.random.default_rng(seed)
    h, w = 60, 80
    K = np.array([[300.0, 0.0, 39.5], [0.0, 310.0, 29.0], [0.0, 0.0, 1.0]])
    test = (rng.uniform(200, 400, (h, w)) * (rng.random((h, w)) > 0.1)).astype(np.float32)
    gt, est = np.zeros((h, w)), np.zeros((h, w))
    gt[41:50, 7:19] = rng.uniform(250, 350, (9, 12)) * (rng.random((9, 12)) > 0.3)
    est[44:53, 12:25] = rng.uniform(250, 350, (9, 13)) * (rng.random((9, 13)) > 0.3)
    want = vsd(test, est, gt, K, 15.0, BOP19_TAUS, 60.0)
    for r0, r1, c0, c1 in [(41, 53, 7, 25), (30, 60, 0, 40), (0, h, 0, w)]:
        win = (slice(r0, r1), slice(c0, c1))
        got = vsd_in_window(test[win], est[win], gt[win], K, (r0, c0), 15.0, BOP19_TAUS, 60.0)
        np.testing.assert_array_equal(got, want)
    empty = np.zeros((3, 4))
    np.testing.assert_array_equal(
        vsd_in_window(test[:3, :4], empty, empty, K, (0, 0), 15.0, BOP19_TAUS), np.ones(10)
    )


def test_float32_difference_like_the_reference() -> None:
    # d_model − d_test = 15.000001 in float64 but 15.0 in float32: visible, as the reference
    d_test = np.array([[1000.0]])
    d_model = np.array([[1015.000001]])
    assert estimate_visib_mask(d_test, d_model, 15.0)[0, 0]
    assert not estimate_visib_mask(d_test, np.array([[1015.01]]), 15.0)[0, 0]


def test_uint16_depth_images_are_accepted() -> None:
    test = np.full((5, 5), 300, dtype=np.uint16)
    gt = np.zeros((5, 5), dtype=np.uint16)
    gt[1:4, 1:4] = 290
    est = np.roll(gt, 1, axis=1)
    got = vsd(test, est, gt, K3, 15.0, BOP19_TAUS, 30.0)
    exp = vsd_ref(test, est, gt, K3, 15.0, BOP19_TAUS, True, 30.0)
    np.testing.assert_array_equal(got, exp)


@pytest.mark.parametrize(
    ("kwargs", "error", "field"),
    [
        ({"depth_est": np.zeros((3, 4))}, ShapeError, "depth_est"),
        ({"depth_gt": np.zeros((3,))}, ShapeError, "depth_gt"),
        ({"depth_test": np.full((3, 3), np.nan)}, ShapeError, "depth_test"),
        ({"K": np.eye(2)}, ShapeError, "K"),
        ({"delta": float("nan")}, InputError, "delta"),
        ({"taus": [0.1, float("inf")]}, InputError, "taus"),
        ({"diameter": 0.0}, InputError, "diameter"),
        ({"cost": "linear"}, InputError, "cost"),
        ({"cost": "tlinear", "taus": [0.0]}, InputError, "taus"),
    ],
)
def test_bad_vsd_input_names_the_field(
    kwargs: dict[str, object], error: type[Exception], field: str
) -> None:
    test, est, gt = _scene()
    args: dict[str, object] = {
        "depth_test": test,
        "depth_est": est,
        "depth_gt": gt,
        "K": K3,
        "delta": 15.0,
        "taus": [0.1],
        "diameter": 10.0,
    }
    args.update(kwargs)
    with pytest.raises(error) as exc:
        vsd(**args)  # type: ignore[arg-type]
    assert exc.value.field == field  # type: ignore[attr-defined]


def test_bad_mask_input() -> None:
    with pytest.raises(ShapeError, match="dist_model"):
        estimate_visib_mask(np.zeros((2, 2)), np.zeros((2, 3)), 15.0)
    with pytest.raises(InputError, match="mode"):
        estimate_visib_mask(np.zeros((2, 2)), np.zeros((2, 2)), 15.0, mode="bop20")  # type: ignore[arg-type]
    with pytest.raises(ShapeError, match="visib_gt"):
        estimate_visib_mask_est(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((3, 3)), 15.0)
