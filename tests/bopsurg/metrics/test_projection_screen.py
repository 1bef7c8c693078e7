"""MSPD's float32 screen: its error bound holds, and the band never loses the exact maximiser."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bopsurg.metrics import max_distance, mspd, symmetry_transforms
from bopsurg.metrics import projection_screen as ps
from bopsurg.metrics import reference as ref

from ._data import CONT_Z, HYP, K_CAM, arc_model, assert_close, box_model, pose_pairs

seeds = st.integers(0, 2**31 - 1)


def _proj_mats(R: np.ndarray, t: np.ndarray, K: np.ndarray = K_CAM) -> np.ndarray:
    """``K [R | t]`` per pose: (n, 3, 4)."""
    return np.matmul(K, np.concatenate([R, t[:, :, None]], axis=2))


def _float32_distances(P_e: np.ndarray, P_g: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, ...]:
    """Scaled forms, their bound and the float32 distances of every vertex, as the kernel does."""
    X_h = np.r_[pts.T, np.ones((1, len(pts)))]
    w = np.minimum(np.abs(P_e[:, 2] @ X_h).min(axis=1), np.abs(P_g[:, 2] @ X_h).min(axis=1))
    scale = 1.0 / w**2  # ≤ |w_e w_g| on every vertex, as the kernel's w_min
    q = ps.quadric_coefficients(P_e, P_g) * scale[:, None, None]
    x_abs = np.abs(X_h).max(axis=1)
    raw = ps.raw_term_sizes(np.abs(P_e) @ x_abs, np.abs(P_g) @ x_abs) * scale[:, None]
    verts = ps.ScreenVertices(X_h)
    a, b, ok = ps.screen_bounds(q, raw, verts.mono_max)
    f = np.matmul(q.astype(np.float32), verts.mono32)  # (n, 3, V)
    d32 = np.sqrt(((f[:, 0] ** 2 + f[:, 1] ** 2) / f[:, 2] ** 2).astype(np.float64))
    return q, a, b, ok, d32, verts


def _float64_distances(P_e: np.ndarray, P_g: np.ndarray, pts: np.ndarray) -> np.ndarray:
    X_h = np.r_[pts.T, np.ones((1, len(pts)))]
    ue, ug = P_e @ X_h, P_g @ X_h
    d = ue[:, :2] / ue[:, 2:3] - ug[:, :2] / ug[:, 2:3]
    return np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)


@HYP
@given(seed=seeds, far=st.sampled_from([1.0, 30.0]), deg=st.sampled_from([0.0, 0.01, 3.0, 90.0]))
def test_float32_distances_are_within_the_bound(seed: int, far: float, deg: float) -> None:
    """``|d₃₂ − d| ≤ a + b·max(d, d₃₂)`` on every vertex, near and far, tiny and large errors."""
    rng = np.random.default_rng(seed)
    pts = box_model(rng, 300) if seed % 2 else arc_model(rng, 300)
    R_e, t_e, R_g, t_g = pose_pairs(rng, 16, deg=deg, mm=deg)
    t_e[:, 2] *= far
    t_g[:, 2] *= far
    P_e, P_g = _proj_mats(R_e, t_e), _proj_mats(R_g, t_g)
    _, a, b, ok, d32, _ = _float32_distances(P_e, P_g, pts)
    d = _float64_distances(P_e, P_g, pts)
    bound = a[:, None] + b[:, None] * np.maximum(d, d32)
    assert np.all((np.abs(d32 - d) <= bound + 1e-12 * d)[ok])
    if deg <= 3.0:  # poses well in front of the camera: usable, and far below a pixel
        assert ok.all()
        assert np.all(a < 1e-3 * (1.0 + d.max(axis=1)))


def test_band_keeps_the_exact_maximiser_when_float32_ranks_it_second() -> None:
    """Two vertices 1e-11 px apart: float32 cannot order them, the band holds both."""
    # Identity rotations, an estimate shifted along x: the projected distance of a vertex
    # depends on its depth only, so mirrored vertices tie; the last one is made farther by a
    # hair (exact maximiser), the first is float32's (first index among equal values).
    pts = np.array([[10.0, 5.0, 0.0], [-10.0, -5.0, 0.0], [0.0, 0.0, 20.0], [3.0, -4.0, 2.0]])
    pts = np.concatenate([pts, [[-10.0, -5.0, -1e-9]]])
    R = np.eye(3)[None]
    t_g = np.array([[0.0, 0.0, 200.0]])
    t_e = t_g + np.array([[1.5, 0.0, 0.0]])
    P_e, P_g = _proj_mats(R, t_e), _proj_mats(R, t_g)
    _, a, b, ok, d32, verts = _float32_distances(P_e, P_g, pts)
    d = _float64_distances(P_e, P_g, pts)
    assert ok.all()
    assert np.argmax(d[0]) == 4  # exact: the nudged vertex
    assert np.argmax(d32[0]) != 4  # float32 ranks another one first
    q = ps.quadric_coefficients(P_e, P_g) * (1.0 / 200.0**2)
    a, b, _ = ps.screen_bounds(q, np.full((1, 3), 1e3), verts.mono_max)
    pair, vertex = ps.screened_max(q.astype(np.float32), verts, a, b, 3, 8)
    assert set(pair.tolist()) == {0}
    assert 4 in vertex.tolist()
    got = mspd(R[0], t_e[0], R[0], t_g[0], K_CAM, pts)[0]
    assert got == pytest.approx(ref.mspd_ref(R[0], t_e[0], R[0], t_g[0], K_CAM, pts), rel=1e-12)


def test_zero_distances_put_every_vertex_in_the_band() -> None:
    """Identical poses: all forms cancel to 0, the bound is 0 and every vertex ties at 0."""
    rng = np.random.default_rng(3)
    pts = box_model(rng, 50)
    R_e, t_e, _, _ = pose_pairs(rng, 2)
    P = _proj_mats(R_e, t_e)
    q, a, b, ok, d32, verts = _float32_distances(P, P, pts)
    assert ok.all()
    assert np.all(d32 == 0.0)
    pair, vertex = ps.screened_max(q.astype(np.float32), verts, a, b, 3, 8)
    assert pair.tolist() == [0] * len(pts) + [1] * len(pts)
    assert vertex.tolist() == list(range(len(pts))) * 2


@pytest.mark.parametrize("case", ["near-plane", "far", "huge-model", "ring-ties"])
def test_screened_mspd_matches_reference_on_hard_poses(case: str) -> None:
    rng = np.random.default_rng(21)
    syms = symmetry_transforms(CONT_Z, 0.05)
    R_e, t_e, R_g, t_g = pose_pairs(rng, 12, deg=3.0, mm=3.0)
    pts = box_model(rng, 400)
    if case == "near-plane":  # the nearest vertex a few mm in front of the camera
        t_g[:, 2] = 40.0
        t_e[:, 2] = 40.0 + rng.normal(0.0, 1.0, 12)
    elif case == "far":  # 50 m away: distances of a few hundredths of a pixel
        t_g[:, 2] += 5e4
        t_e[:, 2] += 5e4
    elif case == "huge-model":  # monomials beyond float32's limit: the float64 path
        pts = pts * 1e9
        t_g[:, 2] *= 1e9
        t_e = t_g + rng.normal(0.0, 1e8, t_e.shape)
        assert not ps.ScreenVertices(np.r_[pts.T, np.ones((1, len(pts)))]).usable
    else:  # a ring: every symmetry of the sampled set is (nearly) exact, all tie
        ang = np.arange(60) * 2 * np.pi / 60
        pts = np.c_[15 * np.cos(ang), 15 * np.sin(ang), np.zeros(60)]
        R_e = R_g @ symmetry_transforms(CONT_Z, 0.05)[0][7]
        t_e = t_g + rng.normal(0.0, 0.5, t_e.shape)
    exp = np.array(
        [ref.mspd_ref(R_e[i], t_e[i], R_g[i], t_g[i], K_CAM, pts, syms) for i in range(12)]
    )
    assert_close(mspd(R_e, t_e, R_g, t_g, K_CAM, pts, syms), exp)


def test_generic_symmetry_set_uses_the_reference_matrices() -> None:
    """Discrete symmetries (no one-parameter family): the per-pair matrices and forms."""
    rng = np.random.default_rng(22)
    syms = symmetry_transforms(
        {"symmetries_discrete": [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]}
    )
    assert max_distance.symmetry_family(*syms) is None
    pts = arc_model(rng, 500)
    R_e, t_e, R_g, t_g = pose_pairs(rng, 30, deg=20.0, mm=5.0)
    exp = np.array(
        [ref.mspd_ref(R_e[i], t_e[i], R_g[i], t_g[i], K_CAM, pts, syms) for i in range(30)]
    )
    assert_close(mspd(R_e, t_e, R_g, t_g, K_CAM, pts, syms), exp)


def test_segment_max_lets_a_non_finite_value_win_its_segment() -> None:
    seg = np.array([0, 0, 0, 1, 1, 2])
    vals = np.array([1.0, 3.0, 2.0, 5.0, np.inf, 4.0])
    idx = np.array([10, 11, 12, 13, 14, 15])
    val, arg = max_distance._segment_max(seg, vals, idx, 4)
    assert val[:3].tolist() == [3.0, np.inf, 4.0]
    assert arg[:3].tolist() == [11, 14, 15]
    assert np.isnan(val[3])  # no entry
    val, arg = max_distance._segment_max(np.array([0, 0]), np.array([1.0, np.nan]), idx[:2], 1)
    assert np.isnan(val[0])
    assert arg[0] == 11
