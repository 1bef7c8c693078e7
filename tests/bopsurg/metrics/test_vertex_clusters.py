"""MSPD's vertex clusters: the bounds hold on every vertex, and pruning never changes a value."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, example, given
from hypothesis import strategies as st

from bopsurg.metrics import max_distance, mspd, symmetry_transforms
from bopsurg.metrics import projection_screen as ps
from bopsurg.metrics import reference as ref
from bopsurg.metrics import vertex_clusters as vc

from ._data import CONT_Z, HYP, K_CAM, arc_model, assert_close, box_model, pose_pairs

seeds = st.integers(0, 2**31 - 1)


def _forms(R_e, t_e, R_g, t_g, pts):  # type: ignore[no-untyped-def]
    """Scaled forms (|N_w| ≥ 1 on the vertices), their float32 copy and screen error bounds."""
    P_e = np.matmul(K_CAM, np.concatenate([R_e, t_e[:, :, None]], axis=2))
    P_g = np.matmul(K_CAM, np.concatenate([R_g, t_g[:, :, None]], axis=2))
    X_h = np.r_[pts.T, np.ones((1, len(pts)))]
    w = np.minimum(np.abs(P_e[:, 2] @ X_h).min(axis=1), np.abs(P_g[:, 2] @ X_h).min(axis=1))
    q = ps.quadric_coefficients(P_e, P_g) / w[:, None, None] ** 2
    x_abs = np.abs(X_h).max(axis=1)
    raw = ps.raw_term_sizes(np.abs(P_e) @ x_abs, np.abs(P_g) @ x_abs) / w[:, None] ** 2
    verts = ps.ScreenVertices(X_h)
    a, b, ok = ps.screen_bounds(q, raw, verts.mono_max)
    return q, a, b, verts, ok


def _exact(q: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(k, V) distances of the forms in float64 (their rounding is far below the margins)."""
    f = q @ ps.monomials(np.r_[pts.T, np.ones((1, len(pts)))])
    return np.hypot(f[:, 0], f[:, 1]) / np.abs(f[:, 2])


def _model(kind: str, rng: np.random.Generator, v: int) -> np.ndarray:
    if kind == "box":
        return box_model(rng, v)
    if kind == "arc":
        return arc_model(rng, v)
    if kind == "duplicates":  # every vertex 8 times: clusters of one repeated point
        return np.repeat(box_model(rng, v // 8), 8, axis=0)
    if kind == "flat":  # a flat disc (z = 0): degenerate along one axis
        pts = box_model(rng, v)
        pts[:, 2] = 0.0
        return pts
    return np.zeros((v, 3)) + np.array([3.0, -2.0, 1.0])  # "point": all vertices equal


@HYP
@given(
    seed=seeds,
    kind=st.sampled_from(["box", "arc", "duplicates", "flat", "point"]),
    deg=st.sampled_from([0.0, 0.01, 3.0, 40.0]),
    near=st.booleans(),
)
@example(seed=97, kind="box", deg=40.0, near=False)  # a pair the screen refuses
def test_bounds_hold_on_every_vertex(seed: int, kind: str, deg: float, near: bool) -> None:
    """``low`` ≤ the distance at the representative, ``up`` ≥ it on every member."""
    rng = np.random.default_rng(seed)
    pts = _model(kind, rng, 1024)
    R_e, t_e, R_g, t_g = pose_pairs(rng, 6, deg=deg, mm=deg)
    if near:  # the nearest vertices a few mm in front of the camera
        t_g[:, 2] = 45.0
        t_e[:, 2] = 45.0 + rng.uniform(-1.0, 1.0, 6)
    q, _, _, verts, ok = _forms(R_e, t_e, R_g, t_g, pts)
    # the clusters serve screenable pairs only (the others take the float64 path)
    assume(ok.any())
    q = q[ok]
    cl = vc.VertexClusters(pts, verts.mono32)
    low, up = vc.cluster_bounds(q, q.astype(np.float32), cl, 64)
    d = _exact(q, pts)
    members = d[:, cl.members]  # (k, C, m)
    slack = 1e-12 * (1.0 + d.max(axis=1))[:, None]
    assert np.all(low <= d[:, cl.reps] + slack)
    assert np.all(members.max(axis=2) <= up + slack)
    if kind in ("box", "arc") and deg <= 3.0 and not near:  # and useful: finite, near d
        assert np.all(np.isfinite(up))
        # (a few clusters of a small model are wide: ρ up to ~17 mm, their bound ~2 d_max)
        assert np.all(up <= members.max(axis=2) + 1.0 + 2.0 * d.max(axis=1)[:, None])


def test_curvature_term_bounds_a_flat_gradient() -> None:
    """Hand-worked: ``f = (x², 0)``, ``N_w = 1``. At a representative near x = 0 the gradient
    vanishes, so only the quadratic term ``‖A‖ ρ² = ρ²`` can bound ``x²`` on the cluster."""
    x = np.linspace(-1.0, 1.0, 1024)
    pts = np.c_[x, np.zeros_like(x), np.zeros_like(x)]
    q = np.zeros((1, 3, 10))
    q[0, 0, 0] = 1.0  # x_0 x_0
    q[0, 2, 9] = 1.0  # the constant monomial
    cl = vc.VertexClusters(pts, ps.monomials(np.r_[pts.T, np.ones((1, 1024))]).astype(np.float32))
    low, up = vc.cluster_bounds(q, q.astype(np.float32), cl, 64)
    d = x[cl.members] ** 2
    assert np.all(d.max(axis=1) <= up[0])
    centre = np.argmin(np.abs(x[cl.reps]))
    assert up[0, centre] >= cl.rho[centre] ** 2  # the curvature term carries the bound
    assert np.all(low[0] <= x[cl.reps] ** 2)


def test_clusters_cover_every_vertex_and_bound_their_radius() -> None:
    rng = np.random.default_rng(4)
    pts = box_model(rng, 1000)
    cl = vc.VertexClusters(pts, ps.ScreenVertices(np.r_[pts.T, np.ones((1, 1000))]).mono32)
    assert cl.c * cl.m >= 1000
    assert set(cl.members.ravel().tolist()) == set(range(1000))
    assert np.all(np.isin(cl.reps, cl.members))
    dist = np.linalg.norm(pts[cl.members] - pts[cl.reps][:, None], axis=2)
    assert np.all(dist.max(axis=1) <= cl.rho)
    assert np.all(cl.rho.astype(np.float32) <= cl.rho32)
    assert vc.make_clusters(pts[:100], cl.mono32[0]) is None  # too few vertices to pay
    big = box_model(rng, 30000)
    many = vc.VertexClusters(big, np.zeros((10, 30000), np.float32))
    assert many.c == vc.MAX_CLUSTERS
    assert set(many.members.ravel().tolist()) == set(range(30000))


@HYP
@given(seed=seeds, kind=st.sampled_from(["box", "arc", "duplicates"]), tie=st.booleans())
def test_clustered_band_holds_the_exact_maximiser(seed: int, kind: str, tie: bool) -> None:
    """The band of the surviving clusters contains every vertex of the exact maximum."""
    rng = np.random.default_rng(seed)
    pts = _model(kind, rng, 1024)
    if tie:  # a mirrored model: every distance of a mirror pose ties with its mirror image
        pts = np.concatenate([pts[:512], pts[:512] * np.array([-1.0, -1.0, 1.0])])
    R_e, t_e, R_g, t_g = pose_pairs(rng, 12, deg=3.0, mm=3.0)
    if tie:
        R_e, R_g = np.repeat(np.eye(3)[None], 12, 0), np.repeat(np.eye(3)[None], 12, 0)
        t_e[:, :2] = t_g[:, :2] = 0.0
    q, a, b, verts, ok = _forms(R_e, t_e, R_g, t_g, pts)
    assert ok.all()
    cl = vc.VertexClusters(pts, verts.mono32)
    q32 = q.astype(np.float32)
    bounds = vc.cluster_bounds(q, q32, cl, 64)
    d = _exact(q, pts)
    lower = d.max(axis=1) * (1.0 - 1e-9)  # a tight known bound: the most pruning
    for known in [(None, None), (lower, None)]:
        pair, vertex = vc.clustered_band(q32, cl, bounds, (a, b), known, 7, 40)
        assert np.all(np.diff(pair) >= 0)
        for i in range(12):
            best = np.flatnonzero(d[i] >= d[i].max() * (1.0 - 1e-12))
            assert set(best.tolist()) <= set(vertex[pair == i].tolist())


def test_capped_pairs_skip_the_other_clusters() -> None:
    """A pair whose first cluster reaches its cap keeps only that cluster's band."""
    rng = np.random.default_rng(8)
    pts = box_model(rng, 1024)
    R_e, t_e, R_g, t_g = pose_pairs(rng, 4, deg=3.0, mm=3.0)
    q, a, b, verts, ok = _forms(R_e, t_e, R_g, t_g, pts)
    assert ok.all()
    cl = vc.VertexClusters(pts, verts.mono32)
    q32 = q.astype(np.float32)
    bounds = vc.cluster_bounds(q, q32, cl, 64)
    cap = np.array([0.0, np.inf, 0.0, np.inf])  # pairs 0 and 2 reach their cap at once
    pair, vertex = vc.clustered_band(q32, cl, bounds, (a, b), (None, cap), 7, 40)
    top = np.argmax(bounds[1], axis=1)
    for i in (0, 2):
        assert set(vertex[pair == i].tolist()) <= set(cl.members[top[i]].tolist())
    d = _exact(q, pts)
    for i in (1, 3):
        assert np.argmax(d[i]) in vertex[pair == i]


@pytest.fixture
def small_clusters(monkeypatch: pytest.MonkeyPatch) -> None:
    """Clusters of 8 vertices from 16 clusters on, for every full evaluation."""
    monkeypatch.setattr(vc, "CLUSTER_SIZE", 8)
    monkeypatch.setattr(vc, "MIN_CLUSTERS", 2)
    monkeypatch.setattr(max_distance, "CLUSTER_MIN_PAIRS", 1)


@pytest.mark.usefixtures("small_clusters")
@pytest.mark.parametrize(
    "case", ["box", "needle", "near-plane", "far", "identical", "ring-ties", "huge"]
)
def test_pruned_mspd_matches_reference(case: str) -> None:
    """MSPD with cluster pruning on every full evaluation equals the reference."""
    rng = np.random.default_rng(31)
    syms = symmetry_transforms(CONT_Z, 0.05)
    R_e, t_e, R_g, t_g = pose_pairs(rng, 16, deg=3.0, mm=3.0)
    pts = arc_model(rng, 300) if case == "needle" else box_model(rng, 300)
    if case == "near-plane":  # the nearest vertex a few mm in front of the camera
        t_g[:, 2] = 40.0
        t_e[:, 2] = 40.0 + rng.normal(0.0, 1.0, 16)
    elif case == "far":  # 50 m away: distances of a few hundredths of a pixel
        t_g[:, 2] += 5e4
        t_e[:, 2] += 5e4
    elif case == "identical":  # every distance 0: all vertices tie
        R_e, t_e = R_g.copy(), t_g.copy()
    elif case == "ring-ties":  # a ring: every symmetry (nearly) exact, all tie
        ang = np.arange(64) * 2 * np.pi / 64
        pts = np.c_[15 * np.cos(ang), 15 * np.sin(ang), np.zeros(64)]
        R_e = R_g @ syms[0][7]
    elif case == "huge":  # coordinates of 1e6 mm, still within float32's range
        pts, t_g = pts * 1e4, t_g * 1e4
        t_e = t_g + rng.normal(0.0, 1e4, t_e.shape)
    exp = np.array(
        [ref.mspd_ref(R_e[i], t_e[i], R_g[i], t_g[i], K_CAM, pts, syms) for i in range(16)]
    )
    assert_close(mspd(R_e, t_e, R_g, t_g, K_CAM, pts, syms), exp)


@HYP
@given(seed=seeds, deg=st.sampled_from([0.01, 2.0, 20.0]))
@pytest.mark.usefixtures("small_clusters")
def test_pruning_never_changes_a_value(seed: int, deg: float) -> None:
    """Random models and poses: the same values as the reference with every shortcut on."""
    rng = np.random.default_rng(seed)
    pts = box_model(rng, 200) if seed % 2 else arc_model(rng, 200)
    syms = symmetry_transforms(CONT_Z, 0.2)
    R_e, t_e, R_g, t_g = pose_pairs(rng, 6, deg=deg, mm=deg)
    exp = np.array(
        [ref.mspd_ref(R_e[i], t_e[i], R_g[i], t_g[i], K_CAM, pts, syms) for i in range(6)]
    )
    assert_close(mspd(R_e, t_e, R_g, t_g, K_CAM, pts, syms), exp)


@pytest.mark.parametrize("model", ["box", "needle"])
def test_default_clusters_match_reference(model: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Default settings: 1,000 vertices (16 clusters) and 120 poses, so round 0 is pruned."""
    calls = []

    def spy(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(args[0].shape[0])
        return vc.clustered_band(*args, **kwargs)

    monkeypatch.setattr(max_distance, "clustered_band", spy)
    rng = np.random.default_rng(41)
    pts = box_model(rng, 1000) if model == "box" else arc_model(rng, 1000)
    syms = symmetry_transforms(CONT_Z, 0.1)
    R_e, t_e, R_g, t_g = pose_pairs(rng, 120, deg=3.0, mm=3.0)
    exp = np.array(
        [ref.mspd_ref(R_e[i], t_e[i], R_g[i], t_g[i], K_CAM, pts, syms) for i in range(120)]
    )
    assert_close(mspd(R_e, t_e, R_g, t_g, K_CAM, pts, syms), exp)
    assert calls[:1] == [120]  # round 0 went through the clusters
