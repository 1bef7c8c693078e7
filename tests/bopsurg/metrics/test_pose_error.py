"""Batched pose errors: hand-worked values, properties, and equality with the per-pose oracle."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from bopsurg.errors import InputError, ShapeError
from bopsurg.geometry import rotation_about_axis
from bopsurg.metrics import (
    add,
    adi,
    hull_vertices,
    mspd,
    mssd,
    proj,
    re,
    symmetry_transforms,
    te,
)
from bopsurg.metrics import reference as ref

from ._data import (
    CONT_Z,
    HYP,
    K_CAM,
    arc_model,
    assert_close,
    box_model,
    pose_pairs,
    random_rotations,
)

RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
RX180 = np.diag([1.0, -1.0, -1.0])
T0 = np.array([0.0, 0.0, 500.0])
seeds = st.integers(0, 2**31 - 1)


# --- hand-worked values ------------------------------------------------------------------


def test_re_hand_values() -> None:
    assert re(RZ90, np.eye(3))[0] == pytest.approx(90.0, abs=1e-12)
    assert re(np.eye(3), np.eye(3))[0] == 0.0
    assert re(RX180, np.eye(3))[0] == pytest.approx(180.0, abs=1e-12)
    assert re(rotation_about_axis([1, 1, 0], np.deg2rad(30.0)), np.eye(3))[0] == pytest.approx(
        30.0, abs=1e-9
    )


def test_te_hand_values() -> None:
    assert te([3.0, 4.0, 0.0], [0.0, 0.0, 0.0]).tolist() == [5.0]
    # (3,) against (3, 1) is the Euclidean norm, not the reference's broadcast pitfall
    assert te(np.array([3.0, 4.0, 0.0]), np.zeros((3, 1))).tolist() == [5.0]
    assert te([[1.0, 2.0, 2.0], [0.0, 0.0, 0.0]], [0.0, 0.0, 0.0]).tolist() == [3.0, 0.0]


def test_mssd_of_a_pure_translation_is_its_norm() -> None:
    pts = box_model(np.random.default_rng(0), 200)
    R = random_rotations(np.random.default_rng(1), 1)[0]
    d = np.array([1.0, -2.0, 2.0])
    assert mssd(R, T0 + d, R, T0, pts)[0] == pytest.approx(3.0, rel=1e-12)
    syms = symmetry_transforms(CONT_Z)
    # with a z symmetry the translation still cannot be undone
    assert mssd(R, T0 + d, R, T0, pts, syms)[0] == pytest.approx(3.0, rel=1e-12)


def test_two_point_model_rotated_by_its_discrete_symmetry() -> None:
    pts = np.array([[-10.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    flip = np.eye(4)
    flip[:3, :3] = rotation_about_axis([0, 0, 1], np.pi)
    syms = symmetry_transforms({"symmetries_discrete": [flip.reshape(-1).tolist()]})
    R_est = rotation_about_axis([0, 0, 1], np.pi)  # the two ends swapped
    assert mssd(R_est, T0, np.eye(3), T0, pts)[0] == pytest.approx(20.0, rel=1e-12)
    assert mssd(R_est, T0, np.eye(3), T0, pts, syms)[0] == pytest.approx(0.0, abs=1e-12)
    assert mspd(R_est, T0, np.eye(3), T0, K_CAM, pts, syms)[0] == pytest.approx(0.0, abs=1e-9)


def test_mspd_and_proj_hand_computed_pixels() -> None:
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])
    t_gt = np.array([0.0, 0.0, 1000.0])
    # 2 mm to the right at 1 m depth: every vertex moves 500 · 2 / 1000 = 1 px
    t_est = t_gt + np.array([2.0, 0.0, 0.0])
    assert mspd(np.eye(3), t_est, np.eye(3), t_gt, K, pts)[0] == pytest.approx(1.0)
    assert proj(np.eye(3), t_est, np.eye(3), t_gt, K, pts)[0] == pytest.approx(1.0)
    # 1000 → 2000 mm: (10, 0) projects to u = 5 px instead of 2.5 px from the centre
    far = np.array([0.0, 0.0, 2000.0])
    assert mspd(np.eye(3), far, np.eye(3), t_gt, K, pts)[0] == pytest.approx(2.5)
    assert proj(np.eye(3), far, np.eye(3), t_gt, K, pts)[0] == pytest.approx(5.0 / 3.0)


def test_add_vs_adi_on_a_symmetric_point_set() -> None:
    # a square about z: rotating by 90° maps the set onto itself
    pts = np.array([[10.0, 0, 0], [0, 10.0, 0], [-10.0, 0, 0], [0, -10.0, 0]])
    assert add(RZ90, T0, np.eye(3), T0, pts)[0] == pytest.approx(10.0 * np.sqrt(2.0))
    assert adi(RZ90, T0, np.eye(3), T0, pts)[0] == pytest.approx(0.0, abs=1e-12)
    # shifted by 20 mm along x: GT (10, 0) meets the estimate's (−10, 0) + 20 exactly; the
    # other GT vertices are 10√2, 20 and 10√2 from their nearest estimate vertex
    shift = T0 + np.array([20.0, 0.0, 0.0])
    assert add(np.eye(3), shift, np.eye(3), T0, pts)[0] == pytest.approx(20.0)
    assert adi(np.eye(3), shift, np.eye(3), T0, pts)[0] == pytest.approx(5.0 * np.sqrt(2) + 5.0)


# --- properties --------------------------------------------------------------------------


@HYP
@given(seed=seeds)
def test_identical_poses_give_zero(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = box_model(rng, 50)
    _, _, R, t = pose_pairs(rng, 4)
    syms = symmetry_transforms(CONT_Z, 0.2)
    assert np.all(re(R, R) < 1e-5)  # acos near 1 amplifies rounding: ≈ 1e-6 deg at most
    assert np.all(te(t, t) == 0.0)
    for v in (
        mssd(R, t, R, t, pts, syms),
        mspd(R, t, R, t, K_CAM, pts, syms),
        add(R, t, R, t, pts),
        adi(R, t, R, t, pts),
        proj(R, t, R, t, K_CAM, pts),
    ):
        np.testing.assert_allclose(v, 0.0, atol=1e-9)


@HYP
@given(seed=seeds, k=st.integers(0, 62), disc=st.booleans())
def test_gt_moved_by_its_own_symmetry_gives_zero(seed: int, k: int, disc: bool) -> None:
    rng = np.random.default_rng(seed)
    pts = arc_model(rng, 80)
    info = {"symmetries_continuous": [{"axis": [0.2, 0.1, 1.0], "offset": [1.0, -2.0, 0.0]}]}
    if disc:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = RX180, [0.0, 0.0, 3.0]
        info["symmetries_discrete"] = [m.reshape(-1).tolist()]
    R_sym, t_sym = symmetry_transforms(info, 0.05)
    _, _, R_gt, t_gt = pose_pairs(rng, 3)
    s = k % R_sym.shape[0]
    R_est = R_gt @ R_sym[s]
    t_est = R_gt @ t_sym[s] + t_gt
    assert np.all(mssd(R_est, t_est, R_gt, t_gt, pts, (R_sym, t_sym)) < 1e-9)
    assert np.all(mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, (R_sym, t_sym)) < 1e-9)


@HYP
@given(seed=seeds)
def test_re_is_symmetric_and_invariant(seed: int) -> None:
    rng = np.random.default_rng(seed)
    A, B = random_rotations(rng, 8), random_rotations(rng, 8)
    Q = random_rotations(rng, 1)[0]
    e = re(A, B)
    np.testing.assert_allclose(re(B, A), e, atol=1e-6)
    np.testing.assert_allclose(re(Q @ A, Q @ B), e, atol=1e-6)
    np.testing.assert_allclose(re(A @ Q, B @ Q), e, atol=1e-6)
    assert np.all((e >= 0.0) & (e <= 180.0))


@HYP
@given(seed=seeds)
def test_adds_is_at_most_add_and_mssd_at_most_unsymmetric(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = box_model(rng, 120)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 6, deg=20.0)
    a = add(R_est, t_est, R_gt, t_gt, pts)
    assert np.all(adi(R_est, t_est, R_gt, t_gt, pts) <= a * (1 + 1e-12) + 1e-12)
    syms = symmetry_transforms(CONT_Z, 0.1)
    plain = mssd(R_est, t_est, R_gt, t_gt, pts)
    assert np.all(mssd(R_est, t_est, R_gt, t_gt, pts, syms) <= plain * (1 + 1e-12))
    assert np.all(plain >= a * (1 - 1e-12))  # max ≥ mean
    plain_px = mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts)
    assert np.all(mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms) <= plain_px * (1 + 1e-12))


# --- equality with the per-pose reference loop --------------------------------------------


def _reference(fn: str, R_est, t_est, R_gt, t_gt, *args):  # type: ignore[no-untyped-def]
    f = getattr(ref, f"{fn}_ref")
    return np.array([f(R_est[i], t_est[i], R_gt[i], t_gt[i], *args) for i in range(len(R_est))])


MODELS = {
    "box_cont_z": (lambda rng: box_model(rng, 400), CONT_Z),
    "needle_cont_disc": (
        lambda rng: arc_model(rng, 400),
        {
            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
            "symmetries_discrete": [np.diag([1.0, -1.0, -1.0, 1.0]).reshape(-1).tolist()],
        },
    ),
    "needle_none": (lambda rng: arc_model(rng, 400), {}),
}


@pytest.mark.parametrize("model", sorted(MODELS))
def test_batched_equals_reference_loop(model: str) -> None:
    rng = np.random.default_rng(7)
    make, info = MODELS[model]
    pts = make(rng)
    syms = symmetry_transforms(info)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 24, deg=8.0)
    # a few far-off estimates too (large errors, other symmetries win)
    R_est[:4] = random_rotations(rng, 4)
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms),
        _reference("mssd", R_est, t_est, R_gt, t_gt, pts, syms),
    )
    assert_close(
        mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
        _reference("mspd", R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
    )
    assert_close(
        add(R_est, t_est, R_gt, t_gt, pts), _reference("add", R_est, t_est, R_gt, t_gt, pts)
    )
    assert_close(
        adi(R_est, t_est, R_gt, t_gt, pts), _reference("adi", R_est, t_est, R_gt, t_gt, pts)
    )
    assert_close(
        proj(R_est, t_est, R_gt, t_gt, K_CAM, pts),
        _reference("proj", R_est, t_est, R_gt, t_gt, K_CAM, pts),
    )
    assert_close(re(R_est, R_gt), [ref.re_ref(a, b) for a, b in zip(R_est, R_gt, strict=True)])
    assert_close(te(t_est, t_gt), [ref.te_ref(a, b) for a, b in zip(t_est, t_gt, strict=True)])


@HYP
@given(seed=seeds, deg=st.sampled_from([0.5, 3.0, 30.0, 180.0]), v=st.sampled_from([4, 9, 60]))
def test_mssd_mspd_equal_reference_random(seed: int, deg: float, v: int) -> None:
    rng = np.random.default_rng(seed)
    pts = arc_model(rng, v) if seed % 2 else box_model(rng, v)
    syms = symmetry_transforms(CONT_Z, 0.2)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 5, deg=deg)
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms),
        _reference("mssd", R_est, t_est, R_gt, t_gt, pts, syms),
    )
    assert_close(
        mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
        _reference("mspd", R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
    )


def test_tiny_rotation_errors_match_reference() -> None:
    rng = np.random.default_rng(3)
    R_gt = random_rotations(rng, 200)
    R_est = Rotation.from_rotvec(rng.normal(size=(200, 3)) * 1e-7).as_matrix() @ R_gt
    assert_close(re(R_est, R_gt), [ref.re_ref(a, b) for a, b in zip(R_est, R_gt, strict=True)])


# --- shapes, broadcasting, chunking --------------------------------------------------------


@pytest.mark.parametrize("t_shape", [(3,), (3, 1), (1, 3)])
def test_single_pose_shapes(t_shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(0)
    pts = box_model(rng, 30)
    R_est, t_est, R_gt, t_gt = (a[0] for a in pose_pairs(rng, 1))
    te_, tg_ = t_est.reshape(t_shape), t_gt.reshape(t_shape)
    expected = ref.mssd_ref(R_est, t_est, R_gt, t_gt, pts)
    for f, args in [
        (mssd, (R_est, te_, R_gt, tg_, pts)),
        (mspd, (R_est, te_, R_gt, tg_, K_CAM, pts)),
        (add, (R_est, te_, R_gt, tg_, pts)),
        (adi, (R_est, te_, R_gt, tg_, pts)),
        (proj, (R_est, te_, R_gt, tg_, K_CAM, pts)),
    ]:
        out = f(*args)
        assert out.shape == (1,)
        assert out.dtype == np.float64
    assert mssd(R_est, te_, R_gt, tg_, pts)[0] == pytest.approx(expected, rel=1e-12)
    assert re(R_est, R_gt).shape == (1,)
    assert te(te_, tg_).shape == (1,)


def test_one_gt_broadcasts_against_many_estimates() -> None:
    rng = np.random.default_rng(1)
    pts = box_model(rng, 100)
    syms = symmetry_transforms(CONT_Z, 0.1)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 9)
    tiled = (R_est, t_est, np.repeat(R_gt[:1], 9, 0), np.repeat(t_gt[:1], 9, 0))
    for f, extra in [(mssd, (pts, syms)), (add, (pts,)), (adi, (pts,))]:
        np.testing.assert_array_equal(f(R_est, t_est, R_gt[0], t_gt[0], *extra), f(*tiled, *extra))
    np.testing.assert_array_equal(
        mspd(R_est, t_est, R_gt[0], t_gt[0], K_CAM, pts, syms),
        mspd(*tiled, np.repeat(K_CAM[None], 9, 0), pts, syms),
    )
    np.testing.assert_array_equal(re(R_est, R_gt[0]), re(R_est, tiled[2]))


@pytest.mark.parametrize("chunk", [1, 4, 1000])
def test_chunk_size_does_not_change_results(chunk: int) -> None:
    rng = np.random.default_rng(2)
    pts = arc_model(rng, 300)
    syms = symmetry_transforms(CONT_Z, 0.05)
    pairs = pose_pairs(rng, 11)
    np.testing.assert_array_equal(
        mssd(*pairs, pts, syms, chunk_size=chunk), mssd(*pairs, pts, syms)
    )
    np.testing.assert_array_equal(
        mspd(*pairs, K_CAM, pts, syms, chunk_size=chunk), mspd(*pairs, K_CAM, pts, syms)
    )
    for f in (add, adi):
        np.testing.assert_array_equal(f(*pairs, pts, chunk_size=chunk), f(*pairs, pts))
    # proj projects a block with one BLAS product whose rounding may depend on the block's
    # rows (OpenBLAS of numpy 2.2, Python 3.10): equal to a few ulp, not bit for bit
    np.testing.assert_allclose(
        proj(*pairs, K_CAM, pts, chunk_size=chunk), proj(*pairs, K_CAM, pts), rtol=1e-13, atol=0
    )


def test_precomputed_hull_candidates() -> None:
    rng = np.random.default_rng(4)
    pts = box_model(rng, 500)
    hull = hull_vertices(pts)
    assert hull.shape[0] < 200
    syms = symmetry_transforms(CONT_Z)
    pairs = pose_pairs(rng, 7)
    np.testing.assert_array_equal(mssd(*pairs, pts, syms, candidates=hull), mssd(*pairs, pts, syms))


def test_empty_batch() -> None:
    pts = box_model(np.random.default_rng(0), 10)
    e33, e3 = np.zeros((0, 3, 3)), np.zeros((0, 3))
    assert mssd(e33, e3, e33, e3, pts).shape == (0,)
    assert mspd(e33, e3, e33, e3, K_CAM, pts, symmetry_transforms(CONT_Z)).shape == (0,)
    assert add(e33, e3, e33, e3, pts).shape == (0,)
    assert adi(e33, e3, e33, e3, pts).shape == (0,)


# --- bad input ------------------------------------------------------------------------------


def _good() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 3)
    return {"R_est": R_est, "t_est": t_est, "R_gt": R_gt, "t_gt": t_gt, "pts": box_model(rng, 20)}


@pytest.mark.parametrize(
    ("field", "bad"),
    [
        ("R_est", np.zeros((3, 3, 4))),
        ("R_gt", np.zeros((3, 2, 3))),
        ("t_est", np.zeros((3, 4))),
        ("t_gt", np.zeros((3, 2, 1))),
        ("pts", np.zeros((5, 2))),
        ("pts", np.zeros((0, 3))),
        ("R_est", np.full((3, 3, 3), np.nan)),
        ("t_gt", np.array([[0.0, np.inf, 1.0]] * 3)),
        ("pts", np.array([[0.0, np.nan, 1.0]])),
    ],
)
def test_bad_shapes_and_nan_name_the_field(field: str, bad: np.ndarray) -> None:
    args = _good()
    args[field] = bad
    a = [args[k] for k in ("R_est", "t_est", "R_gt", "t_gt")]
    for call in (
        lambda: mssd(*a, args["pts"]),
        lambda: mspd(*a, K_CAM, args["pts"]),
        lambda: add(*a, args["pts"]),
        lambda: adi(*a, args["pts"]),
        lambda: proj(*a, K_CAM, args["pts"]),
    ):
        with pytest.raises(ShapeError) as exc:
            call()
        assert exc.value.field == field


def test_bad_batch_sizes_k_syms_and_chunk() -> None:
    g = _good()
    a = [g["R_est"], g["t_est"], g["R_gt"][:2], g["t_gt"][:2]]
    with pytest.raises(ShapeError, match="do not broadcast"):
        mssd(*a, g["pts"])
    a = [g[k] for k in ("R_est", "t_est", "R_gt", "t_gt")]
    with pytest.raises(ShapeError) as exc:
        mspd(*a, np.zeros((2, 3, 3)), g["pts"])
    assert exc.value.field == "K"
    with pytest.raises(ShapeError) as exc:
        mspd(*a, K_CAM * np.nan, g["pts"])
    assert exc.value.field == "K"
    with pytest.raises(ShapeError) as exc:
        mssd(*a, g["pts"], (np.eye(3)[None], np.zeros((2, 3))))
    assert exc.value.field == "syms"
    with pytest.raises(InputError) as exc:
        mssd(*a, g["pts"], chunk_size=0)
    assert exc.value.field == "chunk_size"
    with pytest.raises(InputError) as exc:
        re(g["R_est"], np.zeros((3, 3)))
    assert exc.value.field == "R_gt"
    with pytest.raises(ShapeError) as exc:
        te(np.zeros(4), np.zeros(3))
    assert exc.value.field == "t_est"


@pytest.mark.parametrize("case", ["file_precision", "ties", "not_a_rotation"])
def test_adds_exact_on_hard_cases(case: str) -> None:
    rng = np.random.default_rng(12)
    if case == "ties":
        # a square rotated by 45°: every GT vertex is equidistant from two estimate vertices
        pts = np.array([[10.0, 0, 0], [0, 10.0, 0], [-10.0, 0, 0], [0, -10.0, 0]])
        R_gt = np.repeat(np.eye(3)[None], 4, axis=0)
        R_est = np.repeat(rotation_about_axis([0, 0, 1], np.pi / 4)[None], 4, axis=0)
        t_gt = t_est = np.repeat(T0[None], 4, axis=0)
    else:
        pts = arc_model(rng, 300)
        R_est, t_est, R_gt, t_gt = pose_pairs(rng, 12, deg=4.0)
        if case == "file_precision":  # 8 significant digits, as in BOP JSON/CSV files
            R_est, R_gt = np.round(R_est, 8), np.round(R_gt, 8)
        else:
            R_est = R_est * np.array([1.0, 1.3, 0.8])
    assert_close(
        adi(R_est, t_est, R_gt, t_gt, pts), _reference("adi", R_est, t_est, R_gt, t_gt, pts)
    )
    assert_close(
        add(R_est, t_est, R_gt, t_gt, pts), _reference("add", R_est, t_est, R_gt, t_gt, pts)
    )
