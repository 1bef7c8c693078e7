"""Symmetry sets: the reference's set and order, bit for bit, and input checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bopsurg.errors import InputError, ShapeError
from bopsurg.geometry import rotation_about_axis
from bopsurg.metrics import as_symmetries, symmetry_transforms
from bopsurg.metrics.reference import symmetry_transforms_ref

from ._data import CONT_Z, HYP, random_rotations


def _rot_x_180_with_t(t: tuple[float, float, float]) -> list[float]:
    m = np.eye(4)
    m[:3, :3] = np.diag([1.0, -1.0, -1.0])
    m[:3, 3] = t
    return m.reshape(-1).tolist()


def test_no_symmetry_gives_identity_only() -> None:
    R, t = symmetry_transforms({"diameter": 10.0})
    assert R.shape == (1, 3, 3)
    assert t.shape == (1, 3)
    assert np.array_equal(R[0], np.eye(3))
    assert np.array_equal(t[0], np.zeros(3))


def test_continuous_z_gives_315_rotations_starting_with_identity() -> None:
    R, t = symmetry_transforms(CONT_Z)
    assert R.shape == (315, 3, 3)
    assert np.array_equal(R[0], np.eye(3))
    assert np.array_equal(t, np.zeros((315, 3)))
    step = 2.0 * np.pi / 315
    for i in (1, 100, 314):
        assert np.array_equal(R[i], rotation_about_axis([0, 0, 1], i * step))
    # consecutive samples are 2π/315 apart
    c = 0.5 * (np.trace(R[1]) - 1.0)
    assert math.acos(c) == pytest.approx(step, rel=1e-12)


def test_discrete_outer_continuous_inner_order_hand_checked() -> None:
    # step 0.8 → n = ceil(π / 0.8) = 4 samples: 0°, 90°, 180°, 270° about z.
    info = {
        "symmetries_discrete": [_rot_x_180_with_t((0.0, 0.0, 10.0))],
        "symmetries_continuous": [{"axis": [0, 0, 2], "offset": [0, 0, 0]}],
    }
    R, t = symmetry_transforms(info, max_sym_disc_step=0.8)
    assert R.shape == (8, 3, 3)
    rz = [np.round(rotation_about_axis([0, 0, 1], k * np.pi / 2), 12) for k in range(4)]
    flip = np.diag([1.0, -1.0, -1.0])
    for k in range(4):
        # d = identity (outer), c = k-th continuous sample (inner)
        np.testing.assert_allclose(R[k], rz[k], atol=1e-12)
        np.testing.assert_allclose(t[k], 0.0, atol=1e-12)
        # d = the discrete flip: R = R_c R_d, t = R_c t_d + t_c
        np.testing.assert_allclose(R[4 + k], rz[k] @ flip, atol=1e-12)
        np.testing.assert_allclose(t[4 + k], rz[k] @ [0.0, 0.0, 10.0], atol=1e-12)


def test_continuous_offset_keeps_the_axis_fixed() -> None:
    o = np.array([5.0, -3.0, 2.0])
    R, t = symmetry_transforms(
        {"symmetries_continuous": [{"axis": [0, 1, 0], "offset": o.tolist()}]}, 0.1
    )
    assert R.shape[0] == math.ceil(np.pi / 0.1)
    for p in (o, o + np.array([0.0, 7.0, 0.0])):  # points on the axis through o
        np.testing.assert_allclose(np.einsum("sij,j->si", R, p) + t, np.broadcast_to(p, t.shape))


def test_count_formula() -> None:
    disc = [_rot_x_180_with_t((0, 0, 0)), _rot_x_180_with_t((1, 2, 3))]
    cont = [{"axis": [0, 0, 1], "offset": [0, 0, 0]}, {"axis": [1, 0, 0], "offset": [0, 0, 0]}]
    R, _ = symmetry_transforms({"symmetries_discrete": disc, "symmetries_continuous": cont}, 0.05)
    assert R.shape[0] == (1 + 2) * math.ceil(np.pi / 0.05) * 2
    R, _ = symmetry_transforms({"symmetries_discrete": disc})
    assert R.shape[0] == 3


unit = st.floats(-1.0, 1.0, allow_nan=False)


@HYP
@given(
    axis=st.tuples(unit, unit, unit).filter(lambda a: sum(x * x for x in a) > 1e-3),
    offset=st.tuples(*[st.floats(-50, 50)] * 3),
    n_disc=st.integers(0, 2),
    step=st.sampled_from([0.01, 0.05, 0.3, 1.0]),
    seed=st.integers(0, 2**31 - 1),
)
def test_bit_identical_to_the_reference_loop(
    axis: tuple[float, float, float],
    offset: tuple[float, float, float],
    n_disc: int,
    step: float,
    seed: int,
) -> None:
    rng = np.random.default_rng(seed)
    disc = []
    for R in random_rotations(rng, n_disc):
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = R, rng.uniform(-20, 20, 3)
        disc.append(m.reshape(-1).tolist())
    info = {
        "symmetries_discrete": disc,
        "symmetries_continuous": [{"axis": list(axis), "offset": list(offset)}],
    }
    R, t = symmetry_transforms(info, step)
    ref = symmetry_transforms_ref(info, step)
    assert R.shape[0] == len(ref)
    assert np.array_equal(R, np.stack([s["R"] for s in ref]))
    assert np.array_equal(t, np.stack([s["t"].reshape(3) for s in ref]))


def test_discrete_only_matches_reference() -> None:
    info = {"symmetries_discrete": [_rot_x_180_with_t((0, 0, 4))]}
    R, t = symmetry_transforms(info)
    ref = symmetry_transforms_ref(info, 0.01)
    assert np.array_equal(R, np.stack([s["R"] for s in ref]))
    assert np.array_equal(t, np.stack([s["t"].reshape(3) for s in ref]))


@pytest.mark.parametrize(
    ("info", "step", "error", "field"),
    [
        ({"symmetries_discrete": [[0.0] * 16, [0.0] * 16, [0.0] * 15]}, 0.01, ShapeError,
         "symmetries_discrete[2]"),
        ({"symmetries_discrete": [[float("nan")] + [0.0] * 15]}, 0.01, ShapeError,
         "symmetries_discrete[0]"),
        ({"symmetries_discrete": ["abc"]}, 0.01, InputError, "symmetries_discrete[0]"),
        ({"symmetries_discrete": 3}, 0.01, InputError, "symmetries_discrete"),
        ({"symmetries_continuous": [{"axis": [0, 0, 0], "offset": [0, 0, 0]}]}, 0.01, InputError,
         "symmetries_continuous[0].axis"),
        ({"symmetries_continuous": [{"axis": [0, 0, 1]}]}, 0.01, InputError,
         "symmetries_continuous[0]"),
        ({"symmetries_continuous": [{"axis": [0, 1], "offset": [0, 0, 0]}]}, 0.01, ShapeError,
         "symmetries_continuous[0].axis"),
        ({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, float("inf"), 0]}]}, 0.01,
         ShapeError, "symmetries_continuous[0].offset"),
        ({"symmetries_continuous": [[0, 0, 1]]}, 0.01, InputError, "symmetries_continuous[0]"),
        (CONT_Z, 0.0, InputError, "max_sym_disc_step"),
        (CONT_Z, float("nan"), InputError, "max_sym_disc_step"),
    ],
)  # fmt: skip
def test_bad_model_info_names_the_field(
    info: dict[str, object], step: float, error: type[Exception], field: str
) -> None:
    with pytest.raises(error) as exc:
        symmetry_transforms(info, step)
    assert exc.value.field == field  # type: ignore[attr-defined]
    assert field in str(exc.value)


def test_model_info_must_be_a_mapping() -> None:
    with pytest.raises(InputError, match="model_info"):
        symmetry_transforms([1, 2, 3])  # type: ignore[arg-type]


def test_as_symmetries_accepts_tuples_dicts_and_none() -> None:
    R, t = symmetry_transforms(CONT_Z, 0.5)
    R2, t2 = as_symmetries([{"R": a, "t": b.reshape(3, 1)} for a, b in zip(R, t, strict=True)])
    assert np.array_equal(R, R2)
    assert np.array_equal(t, t2)
    R3, t3 = as_symmetries(None)
    assert np.array_equal(R3, np.eye(3)[None])
    assert np.array_equal(t3, np.zeros((1, 3)))
    with pytest.raises(ShapeError, match="syms"):
        as_symmetries((R, t[:-1]))
    with pytest.raises(ShapeError, match="syms"):
        as_symmetries((R[:, :2], t))
    with pytest.raises(ShapeError, match="NaN"):
        as_symmetries((R * np.nan, t))
