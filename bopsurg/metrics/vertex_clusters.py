"""MSPD's vertex clusters: a rigorous bound of the projected distance per cluster of vertices.

A full MSPD evaluation of a (pose, symmetry) pair needs the maximum of the projected distance
over every vertex. Most vertices are far below it, and whole clusters of them can be shown to
be: the vertices are split once per call into ``C`` clusters of equal size (a balanced k-d
split, :class:`VertexClusters`), each with a representative vertex ``r`` and a radius ``ρ``
(``‖x − r‖ ≤ ρ`` for its vertices). For a pair with the screen's quadratic forms ``N_u, N_v,
N_w`` (:mod:`~bopsurg.metrics.projection_screen`), ``f = (N_u, N_v) / N_w`` is the projected
difference. With ``f_r = f(r)``, ``G = (N_u, N_v) − f_r N_w`` is a pair of quadratic forms that
vanish at ``r``, so ``G(r + δ) = (∇G_u(r)·δ + δᵀ A_Gu δ, ...)`` exactly, with ``A_Gu = A_u −
f_r,u A_w`` (``A``: the forms' quadratic parts, Frobenius norms below) and, on the cluster,

    ``‖f(x)‖ ≤ ‖f_r‖ + ‖G(x)‖ / |N_w(x)|``,
    ``‖G(x)‖ ≤ ‖(∇G_u(r), ∇G_v(r))‖ ρ + (‖(‖A_u‖, ‖A_v‖)‖ + ‖A_w‖ ‖f_r‖) ρ²``,
    ``|N_w(x)| ≥ |N_w(r)| − ‖∇N_w(r)‖ ρ − ‖A_w‖ ρ²``.

Subtracting ``f_r N_w`` keeps the cancellation between the numerators and the denominator:
the bound grows with how fast the projected *difference* varies, not with how fast either
projection does. :func:`cluster_bounds` returns per (pair, cluster) the distance at the
representative (a lower bound of the pair's maximum) and this upper bound, each widened by a
margin for their float32 rounding. A cluster whose upper bound is below a lower bound of the
pair's maximum cannot hold the maximiser (:func:`surviving_clusters`); :func:`clustered_band`
screens the vertices of the other clusters in float32 and returns the same band as
:func:`~bopsurg.metrics.projection_screen.screened_max` would (up to vertices that cannot be
the maximiser), so the float64 maximum over it is the maximum over all vertices.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import NDArray

from bopsurg.metrics.projection_screen import (
    MONO_A,
    MONO_B,
    band_threshold,
    monomials,
    shared_matmul,
)

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]

#: Vertices per cluster (about): small clusters bound tightly, many clusters cost more calls.
CLUSTER_SIZE = 80
#: Fewest clusters worth the bounds.
MIN_CLUSTERS = 8
#: Most clusters: the bounds' (pairs × clusters) arrays stay a few MB for large models.
MAX_CLUSTERS = 256
#: Pairs per block of the bounds: their (pairs × clusters) temporaries stay a few hundred KB,
#: reused from the heap block after block (fresh MB-sized ones cost page faults at every call).
BOUND_PAIRS = 256
#: Relative size of the margin that covers the float32 rounding of the bounds: 2⁻¹⁴ ≈ 1000 u,
#: where the few dozen operations behind each bound round by well under 100 u.
ROUNDING = 2.0**-14

#: (4, 4) index of the monomial ``x_a x_b`` among the 10.
_MONO_INDEX = np.zeros((4, 4), np.int64)
_MONO_INDEX[MONO_A, MONO_B] = _MONO_INDEX[MONO_B, MONO_A] = np.arange(10)
#: (3, 4) index of the coefficient of ``x_i x_j`` and its factor in ``∂_i`` of a form.
_GRAD_T = _MONO_INDEX[:3]
_GRAD_W = np.where(np.arange(3)[:, None] == np.arange(4)[None, :], 2.0, 1.0).astype(np.float32)
#: Monomials of the quadratic part (both indices < 3) and their weight in a Frobenius norm.
_QUAD = np.flatnonzero(MONO_B < 3)
_QUAD_W = np.where(MONO_A[_QUAD] == MONO_B[_QUAD], 1.0, 0.5)


class VertexClusters:
    """A balanced k-d split of the vertices into ``C`` clusters of ``m`` vertices each.

    ``C·m`` may exceed V: the missing members repeat vertices (a repeated vertex changes no
    maximum).

    Args:
        pts: (V, 3) float64 vertices, mm.
        mono32: (10, V) float32 monomials of the vertices (the screen's).
    """

    def __init__(self, pts: F64, mono32: F32) -> None:
        v = pts.shape[0]
        levels = min(
            int(np.round(np.log2(max(1.0, v / CLUSTER_SIZE)))), MAX_CLUSTERS.bit_length() - 1
        )
        self.c, self.m = 1 << levels, -(-v // (1 << levels))
        idx = np.concatenate([np.arange(v), np.arange(self.c * self.m - v) % v])[None]
        coords = np.ascontiguousarray(pts.T)  # (3, V): reductions over contiguous rows
        for _ in range(levels):  # split every node at the median of its widest axis
            x = np.take(coords, idx, axis=1)  # (3, nodes, size), contiguous
            axis = np.argmax(x.max(axis=2) - x.min(axis=2), axis=0)
            key = x[axis, np.arange(idx.shape[0])]
            half = idx.shape[1] // 2
            idx = np.take_along_axis(idx, np.argpartition(key, half, axis=1), axis=1)
            idx = np.concatenate([idx[:, :half], idx[:, half:]])
        self.members: I64 = idx  # (C, m) vertex indices
        x = np.take(coords, idx, axis=1)  # (3, C, m)
        centre = 0.5 * (x.max(axis=2) + x.min(axis=2))
        near = np.argmin(np.square(x - centre[:, :, None]).sum(axis=0), axis=1)
        self.reps: I64 = idx[np.arange(self.c), near]  # (C,)
        r = pts[self.reps]
        # ‖x − r‖ rounded up: the computed norm is within 4u of the exact one
        dist2 = np.square(x - r.T[:, :, None]).sum(axis=0)
        self.rho: F64 = np.sqrt(dist2.max(axis=1)) * (1 + 2**-48)
        self.rho2: F64 = self.rho * self.rho * (1 + 2**-50)
        self.r_h: F64 = np.ascontiguousarray(np.r_[r.T, np.ones((1, self.c))])  # (4, C)
        self.mono_r: F64 = monomials(self.r_h)  # (10, C)
        # |m_t(r)|, ‖∇m_t(r)‖ ρ and the quadratic terms are all below (X_a + ρ)(X_b + ρ)
        # (X_3 = 1 and no ρ for the homogeneous coordinate): the magnitudes behind the
        # rounding margin.
        ext = np.r_[np.abs(coords).max(axis=1) + float(self.rho.max()), 1.0]
        self.mono_mag: F64 = ext[MONO_A] * ext[MONO_B]  # (10,)
        self.mono32: F32 = np.ascontiguousarray(np.take(mono32, idx, axis=1).transpose(1, 0, 2))
        self.mono_r32 = self.mono_r.astype(np.float32)
        self.r_h32 = self.r_h.astype(np.float32)
        # ρ and ρ² rounded up to float32
        self.rho32 = (self.rho * (1 + 2**-22)).astype(np.float32)
        self.rho2_32 = (self.rho2 * (1 + 2**-22)).astype(np.float32)
        self._work: tuple[F32, F32, F32, B] | None = None

    def work(self, n: int) -> tuple[F32, F32, F32, B]:
        """Work buffers for ``n`` entries: forms (3, n, m), two (n, m) and a (n, m) mask.

        Kept across calls: fresh MB-sized buffers would cost page faults at every call.
        """
        if self._work is None or self._work[1].shape[0] < n:
            m = self.m
            self._work = (
                np.empty((3, n, m), np.float32),
                np.empty((n, m), np.float32),
                np.empty((n, m), np.float32),
                np.empty((n, m), np.bool_),
            )
        return self._work


def make_clusters(pts: F64, mono32: F32) -> VertexClusters | None:
    """The clusters of a model, or None when it has too few vertices for them to pay."""
    if pts.shape[0] < MIN_CLUSTERS * CLUSTER_SIZE:
        return None
    return VertexClusters(pts, mono32)


def _rows_times(a: F32, b: F32, rows: int) -> F32:
    """``a @ b`` in products of at most ``rows`` rows of ``a`` (each on one thread)."""
    out = np.empty((a.shape[0], b.shape[1]), np.float32)
    for r in range(0, a.shape[0], rows):
        np.matmul(a[r : r + rows], b, out=out[r : r + rows])
    return out


def cluster_bounds(q: F64, q32: F32, cl: VertexClusters, per_product: int) -> tuple[F32, F32]:
    """Per (pair, cluster): the distance at the representative and an upper bound over all.

    Computed in float32 (``u = 2⁻²⁴``) on (k, C) arrays and widened for its rounding: each
    term is a sum of products of at most a few dozen roundings of quantities bounded by ``mag``
    (``Σ |q_t| (X_a + ρ)(X_b + ρ)`` per form: its terms at ``r``, its gradient times ``ρ`` and
    its quadratic part times ``ρ²``), and ``f_r``'s error, relative to ``mag_w / |N_w(r)|``,
    enters the gradient of ``G``. With ``|N_w(r)| ≥ 1`` (a vertex) both values are within
    ``2 ROUNDING (1 + mag_w)(mag_u + mag_v + ‖f_r‖ mag_w)`` (``ROUNDING`` ≈ 1000 u) of their
    exact counterparts before the division by the lower bound of ``|N_w|``, itself lowered by
    ``ROUNDING · mag_w``.

    Args:
        q: (k, 3, 10) float64 coefficients of ``N_u, N_v, N_w`` (scaled, ``|N_w| ≥ 1`` on the
            vertices).
        q32: ``q`` in float32.
        cl: The model's clusters.
        per_product: Rows per matrix product at most (one thread).

    Returns:
        ``(low, up)`` (k, C) each, px: ``low`` ≤ the exact distance of the forms ``q`` at the
        representative and ``up`` ≥ it at every vertex of the cluster (inf where the bound
        does not hold; NaN for non-finite input).
    """
    k = q.shape[0]
    low, up = np.empty((k, cl.c), np.float32), np.empty((k, cl.c), np.float32)
    for p0 in range(0, k, BOUND_PAIRS):
        p1 = min(k, p0 + BOUND_PAIRS)
        low[p0:p1], up[p0:p1] = _block_bounds(q[p0:p1], q32[p0:p1], cl, per_product)
    return low, up


def _block_bounds(q: F64, q32: F32, cl: VertexClusters, per_product: int) -> tuple[F32, F32]:
    """:func:`cluster_bounds` of one block of pairs."""
    k, c = q.shape[0], cl.c
    qt = np.ascontiguousarray(q32.transpose(1, 0, 2))  # (3, k, 10)
    # (3, 3, k, 4): ∂_i N = grad_rows[., i] · [x; 1]
    grad_rows = np.ascontiguousarray((np.take(qt, _GRAD_T, axis=2) * _GRAD_W).transpose(0, 2, 1, 3))
    at_r = _rows_times(qt.reshape(3 * k, 10), cl.mono_r32, per_product).reshape(3, k, c)
    # float32 operands, C-ordered: a float64 or strided operand takes numpy's slow loop
    g = _rows_times(grad_rows.reshape(9 * k, 4), cl.r_h32, per_product).reshape(3, 3, k, c)
    quad = np.sqrt(
        shared_matmul(
            np.square(np.take(q, _QUAD, axis=2) * _QUAD_W), np.where(_QUAD_W == 1.0, 1.0, 2.0)
        )
    )
    mag = shared_matmul(np.abs(q), cl.mono_mag)  # (k, 3)
    # Per-pair constants, (k, 1): the quadratic parts and the rounding margin α + β‖f_r‖
    # (|N_w(r)| ≥ 1 at a vertex, to within 1e-8: the factor 2 covers it).
    q_uv = np.hypot(quad[:, 0], quad[:, 1]).astype(np.float32)[:, None]
    q_w = quad[:, 2].astype(np.float32)[:, None]
    margin = 2.0 * ROUNDING * (1.0 + mag[:, 2])
    alpha = (margin * (mag[:, 0] + mag[:, 1])).astype(np.float32)[:, None]
    beta = (margin * mag[:, 2]).astype(np.float32)[:, None]
    w_shift = (ROUNDING * mag[:, 2]).astype(np.float32)[:, None]
    f = at_r[:2] / at_r[2]  # (2, k, C): f_r
    w = np.abs(at_r[2], out=at_r[2])
    grad = np.zeros((k, c), np.float32)  # ‖∇G_u‖² + ‖∇G_v‖², then its root
    grad_w = np.zeros((k, c), np.float32)  # ‖∇N_w‖², then its root
    t = np.empty((2, k, c), np.float32)
    for i in range(3):
        np.multiply(f, g[2, i], out=t)
        np.subtract(g[:2, i], t, out=t)
        np.square(t, out=t)
        grad += t[0]
        grad += t[1]
        grad_w += np.square(g[2, i], out=g[2, i])
    np.square(f, out=t)
    d_r = np.add(t[0], t[1], out=t[0])
    np.sqrt(d_r, out=d_r)
    rho, rho2 = cl.rho32, cl.rho2_32
    # |N_w| ≥ |N_w(r)| − ‖∇N_w(r)‖ ρ − ‖A_w‖ ρ² on the cluster, lowered for rounding
    w -= np.multiply(np.sqrt(grad_w, out=grad_w), rho, out=grad_w)
    w -= q_w * rho2 + w_shift
    # ‖G(x)‖ ≤ ‖(‖∇G_u‖, ‖∇G_v‖)‖ ρ + (‖(‖A_u‖, ‖A_v‖)‖ + ‖A_w‖ ‖f_r‖) ρ², plus the margin
    up = np.multiply(np.sqrt(grad, out=grad), rho, out=grad)
    quad_part = np.multiply(d_r, q_w, out=t[1])
    quad_part += q_uv
    quad_part *= rho2
    up += quad_part
    scale = np.multiply(d_r, beta, out=t[1])
    scale += alpha
    up += scale
    with np.errstate(divide="ignore", invalid="ignore"):
        up /= w
    up += d_r
    up[~(w > 0.0)] = np.inf
    low = np.subtract(d_r, scale, out=scale)
    return low, up


def surviving_clusters(low: F32, up: F32, a: F64, b: F64, lower: F64 | None = None) -> B:
    """(k, C) clusters that may hold the maximiser of each pair's exact distance.

    The exact distance ``d`` and that of the forms ``q``, ``d_q``, differ by at most the
    screen's ``a + b·max(d, d_q)`` (its float64 part), so ``d ≤ (up + a) / (1 − b)`` on a
    cluster and ``d(r) ≥ (1 − b)·low − a`` at a representative. A cluster whose first is
    below the largest second (or ``lower``, a known lower bound of the maximum, px) holds no
    maximiser. NaN bounds keep their clusters.

    Args:
        low, up: (k, C) from :func:`cluster_bounds`.
        a, b: (k,) the screen's error bounds
            (:func:`~bopsurg.metrics.projection_screen.screen_bounds`).
        lower: (k,) optional lower bounds of the pairs' maxima, px.
    """
    with np.errstate(invalid="ignore"):
        best = (1.0 - b) * np.max(low, axis=1) - a
        if lower is not None:
            best = np.fmax(best, lower)
        keep: B = ~(up + a[:, None] < ((1.0 - b) * best)[:, None])
    return keep


def _screen_entries(
    q32: F32,
    cl: VertexClusters,
    entries: tuple[I64, I64],
    floor: F32,
    per_product: int,
    per_block: int,
    entry_max: F32 | None = None,
) -> tuple[I64, I64, F32]:
    """Float32 squared distances of the vertices of cluster ``ce`` under pair ``pe``, kept
    where they reach ``floor[pe]``; ``entry_max`` (n,), if given, receives each entry's
    maximum.

    ``ce`` is sorted. Per block of entries one product per cluster (and form), then the
    quotient on contiguous (entries, m) arrays, in work buffers kept across calls.

    Returns:
        ``(entry, column, d²)`` of the kept values (entry indexes ``ce``/``pe``).
    """
    (ce, pe), m = entries, cl.m
    n = ce.size
    qe = np.take(np.ascontiguousarray(q32.transpose(1, 0, 2)), pe, axis=1)  # (3, n, 10)
    nb = max(1, min(n, per_block))
    forms, sq, tmp, mask = cl.work(nb)
    # segments: one cluster each, within one block, at most per_product entries
    cuts = np.r_[np.searchsorted(ce, np.arange(cl.c)), np.arange(0, n, nb)]
    cuts = np.unique(np.r_[cuts[cuts < n], np.arange(0, n, per_product), n]).tolist()
    found: list[tuple[I64, F32]] = []
    e0 = 0
    for s0, s1 in itertools.pairwise(cuts):
        np.matmul(qe[:, s0:s1], cl.mono32[ce[s0]], out=forms[:, s0 - e0 : s1 - e0])
        if s1 % nb and s1 < n:
            continue
        k = s1 - e0  # the block [e0, s1) is complete
        f, s, t = forms[:, :k], sq[:k], tmp[:k]
        np.multiply(f[0], f[0], out=s)
        np.multiply(f[1], f[1], out=t)
        np.add(s, t, out=s)
        np.multiply(f[2], f[2], out=t)
        np.divide(s, t, out=s)
        if entry_max is not None:
            np.max(s, axis=1, out=entry_max[e0:s1])
        np.greater_equal(s, floor[pe[e0:s1], None], out=mask[:k])
        flat = np.flatnonzero(mask[:k])
        found.append((flat + e0 * m, s.ravel()[flat]))
        e0 = s1
    if not found:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
    flat = np.concatenate([f for f, _ in found])
    entry, col = np.divmod(flat, m)
    return entry, col, np.concatenate([v for _, v in found])


def clustered_band(
    q32: F32,
    cl: VertexClusters,
    bounds: tuple[F32, F32],
    err: tuple[F64, F64],
    known: tuple[F64 | None, F64 | None],
    per_product: int,
    per_block: int,
) -> tuple[I64, I64]:
    """The band of every pair (see :func:`~bopsurg.metrics.projection_screen.screened_max`),
    screening only vertices of clusters that may hold the maximum.

    First the cluster with the largest bound of each pair is screened: its float32 maximum,
    lowered by the error bound, is a lower bound of the pair's maximum, usually close to it.
    Then the clusters that :func:`surviving_clusters` keeps with that bound (the one holding
    the exact maximiser among them). The band threshold is monotone in the float32 maximum,
    so the first cluster's threshold keeps every later value that the final one can keep.

    Args:
        q32: (k, 3, 10) float32 coefficients (scaled).
        cl: The model's clusters.
        bounds: ``(low, up)`` of :func:`cluster_bounds`.
        err: ``(a, b)`` (k,) each, the screen's error bounds.
        known: ``(lower, cap)``, (k,) each or None, px: known lower bounds of the maxima, and
            values whose reaching makes a pair's maximum of no interest: a pair whose first
            cluster provably reaches its cap skips the others (its band then holds a vertex
            whose value reaches the cap, not necessarily the maximiser).
        per_product: Pairs per matrix product at most (one thread).
        per_block: Entries per block of the elementwise work (cache-sized).

    Returns:
        ``(pair, vertex)``: (E,) indices of the band entries, sorted by pair.
    """
    (low, up), (a, b), (lower, cap) = bounds, err, known
    k = q32.shape[0]
    rows = np.arange(k)
    with np.errstate(invalid="ignore"):
        top = np.argmax(np.where(np.isnan(up), np.inf, up), axis=1)
    o = np.argsort(top, kind="stable")
    first = (top[o], rows[o])
    # Values below the band threshold of a lower bound of the maximum (lowered as float32
    # values may be) are below the final threshold: not kept.
    floor_d = np.full(k, -np.inf) if lower is None else (1.0 - b) * lower - a
    seen32 = np.empty(k, np.float32)
    e1, c1, v1 = _screen_entries(
        q32, cl, first, band_threshold(floor_d, a, b), per_product, per_block, seen32
    )
    seen32[first[1]] = seen32.copy()
    with np.errstate(invalid="ignore"):
        seen = (1.0 - b) * np.sqrt(seen32.astype(np.float64)) - a
    keep = surviving_clusters(low, up, a, b, seen if lower is None else np.fmax(lower, seen))
    keep[rows, top] = False
    if cap is not None:
        keep[seen >= cap] = False
    cb, pb = np.divmod(np.flatnonzero(keep.T), k)  # cluster-major
    later = (cb, pb)
    floor = band_threshold(np.sqrt(seen32.astype(np.float64)), a, b)
    e2, c2, v2 = _screen_entries(q32, cl, later, floor, per_product, per_block)
    pair = np.r_[first[1][e1], later[1][e2]]
    clus = np.r_[first[0][e1], later[0][e2]]
    col, val = np.r_[c1, c2], np.r_[v1, v2]
    best = seen32.copy()
    np.maximum.at(best, pair, val)
    keep_e = val >= band_threshold(np.sqrt(best.astype(np.float64)), a, b)[pair]
    pair, vertex = pair[keep_e], cl.members[clus[keep_e], col[keep_e]]
    o = np.argsort(pair, kind="stable")
    return pair[o], vertex[o]
