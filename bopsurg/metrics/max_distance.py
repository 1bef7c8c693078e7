"""The MSSD/MSPD kernel: min over symmetries of the max over vertices, by branch and bound.

For N pose pairs, S symmetries ``(R_s, t_s)`` and V vertices the definition costs N·S·V
distance evaluations (the reference: 13.5 ms per pose for MSSD with 315 symmetries and 5,000
vertices). This module returns the same numbers with far less work, using only shortcuts that
provably do not change the value:

1. **Convex hull** (MSSD only). ``x ↦ ‖(R_e x + t_e) − (R_g R_s x + R_g t_s + t_g)‖`` is convex,
   so its maximum over the vertices is attained at a vertex of their convex hull. The hull of
   a 250-point strided sample first drops the vertices strictly inside it
   (:func:`~bopsurg.metrics.point_subsets.hull_probe`); Qhull then runs on the rest when the
   sample says the hull is small (a solid box: ~800 of 5,000 left, 99 on the hull), and is
   skipped when 30 % or more of the sample is on its hull (a thin needle: ~2,700 left; Qhull
   would cost ≈ 10 ms to halve that). All vertices when there are too few evaluations to pay
   for the probe. MSPD's projected distance is not convex, so MSPD screens all vertices (5.).
2. **Branch and bound over symmetries.** The maximum over a subset of vertices is a lower bound
   of the maximum over all of them. Bounds are computed for every (pose, symmetry) from 4
   extreme vertices; each pose evaluates its smallest bound's symmetry in full (MSPD first
   refines the 8 smallest bounds with 32 vertices, as its full evaluations cost more). The
   (pose, symmetry) pairs whose bound is below that value become a flat candidate list,
   tightened with the maximising vertex, 32 extreme vertices and (MSSD, ≥ 1,024 vertices) an
   evenly strided sample of 256; then, per pose, the candidate with the smallest bound is
   evaluated in full until no bound is below the best value found, each new maximising vertex
   tightening the bounds of the others. All poses advance together, in rounds (numpy
   operations over all active candidates; no Python loop over poses or vertices).
3. **The symmetry family.** BOP's continuous symmetries are rotations about one axis, so
   ``[R_s | t_s] = W0 + a_s E1 + b_s E2`` (detected by an SVD of the set with a residual
   check, see :func:`symmetry_family`; other sets take the generic path). MSSD: the squared
   distance of a vertex is then ``[1, a, b, a², ab, b²] · f`` with 6 coefficients per (pose,
   vertex), so the first bounds of all S symmetries are one (S × 6) matrix product. MSPD: the
   GT-symmetry projection matrix and the screen's forms (5.) of a (pose, symmetry) pair are
   a weighted sum of three per-pose matrices (their deviation from the reference's matrices
   is added to the tolerance).
4. **Quadratic form** (MSSD). ``‖D [x; 1]‖² = q · m(x)`` with the 10 entries q of ``DᵀD`` and
   the 10 monomials m(x) of the vertex, precomputed: a full evaluation is one 10-term product
   per vertex instead of a 3×4 product and a sum of squares. ``D`` is formed from the
   difference ``R_e − R_g R_s`` first, so the terms are of the size of the distance.
5. **Float32 screen** (MSPD). ``π_e(x) − π_g(x) = (N_u, N_v) / N_w`` with three quadratic
   forms of the vertex, formed in float64 after the two poses' terms cancel
   (:mod:`~bopsurg.metrics.projection_screen`). A full evaluation computes all vertices in
   float32 with an error bound computed per pair (≈ 1e-5 px on the bench) and then, in
   float64, only the vertices whose float32 distance is within twice that bound of the
   float32 maximum (usually one): the float64 maximum over all vertices, at about a third of
   the cost. From ``CLUSTER_MIN_PAIRS`` pairs on (and 640 vertices), the screen covers only
   the vertex clusters whose rigorous upper bound reaches a lower bound of the pair's maximum
   (:mod:`~bopsurg.metrics.vertex_clusters`: a fifth of the vertices on the bench), and a
   later candidate whose first cluster already exceeds the best value skips the rest. The
   first bounds (per grid vertex ``q`` one product of the rows
   ``P_g − e_q w_g`` over all symmetries, ``e_q`` the estimate's projection of ``q``) and
   the subset bounds are float32 values lowered by their error bound, so they stay bounds.
6. **Final value by the reference's formula.** The search uses these cheaper equivalent forms
   (and ``U · (1 / W)`` for ``U / W`` in MSPD's float64 fallback); the returned value is
   recomputed with the reference's direct difference formula at the maximising vertex of the
   winning symmetry, so it equals the reference to float64 rounding (≤ 1e-9 relative;
   absolute near 0).

Bounds are compared with a tolerance that exceeds any rounding difference between the forms
(MSSD in mm², from the sizes of the terms of each form; ≈ 1e-9 px for MSPD), so a symmetry is
only pruned if its exact value cannot be smaller; a near-tie can only change which of two
equal (to rounding) values is returned. Matrix products are issued in blocks of at most
``SERIAL_MACS`` multiply-adds, which OpenBLAS runs on one thread (see there). Terms too large
for float32 (coordinates beyond ~1e8 mm) take float64 instead of the screen.

**NaN/inf (MSPD).** Vertices on the camera plane (z = 0) project to inf/nan. The reference then
returns NaN when its first (identity) term is NaN (``np.max`` propagates NaN; Python's ``min``
keeps a NaN first element and never picks a later NaN) and otherwise the minimum over the
non-NaN terms (inf included). Poses whose vertices may come within 1e-6 (relative) of the
camera plane under any symmetry are therefore evaluated exhaustively (all symmetries, all
vertices, true division) and combined with exactly this rule. Which vertices give inf/NaN
there depends on the last bit of ``w``, as in the reference.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.metrics._pairs import PosePairs, chunks
from bopsurg.metrics.point_subsets import (
    extreme_point_order,
    hull_probe,
    hull_vertex_indices,
)
from bopsurg.metrics.projection_screen import (
    F32_LIMIT,
    U32,
    U64,
    ScreenVertices,
    quadric_coefficients,
    raw_term_sizes,
    screen_bounds,
    screened_max,
    shared_matmul,
)
from bopsurg.metrics.vertex_clusters import (
    VertexClusters,
    cluster_bounds,
    clustered_band,
    make_clusters,
)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]

EPS = float(np.finfo(np.float64).eps)

#: Vertices per (pose, symmetry) in the first, exhaustive bound stage.
GRID_POINTS = 4
#: Vertices of the later bound stages, for the candidates that survive the previous one.
LEVEL_POINTS = (32,)
#: MSSD's last bound stage: the extreme vertices plus an evenly strided sample of all of them,
#: this many in all (when there are at least 4 times as many). Cheap next to a full evaluation
#: and tight when many vertices are near the maximum (small, thin models).
SAMPLE_POINTS = 256
#: The extreme vertices of the bound subsets come from at most this many vertices.
EXTREME_SAMPLE = 1250
#: Doubles per temporary work block (512 KiB, cache-sized).
WORK = 1 << 16
#: Multiply-adds per matrix product at most: OpenBLAS runs such products on one thread. These
#: products are memory-bound, so threads gain little, and on a loaded machine waiting for a
#: descheduled thread costs 10-100x.
SERIAL_MACS = 1 << 19
#: Values per block of MSPD's grid bounds (float32: 1 MiB; fewer, larger blocks cost fewer
#: numpy calls than cache-sized ones save).
GRID_ELEMENTS = 1 << 18
#: Pairs per block of MSPD's float32 screen.
SCREEN_PAIRS = 32
#: Pairs per block of MSPD's bounds at given vertices.
AT_PAIRS = 1024
#: MSPD's full evaluations bound the vertex clusters first for at least this many pairs (below
#: it, the clustered screen's fixed work, a small product per cluster, outweighs its saving).
CLUSTER_MIN_PAIRS = 96
#: (Pair, cluster) entries per block of the clustered screen (float32 forms: ~256 KiB).
CLUSTER_ENTRIES = 512
#: MSPD's default chunk: bytes of (pose, symmetry) arrays and most poses. Twice MSSD's: each
#: chunk repeats MSPD's set-up (grid and cluster buffers, small per-round products), and its
#: rounds gain from more pairs per numpy call.
MSPD_CHUNK_BYTES = 32 << 20
MSPD_CHUNK_POSES = 1024
#: Vertices per block of MSSD's full evaluations.
VERTEX_BLOCK = 1280
#: MSSD computes the convex hull only for at least this many (pose, symmetry) evaluations.
HULL_MIN_EVALS = 256
#: ... and only if a probe says that at most this share of the vertices is on the hull.
HULL_MAX_SHARE = 0.3
#: Largest deviation of the symmetry set from a one-parameter family ``W0 + a E1 + b E2``
#: (relative to its largest entry) for which the bounds use that family.
FAMILY_RESIDUAL = 1e-10
#: Relative distance to the camera plane below which a pose is evaluated exhaustively.
PLANE_GUARD = 1e-6


def _homogeneous_t(x: F64) -> F64:
    """(P, 3) points as the (4, P) matrix ``[xᵀ; 1]``."""
    out = np.ones((4, x.shape[0]))
    out[:3] = x.T
    return out


def _sym_points(R_sym: F64, t_sym: F64, q: F64) -> F64:
    """``R_s q + t_s`` for every point and symmetry, as (4, m·S) homogeneous columns.

    Columns run over the symmetries fastest, so that reductions over the m points of a
    (pose, symmetry) pair run over a non-innermost axis (numpy is slow on tiny inner axes).
    """
    y = np.einsum("sij,mj->msi", R_sym, q) + t_sym[None, :, :]
    return _homogeneous_t(y.reshape(-1, 3))


def _rowwise_max(sq: F64) -> tuple[F64, I64]:
    """Row maxima of (k, p) and their column indices; the first NaN wins, as in ``np.max``."""
    j = np.argmax(sq, axis=1)
    return sq[np.arange(sq.shape[0]), j], j


#: Index pairs (a ≤ b) of the 10 monomials of a homogeneous point, and their weight in ‖D X‖².
_MONO_A, _MONO_B = np.triu_indices(4)
_MONO_W = np.where(_MONO_A == _MONO_B, 1.0, 2.0)


def _monomials(X_h: F64) -> F64:
    """The 10 products ``X_a X_b`` (a ≤ b) of homogeneous points (4, p), as (10, p) rows.

    With the matching entries of ``Dᵀ D`` (off-diagonal ones doubled, see :func:`_gram_rows`),
    ``‖D X‖² = q · monomials(X)``: one matrix product per set of (pose, symmetry) pairs.
    """
    result: F64 = X_h[_MONO_A] * X_h[_MONO_B]
    return result


def _gram_rows(diff: F64) -> F64:
    """(k, 10) coefficients ``q`` of ``‖D X‖²`` for (k, 3, 4) matrices D (see _monomials)."""
    result: F64 = np.einsum("kit,kit->kt", diff[:, :, _MONO_A], diff[:, :, _MONO_B]) * _MONO_W
    return result


def symmetry_family(R_sym: F64, t_sym: F64) -> tuple[F64, F64, F64, float] | None:
    """The symmetry set as a one-parameter family ``[R_s | t_s] = W0 + a_s E1 + b_s E2``.

    BOP's continuous symmetries are rotations about one axis: ``R_s`` and ``t_s`` are affine in
    ``(cos θ_s, sin θ_s)``, so the (S, 12) matrix of ``[R_s | t_s]`` has rank 2 after
    centring. Then a squared vertex distance is a quadratic in ``(a_s, b_s)``, and the bounds of
    all symmetries come from one small matrix product. Detected numerically (SVD), not assumed.

    Returns:
        ``(ab (S, 2), W0 (3, 4), E (2, 3, 4), residual)`` with ``residual`` the largest entry
        deviation (mm for the translations), or None when the set is not such a family
        (e.g. discrete symmetries, or fewer than 3 transforms).
    """
    S = R_sym.shape[0]
    if S < 3:
        return None
    w = np.concatenate([R_sym, t_sym[:, :, None]], axis=2).reshape(S, 12)
    w0 = w.mean(axis=0)
    u, sv, vt = np.linalg.svd(w - w0, full_matrices=False)
    ab = u[:, :2] * sv[:2]
    residual = float(np.abs(w - w0 - ab @ vt[:2]).max())
    if not residual <= FAMILY_RESIDUAL * max(1.0, float(np.abs(w).max())):
        return None
    return ab, w0.reshape(3, 4), vt[:2].reshape(2, 3, 4), residual


def _reference_min(vals: F64) -> F64:
    """Python's ``min`` over each row as the reference applies it (NaN first → NaN)."""
    filled = np.where(np.isnan(vals), np.inf, vals).min(axis=1)
    return np.where(np.isnan(vals[:, 0]), np.nan, filled)


class _Common:
    """Pose-independent data shared by all chunks of one call.

    Args:
        pts: (V, 3) all model vertices, mm.
        X_c: (H, 3) vertices of the full evaluations (hull vertices for MSSD, all for MSPD).
        order: Indices into ``X_c`` in farthest-point order; its prefixes are the bound subsets.
        R_sym: (S, 3, 3) symmetry rotations.
        t_sym: (S, 3) symmetry translations, mm.
    """

    def __init__(
        self,
        pts: F64,
        X_c: F64,
        order: I64,
        R_sym: F64,
        t_sym: F64,
        level_points: tuple[int, ...] = LEVEL_POINTS,
    ) -> None:
        self.X_c = np.ascontiguousarray(X_c)
        self.X_ch = _homogeneous_t(self.X_c)  # (4, H)
        self.R_sym, self.t_sym = R_sym, t_sym
        self.order = order
        self.m1 = min(GRID_POINTS, order.size)
        self.Y1 = _sym_points(R_sym, t_sym, self.X_c[order[: self.m1]])  # (4, m1·S)
        # Nested farthest-point subsets, each smaller than the full set.
        sizes = {min(m, order.size) for m in level_points}
        self.levels = sorted(m for m in sizes if self.m1 < m < self.X_c.shape[0])
        self.levels_h = [np.ascontiguousarray(self.X_ch[:, order[:m]]) for m in self.levels]
        rho2 = max(np.einsum("ij,ij->i", pts, pts).max(), np.einsum("ij,ij->i", X_c, X_c).max())
        self.rho = float(np.sqrt(rho2))  # ≥ ‖x‖
        tn = np.linalg.norm(t_sym, axis=1)
        self.sym_frob = float(np.linalg.norm(R_sym, axis=(1, 2)).max())
        self.sym_t = float(tn.max())
        self.family = symmetry_family(R_sym, t_sym)
        with np.errstate(over="ignore"):
            self.mono = _monomials(self.X_ch)  # (10, H)
        self.mono_finite = bool(np.all(np.isfinite(self.mono)))
        self.levels_mono = [np.ascontiguousarray(self.mono[:, order[:m]]) for m in self.levels]
        # Vertex blocks of the full evaluations: more pairs per single-threaded product and a
        # cache-sized result.
        self.mono_blocks = [
            (v.start, np.ascontiguousarray(self.mono[:, v]))
            for v in chunks(self.mono.shape[1], VERTEX_BLOCK)
        ]

    @functools.cached_property
    def x_abs(self) -> F64:
        """(4,) largest ``|x_j|`` of the homogeneous vertices (the last is 1)."""
        result: F64 = np.abs(self.X_ch).max(axis=1)
        return result

    @functools.cached_property
    def sym_abs(self) -> F64:
        """(3, 4) largest ``|[R_s | t_s]|`` entries over the symmetries."""
        result: F64 = np.abs(np.concatenate([self.R_sym, self.t_sym[:, :, None]], axis=2)).max(0)
        return result

    @functools.cached_property
    def y_abs(self) -> F64:
        """(4,) largest ``|y_j|`` of the grid's columns ``[R_s q + t_s; 1]``."""
        result: F64 = np.abs(self.Y1).max(axis=1)
        return result

    @functools.cached_property
    def levels_mono32(self) -> list[NDArray[np.float32]]:
        """MSPD's float32 monomials of the bound subsets, (10, m) each."""
        return [np.ascontiguousarray(self.screen.mono32[:, self.order[:m]]) for m in self.levels]

    @functools.cached_property
    def screen(self) -> ScreenVertices:
        """MSPD's float32 monomials of all vertices."""
        return ScreenVertices(self.X_ch)

    @functools.cached_property
    def clusters(self) -> VertexClusters | None:
        """MSPD's vertex clusters (None for small models)."""
        return make_clusters(self.X_c, self.screen.mono32) if self.screen.usable else None

    @functools.cached_property
    def rho_sym(self) -> float:
        """≥ ‖R_s x + t_s‖ for all s and x, mm (MSPD's camera-plane guard only)."""
        sig = np.linalg.norm(self.R_sym, ord=2, axis=(1, 2))
        return float(np.max(sig * self.rho + np.linalg.norm(self.t_sym, axis=1)))


class _Kernel:
    """One chunk of pose pairs; subclasses define the distance (3-D or projected).

    Every ``pairs_*`` method takes flat pairs: local pose indices ``i`` and symmetry indices
    ``s`` (both (k,)). Values are squared distances, except in :meth:`final`.
    """

    c: _Common
    n: int
    s: int
    tol: F64  # (n,) pruning tolerance, in the units of the values
    unsafe: B  # (n,) poses that need the exhaustive path
    #: Symmetries per pose whose bounds are refined before the first full evaluation.
    first_picks = 0

    def grid_lb(self) -> F64:
        """(n, S) squared maxima over the first ``GRID_POINTS`` vertices of ``order``."""
        raise NotImplementedError

    def pairs_lb(self, i: I64, s: I64, level: int) -> F64:
        """(k,) squared maxima over the subset ``order[:levels[level]]``."""
        raise NotImplementedError

    def pairs_full(
        self,
        i: I64,
        s: I64,
        exact: bool = False,
        lower: F64 | None = None,
        cap: F64 | None = None,
    ) -> tuple[F64, I64]:
        """(k,) squared maxima over all of ``X_c`` and (k,) their indices into ``X_c``.

        ``exact``: evaluate with the reference's arithmetic where the fast form could differ
        in its inf/NaN pattern (MSPD near the camera plane). ``lower``: (k,) known lower
        bounds of the maxima (MSPD: px; they may prune vertices). ``cap``: (k,) values
        above which a maximum is of no interest: a pair whose maximum provably reaches its
        cap may return any vertex whose value reaches it (MSPD).
        """
        raise NotImplementedError

    def pairs_at(self, i: I64, s: I64, jj: I64) -> F64:
        """(k,) squared maxima over the vertices ``X_c[jj]``, jj (k, m)."""
        raise NotImplementedError

    def final(self, i: I64, s: I64, j: I64) -> F64:
        """(k,) distances at vertex ``X_c[j]`` by the reference's formula."""
        raise NotImplementedError


class _Kernel3D(_Kernel):
    """``‖(R_e x + t_e) − (R_g R_s x + R_g t_s + t_g)‖`` over the candidate vertices.

    Values are squared distances (mm²) and ``tol`` is in mm², so that no square root is taken
    before the final value.
    """

    def __init__(self, c: _Common, R_e: F64, te: F64, R_g: F64, tg: F64) -> None:
        self.c = c
        self.R_e, self.te = np.ascontiguousarray(R_e), np.ascontiguousarray(te)
        self.R_g, self.tg = np.ascontiguousarray(R_g), np.ascontiguousarray(tg)
        self.n, self.s = R_e.shape[0], c.R_sym.shape[0]
        fe = np.sqrt(np.einsum("nij,nij->n", self.R_e, self.R_e))  # Frobenius norms
        fg = np.sqrt(np.einsum("nij,nij->n", self.R_g, self.R_g))
        scale = (
            (fe + fg * c.sym_frob) * c.rho
            + fg * c.sym_t
            + np.sqrt(np.einsum("ni,ni->n", self.te, self.te))
            + np.sqrt(np.einsum("ni,ni->n", self.tg, self.tg))
        )
        self.M: F64 | None = None
        fit = np.zeros(self.n)
        if c.family is not None:
            ab, w0, e12, residual = c.family
            # [R_e | t_e] − R_g [R_s | t_s] − [0 | t_g] = M0 + a_s M1 + b_s M2
            self.M = np.empty((self.n, 3, 3, 4))
            self.M[:, 0] = -np.matmul(self.R_g, w0)
            self.M[:, 0, :, :3] += self.R_e
            self.M[:, 0, :, 3] += self.te - self.tg
            self.M[:, 1:] = -np.einsum("nij,ejk->neik", self.R_g, e12)
            # the family's terms are summed separately: their sizes enter the rounding
            amax = np.abs(ab).max(axis=0)
            terms = np.linalg.norm(w0) + amax[0] * np.linalg.norm(e12[0])
            scale = scale + fg * (terms + amax[1] * np.linalg.norm(e12[1])) * (c.rho + 1.0)
            fit = fg * np.sqrt(12.0) * residual * (c.rho + 1.0)  # ≥ the family's point error
        # Any two float64 evaluations of one distance differ by far less than tau (mm); their
        # squares by less than tol (mm²).
        tau = 64.0 * EPS * scale + fit
        self.tol = tau * (2.0 * scale + tau)
        # Squared coordinates that overflow (|x| > 1e150): the exhaustive difference form.
        self.unsafe = np.full(self.n, not c.mono_finite)

    def grid_lb(self) -> F64:
        if self.M is None:
            return self._grid_lb_generic()
        c, m1, S = self.c, self.c.m1, self.s
        assert c.family is not None
        ab = c.family[0]
        phi = np.stack([np.ones(S), ab[:, 0], ab[:, 1], ab[:, 0] ** 2, ab[:, 0] * ab[:, 1]])
        phi = np.concatenate([phi, ab[None, :, 1] ** 2]).T.copy()  # (S, 6)
        X = c.X_ch[:, c.order[:m1]]
        y = np.matmul(self.M, X)  # (n, 3, 3, m1): M0 X, M1 X, M2 X
        y0, y1, y2 = y[:, 0], y[:, 1], y[:, 2]
        # ‖y0 + a y1 + b y2‖² = [1, a, b, a², ab, b²] · f
        f = np.empty((self.n, m1, 6))
        f[:, :, 0] = np.einsum("niq,niq->nq", y0, y0)
        f[:, :, 1] = 2.0 * np.einsum("niq,niq->nq", y0, y1)
        f[:, :, 2] = 2.0 * np.einsum("niq,niq->nq", y0, y2)
        f[:, :, 3] = np.einsum("niq,niq->nq", y1, y1)
        f[:, :, 4] = 2.0 * np.einsum("niq,niq->nq", y1, y2)
        f[:, :, 5] = np.einsum("niq,niq->nq", y2, y2)
        out = np.empty((self.n, S))
        phi_t = np.ascontiguousarray(phi.T)
        for b in chunks(self.n, max(1, SERIAL_MACS // (6 * S * m1))):
            k = b.stop - b.start
            out[b] = (f[b].reshape(k * m1, 6) @ phi_t).reshape(k, m1, S).max(axis=1)
        return out

    def _grid_lb_generic(self) -> F64:
        c, m1, S = self.c, self.c.m1, self.s
        P_g = np.concatenate([self.R_g, (self.tg - self.te)[:, :, None]], axis=2)  # (n, 3, 4)
        eq = np.matmul(self.R_e, c.X_c[c.order[:m1]].T)[:, :, :, None]  # (n, 3, m1, 1): R_e q
        out = np.empty((self.n, S))
        for b in chunks(self.n, max(1, WORK // (3 * S * m1))):
            k = b.stop - b.start
            # R_g (R_s q + t_s) + t_g − t_e − R_e q = GT-sym point − estimate point
            diff = (P_g[b].reshape(k * 3, 4) @ c.Y1).reshape(k, 3, m1, S)
            diff -= eq[b]
            out[b] = np.einsum("kiqs,kiqs->kqs", diff, diff).max(axis=1)
        return out

    def _diff_mats(self, i: I64, s: I64) -> F64:
        """``[R_e − R_g R_s | t_e − (R_g t_s + t_g)]`` per pair: (k, 3, 4)."""
        if self.M is not None:
            assert self.c.family is not None
            ab = self.c.family[0][s]
            m = self.M[i]
            diff: F64 = m[:, 0] + ab[:, 0, None, None] * m[:, 1] + ab[:, 1, None, None] * m[:, 2]
            return diff
        R_g = self.R_g[i]
        A = np.empty((i.size, 3, 4))
        A[:, :, :3] = self.R_e[i] - np.matmul(R_g, self.c.R_sym[s])
        t_gs = np.matmul(R_g, self.c.t_sym[s][:, :, None])[:, :, 0] + self.tg[i]
        A[:, :, 3] = self.te[i] - t_gs
        return A

    def _pairs_max(self, i: I64, s: I64, blocks: list[tuple[int, F64]]) -> tuple[F64, I64]:
        """Maxima over the vertices of ``blocks`` ((offset, (10, w) monomials) each)."""
        q = _gram_rows(self._diff_mats(i, s))
        width = max(m.shape[1] for _, m in blocks)
        kb = max(1, SERIAL_MACS // (10 * width))
        buf = np.empty((min(kb, i.size), width))
        # per block: maxima and their indices (offset included), then the best block per pair
        vals = np.empty((len(blocks), i.size))
        args = np.empty((len(blocks), i.size), dtype=np.int64)
        rows = np.arange(buf.shape[0])
        for b in chunks(i.size, kb):
            k = b.stop - b.start
            for n, (off, m) in enumerate(blocks):
                sq = np.matmul(q[b], m, out=buf[:k, : m.shape[1]])
                j = sq.argmax(axis=1)
                vals[n, b] = sq[rows[:k], j]
                args[n, b] = j + off
        if len(blocks) == 1:
            return vals[0], args[0]
        best = np.argmax(vals, axis=0)  # the first NaN wins, as in np.max
        cols = np.arange(i.size)
        return vals[best, cols], args[best, cols]

    def pairs_lb(self, i: I64, s: I64, level: int) -> F64:
        return self._pairs_max(i, s, [(0, self.c.levels_mono[level])])[0]

    def pairs_full(
        self,
        i: I64,
        s: I64,
        exact: bool = False,
        lower: F64 | None = None,
        cap: F64 | None = None,
    ) -> tuple[F64, I64]:
        if exact:  # the difference form, for coordinates whose squares overflow
            d = np.einsum("kij,jp->kip", self._diff_mats(i, s), self.c.X_ch)
            return _rowwise_max(np.einsum("kip,kip->kp", d, d))
        return self._pairs_max(i, s, self.c.mono_blocks)

    def pairs_at(self, i: I64, s: I64, jj: I64) -> F64:
        d = np.einsum("kij,jkm->kim", self._diff_mats(i, s), self.c.X_ch[:, jj])
        result: F64 = np.einsum("kim,kim->km", d, d).max(axis=1)
        return result

    def final(self, i: I64, s: I64, j: I64) -> F64:
        # The reference's formula: transform both, subtract, norm (sqrt of the summed squares).
        R_g = self.R_g[i]
        R_gs = np.matmul(R_g, self.c.R_sym[s])
        t_gs = np.matmul(R_g, self.c.t_sym[s][:, :, None])[:, :, 0] + self.tg[i]
        x = self.c.X_c[j][:, :, None]
        p_est = np.matmul(self.R_e[i], x)[:, :, 0] + self.te[i]
        p_gt = np.matmul(R_gs, x)[:, :, 0] + t_gs
        d = p_est - p_gt
        result: F64 = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
        return result


class _KernelProj(_Kernel):
    """``‖π(K, R_e, t_e, x) − π(K, R_g R_s, R_g t_s + t_g, x)‖`` over all vertices (px).

    Full evaluations screen all vertices in float32 with a rigorous error bound and evaluate
    the few that may hold the maximum in float64 (:mod:`~bopsurg.metrics.projection_screen`).
    With a symmetry family, the GT-symmetry projection matrices and the screen's quadratic
    forms are affine in ``(a_s, b_s)``: per pair a weighted sum of three per-pose matrices.
    """

    first_picks = 8

    def __init__(self, c: _Common, R_e: F64, te: F64, R_g: F64, tg: F64, K: F64) -> None:
        self.c = c
        self.R_g, self.tg = np.ascontiguousarray(R_g), np.ascontiguousarray(tg)
        self.K = np.ascontiguousarray(K)
        self.n, self.s = R_e.shape[0], c.R_sym.shape[0]
        # The estimate's projection matrix as the reference builds it: P = K [R | t].
        self.P_e = np.matmul(self.K, np.concatenate([R_e, te[:, :, None]], axis=2))
        # Estimate projections of the bound-subset vertices (the others: on the fly).
        with np.errstate(divide="ignore", invalid="ignore"):
            uvw = np.matmul(self.P_e, c.X_ch[:, c.order])
            self.est_sub = uvw[:, :2] / uvw[:, 2:3]  # (n, 2, |order|)
        self._guard(R_e, te)
        self.KR_g = np.matmul(self.K, self.R_g)
        self.Kt_g = np.einsum("nij,nj->ni", self.K, self.tg)
        # |P_g,s| ≤ |K R_g| max_s |[R_s | t_s]| + |[0 | K t_g]| entrywise, for every s.
        abs_g = shared_matmul(np.abs(self.KR_g), c.sym_abs)
        abs_g[:, :, 3] += np.abs(self.Kt_g)
        self.B: F64 | None = None  # (n, 3, 3, 4): P_g,s = B0 + a_s B1 + b_s B2
        if c.family is not None:
            # the family's terms, summed in float64, are as large as |B0| + |a| |B1| + |b| |B2|
            abs_g = np.maximum(abs_g, self._family_mats(abs_g))
        self.rows_e = shared_matmul(np.abs(self.P_e), c.x_abs)  # (n, 3)
        self.rows_g = shared_matmul(abs_g, c.x_abs)
        self.C: F64 | None = None  # (n, 3, 3, 10): the screen's forms, likewise
        # The screen's forms over w_min² (≤ |w_e w_g|): |N_w| ≥ 1, sizes near the distances.
        self.scale = 1.0 / np.where(self.unsafe, 1.0, self.w_min) ** 2
        if self.B is not None:
            # one family term at a time: a third of the temporaries, reused from the heap
            self.C = np.empty((self.n, 3, 3, 10))
            for j in range(3):
                q = quadric_coefficients(self.P_e, self.B[:, j])
                np.multiply(q, self.scale[:, None, None], out=self.C[:, j])
        self.t_raw = raw_term_sizes(self.rows_e, self.rows_g) * self.scale[:, None]

    def _guard(self, R_e: F64, te: F64) -> None:
        """``unsafe`` (near the camera plane), ``w_min`` (≤ |w| everywhere) and ``tol``."""
        c, k3 = self.c, self.K[:, 2, :]
        k3n = np.linalg.norm(k3, axis=1)
        ge = np.linalg.norm(np.einsum("nji,nj->ni", R_e, k3), axis=1) * c.rho
        gg = np.linalg.norm(np.einsum("nji,nj->ni", self.R_g, k3), axis=1) * c.rho_sym
        we, wg = np.einsum("ni,ni->n", k3, te), np.einsum("ni,ni->n", k3, self.tg)
        w_min = np.minimum(np.maximum(we - ge, -we - ge), np.maximum(wg - gg, -wg - gg))
        scale = (
            np.linalg.norm(te, axis=1)
            + np.linalg.norm(self.tg, axis=1)
            + np.linalg.norm(R_e, axis=(1, 2)) * c.rho
            + np.linalg.norm(self.R_g, axis=(1, 2)) * c.rho_sym
        )
        self.unsafe = ~(w_min > PLANE_GUARD * k3n * scale)
        self.w_min = w_min
        kmax = np.maximum(
            np.linalg.norm(self.K[:, 0], axis=1), np.linalg.norm(self.K[:, 1], axis=1)
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            r = scale / w_min
            # Rounding of u = U / W, relative to the magnitudes involved, with a wide margin.
            self.tol = np.where(self.unsafe, np.inf, 256.0 * EPS * kmax * r * (1.0 + k3n * r))

    def _family_mats(self, abs_g: F64) -> F64:
        """``B`` of the family form and its deviation from the reference's matrices in ``tol``.

        Returns the (n, 3, 4) entrywise bound ``|B0| + max|a| |B1| + max|b| |B2|``.
        """
        assert self.c.family is not None
        ab, w0, e12, residual = self.c.family
        self.B = np.empty((self.n, 3, 3, 4))
        self.B[:, 0] = np.matmul(self.KR_g, w0)
        self.B[:, 0, :, 3] += self.Kt_g
        self.B[:, 1:] = np.einsum("nij,ejk->neik", self.KR_g, e12)
        # |P_fam − P_ref| entrywise: the fit residual and the rounding of both sums.
        amax = np.abs(ab).max(axis=0)
        terms = np.abs(w0) + amax[0] * np.abs(e12[0]) + amax[1] * np.abs(e12[1])
        abs_fam = shared_matmul(np.abs(self.KR_g), terms)
        abs_fam[:, :, 3] += np.abs(self.Kt_g)
        dev = shared_matmul(np.abs(self.KR_g), residual + 8.0 * EPS * terms) + 8.0 * EPS * abs_g
        d = shared_matmul(dev, self.c.x_abs)  # (n, 3): rows u, v, w over all vertices
        with np.errstate(divide="ignore", invalid="ignore"):
            rows = shared_matmul(np.maximum(abs_g, abs_fam), self.c.x_abs)
            u_max = (rows[:, 0] + rows[:, 1]) / self.w_min  # ≥ |u| + |v| of the GT points
            fit = 2.0 * (d[:, 0] + d[:, 1] + u_max * d[:, 2]) / (self.w_min - d[:, 2])
        self.tol = np.where(fit >= 0.0, self.tol + fit, np.inf)
        return abs_fam

    def grid_lb(self) -> F64:
        """Bounds over the first ``GRID_POINTS`` vertices, in float32 lowered by its error (px).

        Per grid vertex ``q`` one product gives ``U − e_u W``, ``V − e_v W`` and ``W`` for all
        symmetries (``e`` the estimate's projection of ``q``): ``d² = ((U − e_u W)² +
        (V − e_v W)²) / W²``.
        """
        rows, a, b = self._grid_rows()
        if np.all(shared_matmul(np.abs(rows), self.c.y_abs) < F32_LIMIT):
            return self._grid_max(rows, np.float32, a, b)
        # float64 throughout: its rounding is within tol, as for the other bounds
        return self._grid_max(rows, np.float64, np.zeros(self.n), np.zeros(self.n))

    def _grid_rows(self) -> tuple[F64, F64, F64]:
        """The grid's rows ``[P_g0 − e_u P_g2; P_g1 − e_v P_g2; P_g2]`` (n, m1, 3, 4), and the
        error bound ``(a, b)`` (n,) each of their float32 distances (``|d₃₂ − d| ≤ a + b d``)."""
        c, m1 = self.c, self.c.m1
        P_g = np.matmul(self.K, np.concatenate([self.R_g, self.tg[:, :, None]], axis=2))
        e = np.moveaxis(self.est_sub[:, :, :m1], 1, 2)  # (n, m1, 2)
        rows = np.repeat(P_g[:, None], m1, axis=1)
        rows[:, :, :2] -= e[:, :, :, None] * P_g[:, None, 2:3, :]
        # Per (pose, q): float32 rounding of the 4-term products (inputs included) and float64
        # rounding of forming the rows, as in projection_screen.screen_bounds.
        raw = shared_matmul(np.abs(P_g), c.y_abs)  # (n, 3)
        err = 8.0 * U32 * shared_matmul(np.abs(rows), c.y_abs)  # (n, m1, 3)
        err[:, :, :2] += 8.0 * U64 * (raw[:, None, :2] + np.abs(e) * raw[:, None, 2:])
        err[:, :, 2] += 8.0 * U64 * raw[:, None, 2]
        w_min = np.where(self.unsafe, 1.0, self.w_min)[:, None]  # ≤ |W| (safe poses)
        ew = np.minimum(err[:, :, 2], 0.5 * w_min)
        a = ((err[:, :, 0] + err[:, :, 1]) / (w_min - ew)).max(axis=1)
        a[np.any(err[:, :, 2] >= 0.5 * w_min, axis=1)] = np.inf  # no useful bound
        b = (ew / (w_min - ew)).max(axis=1) + 3.0 * U32
        return rows, a, b

    def _grid_max(self, rows: F64, dt: type[np.floating[Any]], a: F64, b: F64) -> F64:
        """(n, S) maxima over the grid vertices in ``dt`` lowered by ``a + b d`` (float64, px).

        The square root and the lowering run in ``dt`` on each block while it is in cache:
        ``b + 8u`` and ``a`` rounded up cover their rounding (the result is clipped at 0).
        """
        c, m1, S = self.c, self.c.m1, self.s
        cols = [np.ascontiguousarray(c.Y1[:, q * S : (q + 1) * S], dtype=dt) for q in range(m1)]
        rows_t = np.moveaxis(rows.astype(dt), 0, 2)  # (m1, 3, n, 4)
        out = np.empty((self.n, S))
        u = float(np.finfo(dt).eps) / 2.0
        scale = (1.0 - (b + 8.0 * u)).astype(dt)
        shift = np.where(a > 0.0, a * (1.0 + 4.0 * u), 0.0).astype(dt)  # ≥ a after rounding
        nb = max(1, min(self.n, GRID_ELEMENTS // (3 * S * m1)))
        # Work buffers, one cache-sized block of poses: products (m1, 3, k, S) in the order
        # that makes each of u, v, w a contiguous block, then elementwise.
        buf = np.empty(m1 * 3 * nb * S, dt)
        sq_buf, tmp_buf = np.empty(m1 * nb * S, dt), np.empty(m1 * nb * S, dt)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for blk in chunks(self.n, nb):
                k = blk.stop - blk.start
                f = buf[: m1 * 3 * k * S].reshape(m1, 3, k, S)
                for q in range(m1):
                    a_q = np.ascontiguousarray(rows_t[q, :, blk]).reshape(3 * k, 4)
                    np.matmul(a_q, cols[q], out=f[q].reshape(3 * k, S))
                sq = sq_buf[: m1 * k * S].reshape(m1, k, S)
                tmp = tmp_buf[: m1 * k * S].reshape(m1, k, S)
                np.multiply(f[:, 0], f[:, 0], out=sq)
                np.multiply(f[:, 1], f[:, 1], out=tmp)
                np.add(sq, tmp, out=sq)
                np.multiply(f[:, 2], f[:, 2], out=tmp)
                np.divide(sq, tmp, out=sq)
                o = np.max(sq, axis=0, out=tmp[0])
                np.sqrt(o, out=o)
                np.multiply(o, scale[blk, None], out=o)
                np.subtract(o, shift[blk, None], out=o)
                np.maximum(o, 0.0, out=out[blk])  # float64: exact
        return out

    def _gt_mats(self, i: I64, s: I64) -> F64:
        """``P_g,s`` per pair for the bounds (the family form when there is one): (k, 3, 4)."""
        if self.B is None:
            return self._proj_mats(i, s)
        assert self.c.family is not None
        ab = self.c.family[0][s]
        m = self.B[i]
        P: F64 = m[:, 0] + ab[:, 0, None, None] * m[:, 1] + ab[:, 1, None, None] * m[:, 2]
        return P

    def _coeffs(self, i: I64, s: I64) -> F64:
        """The screen's scaled quadratic forms per pair: (k, 3, 10)."""
        if self.C is None:
            q = quadric_coefficients(self.P_e[i], self._proj_mats(i, s))
            result: F64 = q * self.scale[i, None, None]
            return result
        assert self.c.family is not None
        ab = self.c.family[0][np.ascontiguousarray(s)]
        m = self.C[np.ascontiguousarray(i)]
        # m0 + a m1 + b m2 (in this order), in place: fewer temporaries
        q = np.multiply(m[:, 1], ab[:, 0, None, None])
        q += m[:, 0]
        q += np.multiply(m[:, 2], ab[:, 1, None, None], out=m[:, 1])
        return q

    def _proj_mats(self, i: I64, s: I64) -> F64:
        """``K [R_g R_s | R_g t_s + t_g]`` per pair, as the reference builds P: (k, 3, 4)."""
        R_g = self.R_g[i]
        R_t = np.empty((i.size, 3, 4))
        R_t[:, :, :3] = np.matmul(R_g, self.c.R_sym[s])
        R_t[:, :, 3] = np.matmul(R_g, self.c.t_sym[s][:, :, None])[:, :, 0] + self.tg[i]
        result: F64 = np.matmul(self.K[i], R_t)
        return result

    def pairs_lb(self, i: I64, s: I64, level: int) -> F64:
        # float32 forms over the subset, lowered by their error bound; in cache-sized blocks
        # of pairs (the forms of all pairs at once would be MB-sized temporaries).
        mono = self.c.levels_mono32[level]
        m = mono.shape[1]
        val = np.empty(i.size)
        for blk in chunks(i.size, max(1, SERIAL_MACS // (30 * m))):
            ib, sb = i[blk], s[blk]
            q = self._coeffs(ib, sb)
            a, b, ok = screen_bounds(q, self.t_raw[ib], self.c.screen.mono_max)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # ok is false
                # (m, 3, k): the pairs innermost, so the maximum over the vertices runs
                # across rows (the subset's rows are too short for a fast reduction)
                q32 = np.empty((3, ib.size, 10), np.float32)
                np.copyto(q32, q.transpose(1, 0, 2), casting="same_kind")
                f = (mono.T @ q32.reshape(-1, 10).T).reshape(m, 3, -1)
                d2 = np.square(f[:, 0])
                d2 += np.square(f[:, 1])
                d2 /= np.square(f[:, 2])
                d = np.sqrt(d2.max(axis=0).astype(np.float64))
                v = np.maximum(d * (1.0 - b) - a, 0.0)
            if not (ok.all() and self.c.screen.usable):
                bad = np.flatnonzero(~ok) if self.c.screen.usable else np.arange(ib.size)
                v[bad] = self._lb_f64(ib[bad], sb[bad], level)
            val[blk] = v
        return val

    def _lb_f64(self, i: I64, s: I64, level: int) -> F64:
        m = self.c.levels[level]
        X_h = self.c.levels_h[level]
        P = self._gt_mats(i, s)
        val = np.empty(i.size)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for b in chunks(i.size, max(1, WORK // (3 * m))):
                uvw = (P[b].reshape(-1, 4) @ X_h).reshape(-1, 3, m)
                uv = uvw[:, :2]
                uv *= np.divide(1.0, uvw[:, 2])[:, None]
                uv -= self.est_sub[i[b], :, :m]
                val[b] = np.einsum("kip,kip->kp", uv, uv).max(axis=1)
        return np.sqrt(val)

    def pairs_full(
        self,
        i: I64,
        s: I64,
        exact: bool = False,
        lower: F64 | None = None,
        cap: F64 | None = None,
    ) -> tuple[F64, I64]:
        if exact:
            v, j = self._full_f64(i, s, exact=True)
            return np.sqrt(v), j
        screen = self.c.screen
        q = self._coeffs(i, s)
        a, b, ok = screen_bounds(q, self.t_raw[i], screen.mono_max)
        ok &= screen.usable
        val, arg = np.empty(i.size), np.empty(i.size, dtype=np.int64)
        if not ok.all():
            bad = np.flatnonzero(~ok)
            val[bad], arg[bad] = self._full_f64(i[bad], s[bad])
        g = np.flatnonzero(ok)
        if g.size:
            known = [None if x is None else x[g] for x in (lower, cap)]
            bp, bj = self._band(q[g], a[g], b[g], *known)
            # The band in float64: the maximum over it is the maximum over all vertices.
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                sq = self._sq_flat(i[g][bp], s[g][bp], bj, reference=False)
            val[g], arg[g] = _segment_max(bp, sq, bj, g.size)
        return np.sqrt(val), arg

    def _band(self, q: F64, a: F64, b: F64, lower: F64 | None, cap: F64 | None) -> tuple[I64, I64]:
        """The float32 screen's band (pair, vertex) of the pairs with forms ``q`` (k, 3, 10):
        of the clusters that may hold the maximum (enough pairs), else of all vertices."""
        cl, q32 = self.c.clusters, q.astype(np.float32)
        if cl is not None and q.shape[0] >= CLUSTER_MIN_PAIRS:
            bounds = cluster_bounds(q, q32, cl, max(1, SERIAL_MACS // (10 * cl.c)))
            per = max(1, SERIAL_MACS // (10 * cl.m))
            return clustered_band(q32, cl, bounds, (a, b), (lower, cap), per, CLUSTER_ENTRIES)
        kb = max(1, SERIAL_MACS // (30 * self.c.screen.v))
        return screened_max(q32, self.c.screen, a, b, kb, SCREEN_PAIRS)

    def _full_f64(self, i: I64, s: I64, exact: bool = False) -> tuple[F64, I64]:
        """Maxima over all vertices in float64 (``exact``: true division, as the reference)."""
        p = self.c.X_ch.shape[1]
        # Estimate and GT-sym projection matrices, stacked so one product serves both.
        P = np.concatenate([self.P_e[i], self._proj_mats(i, s)], axis=1)  # (k, 6, 4)
        val, arg = np.empty(i.size), np.empty(i.size, dtype=np.int64)
        kb = max(1, SERIAL_MACS // (24 * p))
        n0 = min(kb, i.size)
        # Reused work buffers: fresh ~MB-sized temporaries per block cost page faults.
        buf, rbuf, sqbuf = np.empty((n0 * 6, p)), np.empty((n0, 2, p)), np.empty((n0, p))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for b in chunks(i.size, kb):
                k = b.stop - b.start
                uvw = np.matmul(P[b].reshape(-1, 4), self.c.X_ch, out=buf[: 6 * k])
                uvw = uvw.reshape(k, 2, 3, p)
                uv = uvw[:, :, :2]
                if exact:  # U / W as the reference: same inf/NaN where W is (near) 0
                    np.divide(uv, uvw[:, :, 2:3], out=uv)
                else:
                    w_inv = np.divide(1.0, uvw[:, :, 2], out=rbuf[:k])
                    np.multiply(uv, w_inv[:, :, None], out=uv)
                d = uv[:, 0]
                np.subtract(d, uv[:, 1], out=d)  # estimate − GT-sym, as the reference
                val[b], arg[b] = _rowwise_max(np.einsum("kip,kip->kp", d, d, out=sqbuf[:k]))
        return val, arg

    def _sq_flat(self, i: I64, s: I64, j: I64, reference: bool = True) -> F64:
        """(k,) squared projection distances at vertices ``X_c[j]`` (the reference's formula;
        ``reference=False``: with the bounds' GT-symmetry matrices)."""
        P_g = self._proj_mats(i, s) if reference else self._gt_mats(i, s)
        return self._dist_sq(i, P_g, j[:, None])[:, 0]

    def _dist_sq(self, i: I64, P_g: F64, jj: I64) -> F64:
        """(k, m) squared projection distances at vertices ``X_c[jj]``, jj (k, m)."""
        X = np.take(self.c.X_ch, jj.T, axis=1)  # (4, m, k): pairs on the long inner axis
        ue, ug = _apply(self.P_e[i], X), _apply(P_g, X)
        d = ue[:2] / ue[2] - ug[:2] / ug[2]
        result: F64 = (d[0] * d[0] + d[1] * d[1]).T
        return result

    def pairs_at(self, i: I64, s: I64, jj: I64) -> F64:
        # in blocks of pairs: their temporaries are reused from the heap, not fresh pages
        val = np.empty(i.size)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for b in chunks(i.size, AT_PAIRS):
                sq = self._dist_sq(i[b], self._gt_mats(i[b], s[b]), jj[b])
                np.sqrt(sq.max(axis=1), out=val[b])
        return val

    def final(self, i: I64, s: I64, j: I64) -> F64:
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            return np.sqrt(self._sq_flat(i, s, j))


def _apply(P: F64, X: F64) -> F64:
    """``P_k X[:, :, k]`` per k: (k, 3, 4) matrices on (4, m, k) points, (3, m, k).

    Four broadcast multiply-adds (summed in column order, as a dot product) over arrays with
    the pairs innermost: faster than einsum or a stacked matmul of tiny matrices.
    """
    p_t = np.ascontiguousarray(P.transpose(1, 2, 0))[:, :, None, :]  # (3, 4, 1, k)
    out: F64 = p_t[:, 0] * X[0]
    for c in range(1, 4):
        out += p_t[:, c] * X[c]
    return out


def _segment_max(seg: I64, vals: F64, idx: I64, m: int) -> tuple[F64, I64]:
    """Per segment ``0..m-1`` of the sorted ``seg``: the largest value and its ``idx``.

    A non-finite value (overflow; not expected where the float32 screen is usable) wins its
    segment, as NaN in ``np.max``, so that the final value is non-finite and the pose is
    redone exhaustively. An empty segment (cannot happen: a band holds its float32
    maximiser) gets NaN.
    """
    key = np.where(np.isfinite(vals), -vals, -np.inf)
    o = np.lexsort((key, seg))
    seg, vals, idx = seg[o], vals[o], idx[o]
    first = np.r_[True, seg[1:] != seg[:-1]]
    val, arg = np.full(m, np.nan), np.zeros(m, dtype=np.int64)
    val[seg[first]], arg[seg[first]] = vals[first], idx[first]
    return val, arg


def _nonzero2d(mask: B) -> tuple[I64, I64]:
    """``np.nonzero`` of a 2-D mask (same order), several times faster on wide rows."""
    rows, cols = np.divmod(np.flatnonzero(mask), mask.shape[1])
    return rows, cols


def _search(k: _Kernel, g: I64, lb: F64) -> F64:
    """Branch and bound for the poses ``g`` of a chunk, given their bounds ``lb`` (ng, S).

    Values and bounds are in the kernel's units (squared for MSSD). After the first full
    evaluation per pose, only the (pose, symmetry) candidates whose bound is below the best
    value are kept, as a flat list: later rounds never touch the (ng, S) grid.
    """
    ng, S = lb.shape
    rows = np.arange(ng)
    tol = k.tol[g]
    if k.first_picks and k.c.levels and k.first_picks < S:
        # Round 0's symmetry is chosen by the bounds of a larger subset for the few smallest
        # first bounds (worth it when a full evaluation is expensive: MSPD).
        kth = np.partition(lb, k.first_picks - 1, axis=1)[:, k.first_picks - 1]
        ci, cs = _nonzero2d(lb <= kth[:, None])
        lb[ci, cs] = np.maximum(lb[ci, cs], k.pairs_lb(g[ci], cs, 0))
    win_s = np.argmin(lb, axis=1)
    best, win_j = k.pairs_full(g, win_s, lower=lb[rows, win_s] - tol)
    lb[rows, win_s] = np.inf
    ci, cs = _nonzero2d(lb < (best + tol)[:, None])
    clb = lb[ci, cs]
    # Tighten: the maximising vertex of round 0 (near symmetries tend to peak at the same
    # vertex), then larger farthest-point subsets.
    for level in range(-1, len(k.c.levels)):
        if not ci.size:
            break
        at_j = level < 0
        clb = np.maximum(
            clb, k.pairs_at(g[ci], cs, win_j[ci, None]) if at_j else k.pairs_lb(g[ci], cs, level)
        )
        keep = clb - best[ci] < tol[ci]
        ci, cs, clb = ci[keep], cs[keep], clb[keep]
    j_new = np.empty(ng, dtype=np.int64)
    while ci.size:
        # Per pose, the candidate with the smallest bound is evaluated in full.
        o = np.lexsort((clb, ci))
        ci, cs, clb = ci[o], cs[o], clb[o]
        first = np.r_[True, ci[1:] != ci[:-1]]
        fi, fs = ci[first], cs[first]
        # a candidate that reaches best + tol cannot win: its exact maximum is not needed
        v, j = k.pairs_full(g[fi], fs, lower=clb[first] - tol[fi], cap=best[fi] + tol[fi])
        imp = v < best[fi]
        best[fi[imp]], win_s[fi[imp]], win_j[fi[imp]] = v[imp], fs[imp], j[imp]
        ci, cs, clb = ci[~first], cs[~first], clb[~first]
        # The new maximiser bounds the other candidates of the same pose.
        j_new[fi] = j
        clb = np.maximum(clb, k.pairs_at(g[ci], cs, j_new[ci, None]))
        keep = clb - best[ci] < tol[ci]
        ci, cs, clb = ci[keep], cs[keep], clb[keep]
    return k.final(g, win_s, win_j)


def _exhaustive(k: _Kernel, b: I64) -> F64:
    """All symmetries of the poses ``b``, combined with the reference's ``min`` semantics."""
    out = np.empty(b.size)
    for sl in chunks(b.size, max(1, 4096 // k.s)):  # bounded pair arrays
        bb = b[sl]
        i = np.repeat(bb, k.s)
        s = np.tile(np.arange(k.s), bb.size)
        j = k.pairs_full(i, s, exact=True)[1]
        out[sl] = _reference_min(k.final(i, s, j).reshape(bb.size, k.s))
    return out


def _solve(k: _Kernel) -> F64:
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # inf/NaN handled here
        return _solve_chunk(k)


def _solve_chunk(k: _Kernel) -> F64:
    out = np.full(k.n, np.nan)
    if k.n == 0:
        return out
    brute = k.unsafe.copy()
    g = np.flatnonzero(~brute)
    if k.s == 1:  # no symmetry: one full evaluation per pose
        s = np.zeros(g.size, dtype=np.int64)
        out[g] = k.final(g, s, k.pairs_full(g, s)[1])
    elif g.size:
        lb = k.grid_lb()
        if g.size < k.n:
            lb = lb[g]
        ok = np.isfinite(lb.max(axis=1))  # NaN and inf both reach the row maximum
        if not ok.all():
            brute[g[~ok]] = True
            g, lb = g[ok], lb[ok]
        if g.size:
            out[g] = _search(k, g, lb)
    brute[g[~np.isfinite(out[g])]] = True  # overflow: redo exhaustively
    b = np.flatnonzero(brute)
    if b.size:
        out[b] = _exhaustive(k, b)
    return out


def _bound_order(pts: F64, m: int) -> I64:
    """Indices of up to ``m`` extreme vertices for the bound subsets, farthest-point ordered.

    Any subset gives valid bounds; above ``EXTREME_SAMPLE`` vertices the extreme points are
    taken from an evenly strided sample (a fraction of the cost, nearly as extreme).
    """
    step = -(-pts.shape[0] // EXTREME_SAMPLE)
    result: I64 = np.arange(0, pts.shape[0], step)[extreme_point_order(pts[::step], m)]
    return result


def _default_chunk(n_syms: int, budget: int = 16 << 20, most: int = 512) -> int:
    # ~budget bytes of per-chunk arrays: the (pose, symmetry) bound grids and their masks.
    per_pose = 8 * (8 * n_syms + 256)
    return int(np.clip(budget // per_pose, 1, most))


def min_max_distance_3d(
    pairs: PosePairs,
    pts: F64,
    R_sym: F64,
    t_sym: F64,
    *,
    candidates: F64 | None = None,
    chunk_size: int | None = None,
) -> F64:
    """MSSD kernel: ``min_s max_x ‖(R_e x + t_e) − (R_g R_s x + R_g t_s + t_g)‖``.

    Args:
        pairs: N pose pairs (mm).
        pts: (V, 3) float64 model vertices, mm.
        R_sym: (S, 3, 3) float64 symmetry rotations.
        t_sym: (S, 3) float64 symmetry translations, mm.
        candidates: (H, 3) float64 subset of ``pts`` that contains the vertices of their
            convex hull, e.g. :func:`~bopsurg.metrics.point_subsets.hull_vertices` (default:
            the hull when there are enough evaluations to pay for it, else all of ``pts``).
        chunk_size: Poses per chunk (default from a ~16 MB budget).

    Returns:
        (N,) float64, mm.
    """
    if candidates is not None:
        X_c = candidates
    elif pairs.n * min(R_sym.shape[0], 2) >= HULL_MIN_EVALS:
        cand, share = hull_probe(pts)
        X_c = pts[cand]
        if share <= HULL_MAX_SHARE:  # a small hull: Qhull pays for itself
            X_c = X_c[hull_vertex_indices(X_c)]
    else:  # too few evaluations to pay for the probe
        X_c = pts
    order = _bound_order(X_c, max(LEVEL_POINTS))
    h = X_c.shape[0]
    if h >= 4 * SAMPLE_POINTS:
        sample = np.arange(0, h, -(-h // (SAMPLE_POINTS - order.size)), dtype=np.int64)
        order = np.concatenate([order, np.setdiff1d(sample, order)])
    c = _Common(pts, X_c, order, R_sym, t_sym, (*LEVEL_POINTS, order.size))
    size = chunk_size or _default_chunk(R_sym.shape[0])
    out = np.empty(pairs.n)
    for sl in chunks(pairs.n, size):
        k = _Kernel3D(c, pairs.R_est[sl], pairs.t_est[sl], pairs.R_gt[sl], pairs.t_gt[sl])
        out[sl] = _solve(k)
    return out


def min_max_distance_proj(
    pairs: PosePairs,
    K: F64,
    pts: F64,
    R_sym: F64,
    t_sym: F64,
    *,
    chunk_size: int | None = None,
) -> F64:
    """MSPD kernel: ``min_s max_x ‖π(K, R_e, t_e, x) − π(K, R_g R_s, R_g t_s + t_g, x)‖``.

    Args:
        pairs: N pose pairs (mm).
        K: (N, 3, 3) float64 camera matrices.
        pts: (V, 3) float64 model vertices, mm.
        R_sym: (S, 3, 3) float64 symmetry rotations.
        t_sym: (S, 3) float64 symmetry translations, mm.
        chunk_size: Poses per chunk (default from a ~32 MB budget).

    Returns:
        (N,) float64, px (NaN/inf where the reference gives them, see the module docstring).
    """
    # Bound subsets from extreme vertices: projected distances tend to peak there (not always,
    # so the full evaluations still cover every vertex).
    order = _bound_order(pts, max(LEVEL_POINTS) if R_sym.shape[0] > 1 else 1)
    c = _Common(pts, pts, order, R_sym, t_sym)
    size = chunk_size or _default_chunk(R_sym.shape[0], MSPD_CHUNK_BYTES, MSPD_CHUNK_POSES)
    out = np.empty(pairs.n)
    for sl in chunks(pairs.n, size):
        k = _KernelProj(c, pairs.R_est[sl], pairs.t_est[sl], pairs.R_gt[sl], pairs.t_gt[sl], K[sl])
        out[sl] = _solve(k)
    return out
