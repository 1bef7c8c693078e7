"""The MSSD/MSPD kernel's shortcuts on hard cases: degenerate hulls, ties, z = 0, non-rotations."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bopsurg.geometry import rotation_about_axis
from bopsurg.metrics import adi, max_distance, mspd, mssd, symmetry_transforms
from bopsurg.metrics import reference as ref
from bopsurg.metrics.point_subsets import (
    extreme_point_order,
    farthest_point_order,
    hull_probe,
    hull_vertex_indices,
    hull_vertices,
    sphere_directions,
)

from ._data import CONT_Z, HYP, K_CAM, arc_model, assert_close, box_model, pose_pairs

seeds = st.integers(0, 2**31 - 1)


def _ref(fn, R_est, t_est, R_gt, t_gt, *args):  # type: ignore[no-untyped-def]
    f = getattr(ref, f"{fn}_ref")
    return np.array([f(R_est[i], t_est[i], R_gt[i], t_gt[i], *args) for i in range(len(R_est))])


# --- point subsets ----------------------------------------------------------------------------


def test_hull_of_a_cube_is_its_corners() -> None:
    rng = np.random.default_rng(0)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    pts = np.concatenate([rng.uniform(-0.9, 0.9, (300, 3)), corners])
    idx = hull_vertex_indices(pts)
    assert sorted(map(tuple, pts[idx])) == sorted(map(tuple, corners))
    assert np.array_equal(hull_vertices(pts), pts[idx])


@pytest.mark.parametrize(
    "pts",
    [
        np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]),  # fewer than 4 points
        np.c_[np.random.default_rng(1).uniform(-5, 5, (50, 2)), np.zeros(50)],  # planar
        np.outer(np.linspace(-3, 3, 20), [1.0, 2.0, -1.0]),  # collinear
        np.ones((10, 3)),  # all the same point
    ],
    ids=["three", "planar", "collinear", "duplicates"],
)
def test_degenerate_hulls_fall_back_to_all_points(pts: np.ndarray) -> None:
    assert np.array_equal(hull_vertex_indices(pts), np.arange(len(pts)))
    rng = np.random.default_rng(2)
    syms = symmetry_transforms(CONT_Z, 0.3)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 6, deg=20.0)
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms), _ref("mssd", R_est, t_est, R_gt, t_gt, pts, syms)
    )
    assert_close(
        mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
        _ref("mspd", R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
    )


def test_farthest_point_order() -> None:
    rng = np.random.default_rng(3)
    pts = np.concatenate([box_model(rng, 100), np.repeat([[50.0, 0.0, 0.0]], 3, axis=0)])
    order = farthest_point_order(pts, 40)
    assert len(set(order.tolist())) == 40  # no repeats, even among duplicate points
    assert order[0] >= 100  # farthest from the centroid first
    assert farthest_point_order(pts, 10_000).size == len(pts)
    assert farthest_point_order(np.ones((5, 3)), 5).tolist() == [0, 1, 2, 3, 4]


def test_extreme_points_are_spread_hull_vertices() -> None:
    rng = np.random.default_rng(8)
    pts = arc_model(rng, 2000)
    d = sphere_directions(64)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    order = extreme_point_order(pts, 32)
    assert 4 <= order.size <= 32
    assert len(set(order.tolist())) == order.size
    assert set(order.tolist()) <= set(hull_vertex_indices(pts).tolist())


@pytest.mark.parametrize("hull_min", [0, 10**9])
def test_with_and_without_the_hull_shortcut(monkeypatch: pytest.MonkeyPatch, hull_min: int) -> None:
    monkeypatch.setattr(max_distance, "HULL_MIN_EVALS", hull_min)
    rng = np.random.default_rng(9)
    pts = arc_model(rng, 500)
    syms = symmetry_transforms(CONT_Z, 0.05)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 20, deg=6.0)
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms), _ref("mssd", R_est, t_est, R_gt, t_gt, pts, syms)
    )
    assert_close(mssd(R_est, t_est, R_gt, t_gt, pts), _ref("mssd", R_est, t_est, R_gt, t_gt, pts))


# --- ties and exact symmetries ----------------------------------------------------------------


def test_exactly_symmetric_model_with_many_tied_symmetries() -> None:
    # a regular 12-gon prism has 12 exact symmetries among the 36 sampled ones: ties everywhere
    ang = np.arange(12) * 2 * np.pi / 12
    ring = np.c_[10 * np.cos(ang), 10 * np.sin(ang)]
    pts = np.concatenate([np.c_[ring, np.full(12, -5.0)], np.c_[ring, np.full(12, 5.0)]])
    syms = symmetry_transforms(CONT_Z, np.pi / 18)
    rng = np.random.default_rng(4)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 10, deg=2.0)
    R_est[:3] = R_gt[:3]
    t_est[:3] = t_gt[:3]
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms), _ref("mssd", R_est, t_est, R_gt, t_gt, pts, syms)
    )
    assert_close(
        mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
        _ref("mspd", R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
    )


@HYP
@given(seed=seeds, scale=st.sampled_from([0.7, 1.3]))
def test_non_rotation_matrices_still_match_reference(seed: int, scale: float) -> None:
    # The definitions make sense for any matrix; the shortcuts must not assume orthonormality.
    rng = np.random.default_rng(seed)
    pts = arc_model(rng, 60)
    syms = symmetry_transforms(CONT_Z, 0.2)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 4)
    R_est = R_est * scale + rng.normal(0, 0.05, R_est.shape)
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms), _ref("mssd", R_est, t_est, R_gt, t_gt, pts, syms)
    )
    assert_close(
        mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
        _ref("mspd", R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
    )
    # ADD-S answers such estimates with the reference's own per-pose tree
    assert_close(adi(R_est, t_est, R_gt, t_gt, pts), _ref("adi", R_est, t_est, R_gt, t_gt, pts))


def test_far_and_large_coordinates() -> None:
    rng = np.random.default_rng(5)
    pts = box_model(rng, 200) * 10
    syms = symmetry_transforms(CONT_Z)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 8, deg=0.01, mm=1e-4)
    t_est[:, 2] += 1e5
    t_gt[:, 2] += 1e5
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms), _ref("mssd", R_est, t_est, R_gt, t_gt, pts, syms)
    )
    assert_close(
        mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
        _ref("mspd", R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
    )


# --- points on or behind the camera plane (MSPD) ---------------------------------------------


def test_vertex_on_the_camera_plane_gives_the_reference_nan_or_inf() -> None:
    """z = 0 makes the projection inf/nan; the result follows the reference's min rule.

    The reference takes ``np.max`` per symmetry (NaN propagates) and Python's ``min`` over the
    list: NaN exactly when the first (identity) term is NaN, else the minimum of the others.
    """
    pts = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 30.0, 5.0], [-20.0, 5.0, -5.0]])
    syms = symmetry_transforms(CONT_Z, 0.5)
    R = np.eye(3)
    cases = {
        # the origin vertex lands on z = 0 in both poses: 0/0 → NaN in the identity term
        "nan": (R, np.array([1.0, 2.0, 0.0]), R, np.array([0.0, 0.0, 0.0])),
        # only the estimate's vertex at z = 0 (x ≠ 0): ±inf − finite → inf in every term
        "inf": (R, np.array([1.0, 2.0, 0.0]), R, np.array([0.0, 0.0, 100.0])),
        # GT-sym vertices reach z ≤ 0 only under some symmetries: tilted axis, object near z=0
        "straddle": (
            rotation_about_axis([1, 0, 0], 1.2),
            np.array([3.0, 1.0, 20.0]),
            rotation_about_axis([1, 0, 0], 1.3),
            np.array([0.0, 0.0, 20.0]),
        ),
    }
    for name, (R_est, t_est, R_gt, t_gt) in cases.items():
        got = mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms)[0]
        exp = ref.mspd_ref(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms)
        if name == "nan":
            assert np.isnan(got)
            assert np.isnan(exp)
        elif name == "inf":
            assert np.isinf(got)
            assert np.isinf(exp)
        else:
            assert got == pytest.approx(exp, rel=1e-9), name
        # without symmetries as well
        exp1 = ref.mspd_ref(R_est, t_est, R_gt, t_gt, K_CAM, pts)
        assert_close(mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts), np.array([exp1]))


def test_objects_behind_the_camera_match_reference() -> None:
    rng = np.random.default_rng(6)
    pts = box_model(rng, 100)
    syms = symmetry_transforms(CONT_Z, 0.1)
    R_est, t_est, R_gt, t_gt = pose_pairs(rng, 6)
    t_est[:, 2] *= -1  # entirely behind the camera: finite, mirrored projections
    t_gt[:, 2] *= -1
    t_gt[:2, 2] = 10.0  # straddling z = 0
    assert_close(
        mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
        _ref("mspd", R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
    )


def test_nan_only_under_a_later_symmetry_is_skipped_like_python_min() -> None:
    # 180° about y maps (5, 0, 10) to (−5, 0, −10); with t_gt = (0, 0, 10) it lands on z = 0
    # with y = 0: v = 0/0 = NaN in that symmetry's term only.
    flip = np.diag([-1.0, 1.0, -1.0])
    R_sym = np.stack([np.eye(3), flip])
    t_sym = np.zeros((2, 3))
    pts = np.array([[5.0, 0.0, 10.0], [-3.0, 2.0, 1.0], [1.0, -4.0, -2.0], [0.0, 1.0, 3.0]])
    t_gt = np.array([0.0, 0.0, 10.0])
    t_est = t_gt + np.array([0.5, -0.2, 0.3])
    args = (np.eye(3), t_est, np.eye(3), t_gt, K_CAM, pts)
    first = ref.mspd_ref(*args, (R_sym, t_sym))
    assert np.isfinite(first)  # identity first: the NaN term is never picked
    assert mspd(*args, (R_sym, t_sym))[0] == pytest.approx(first, rel=1e-12)
    swapped = (R_sym[::-1].copy(), t_sym)
    assert np.isnan(ref.mspd_ref(*args, swapped))  # NaN first: Python's min returns it
    assert np.isnan(mspd(*args, swapped)[0])


@pytest.mark.parametrize("model", ["box", "needle"])
def test_stress_many_poses_against_reference(model: str) -> None:
    """Branch and bound vs the reference on 240 poses with errors from 0.01° to 180°."""
    rng = np.random.default_rng(11)
    pts = box_model(rng, 300) if model == "box" else arc_model(rng, 300)
    syms = symmetry_transforms(CONT_Z)
    parts = [pose_pairs(rng, 60, deg=d, mm=d) for d in (0.01, 2.0, 10.0, 180.0)]
    R_est, t_est, R_gt, t_gt = (np.concatenate(x) for x in zip(*parts, strict=True))
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms), _ref("mssd", R_est, t_est, R_gt, t_gt, pts, syms)
    )
    assert_close(
        mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
        _ref("mspd", R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
    )


def test_overflowing_coordinates_give_inf_like_the_reference() -> None:
    pts = np.array([[1e200, 0.0, 0.0], [0.0, 1e200, 0.0], [0.0, 0.0, 1e200], [1.0, 2.0, 3.0]])
    syms = symmetry_transforms(CONT_Z, 0.5)
    R_est, t_est, R_gt, t_gt = pose_pairs(np.random.default_rng(10), 3)
    got = mssd(R_est, t_est, R_gt, t_gt, pts, syms)
    with np.errstate(over="ignore", invalid="ignore"):
        exp = _ref("mssd", R_est, t_est, R_gt, t_gt, pts, syms)
    assert_close(got, exp)
    assert np.all(np.isinf(got))


# --- the symmetry family, the hull probe and the sampled bound stage -------------------------

TILTED = {"symmetries_continuous": [{"axis": [1.0, -2.0, 0.5], "offset": [3.0, -4.0, 7.0]}]}
DISC_AND_CONT = {
    "symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 5.0, 0, 0, 0, 1]],
    **CONT_Z,
}


def test_symmetry_family_of_a_continuous_symmetry_reconstructs_every_transform() -> None:
    R_sym, t_sym = symmetry_transforms(TILTED, 0.05)
    fam = max_distance.symmetry_family(R_sym, t_sym)
    assert fam is not None
    ab, w0, e12, residual = fam
    rebuilt = w0 + np.einsum("sk,kij->sij", ab, e12)
    np.testing.assert_allclose(rebuilt[:, :, :3], R_sym, atol=1e-14)
    np.testing.assert_allclose(rebuilt[:, :, 3], t_sym, atol=1e-13)
    assert residual < 1e-12


@pytest.mark.parametrize(
    "syms",
    [
        (np.stack([np.eye(3), np.diag([-1.0, -1.0, 1.0])]), np.zeros((2, 3))),  # S < 3
        symmetry_transforms(DISC_AND_CONT, 0.3),  # two families: rank 4
    ],
    ids=["discrete", "discrete-and-continuous"],
)
def test_symmetry_family_is_none_for_other_sets(syms: tuple[np.ndarray, np.ndarray]) -> None:
    assert max_distance.symmetry_family(*syms) is None


@pytest.mark.parametrize("info", [TILTED, DISC_AND_CONT], ids=["family", "generic"])
def test_family_and_generic_bounds_match_reference(info: dict[str, object]) -> None:
    rng = np.random.default_rng(12)
    pts = box_model(rng, 400)
    syms = symmetry_transforms(info, 0.1)
    parts = [pose_pairs(rng, 15, deg=d, mm=d) for d in (0.01, 3.0, 30.0, 180.0)]
    R_est, t_est, R_gt, t_gt = (np.concatenate(x) for x in zip(*parts, strict=True))
    R_gt = R_gt * 1.1 + rng.normal(
        0, 0.02, R_gt.shape
    )  # not orthonormal: no shortcut may assume it
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms), _ref("mssd", R_est, t_est, R_gt, t_gt, pts, syms)
    )
    assert_close(
        mspd(R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
        _ref("mspd", R_est, t_est, R_gt, t_gt, K_CAM, pts, syms),
    )


@pytest.mark.parametrize("model", ["box", "needle", "planar", "few"])
def test_hull_probe_keeps_every_hull_vertex_and_tells_solid_from_thin(model: str) -> None:
    rng = np.random.default_rng(13)
    pts = {
        "box": lambda: box_model(rng, 5000),
        "needle": lambda: arc_model(rng, 5000),
        "planar": lambda: np.c_[rng.uniform(-5, 5, (600, 2)), np.zeros(600)],
        "few": lambda: box_model(rng, 4),
    }[model]()
    cand, share = hull_probe(pts)
    assert np.all(np.diff(cand) > 0)
    assert set(hull_vertex_indices(pts).tolist()) <= set(cand.tolist())
    if model == "box":  # solid: a small hull, most points dropped before Qhull
        assert share < max_distance.HULL_MAX_SHARE
        assert cand.size < len(pts) // 4
    elif model == "needle":  # thin: half the points on the hull, and still a cut
        assert share > max_distance.HULL_MAX_SHARE
        assert cand.size < 0.7 * len(pts)
    else:  # degenerate sample hulls keep everything
        assert share == 1.0
        assert cand.size == len(pts)


@pytest.mark.parametrize("model", ["box", "needle"])
def test_many_vertices_with_the_sampled_bound_stage(model: str) -> None:
    """≥ 4·SAMPLE_POINTS vertices: the strided sample stage and (box) the probed hull."""
    rng = np.random.default_rng(14)
    v = 4 * max_distance.SAMPLE_POINTS
    pts = box_model(rng, v) if model == "box" else arc_model(rng, v)
    syms = symmetry_transforms(CONT_Z, 0.03)
    parts = [pose_pairs(rng, 70, deg=d, mm=d) for d in (0.01, 3.0, 90.0)]
    R_est, t_est, R_gt, t_gt = (np.concatenate(x) for x in zip(*parts, strict=True))
    assert_close(
        mssd(R_est, t_est, R_gt, t_gt, pts, syms), _ref("mssd", R_est, t_est, R_gt, t_gt, pts, syms)
    )
