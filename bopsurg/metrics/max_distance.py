"""The MSSD/MSPD kernel: min over symmetries of the max over vertices, by branch and bound.

For N pose pairs, S symmetries ``(R_s, t_s)`` and V vertices the definition costs N·S·V
distance evaluations (the reference: 13.5 ms per pose for MSSD with 315 symmetries and 5,000
vertices). This module returns the same numbers with far less work, using only shortcuts that
provably do not change the value:

1. **Convex hull** (MSSD only). ``x ↦ ‖(R_e x + t_e) − (R_g R_s x + R_g t_s + t_g)‖`` is convex,
   so its maximum over the vertices is attained at a vertex of their convex hull (Qhull; all
   vertices when the hull is degenerate, or when there are too few evaluations to pay for it).
   MSPD's projected distance is not convex, so MSPD evaluates all vertices.
2. **Branch and bound over symmetries.** The maximum over a subset of vertices is a lower bound
   of the maximum over all of them. Bounds are computed for every (pose, symmetry) from 4
   extreme vertices, refined with 32 for the most promising symmetries; then, per pose,
   symmetries are evaluated in full in increasing order of their bound until the next bound is
   not below the best value found. After each full evaluation the maximising vertex tightens
   the bounds of the remaining candidates. All poses advance together, in rounds (numpy
   operations over all active poses; no Python loop over poses or vertices).
3. **Final value by the reference's formula.** The search uses cheaper equivalent forms
   (``[R_e − R_g R_s | t_e − t_g'] [x; 1]``; ``U · (1 / W)`` for ``U / W``); the returned value
   is recomputed with the reference's direct difference formula at the maximising vertex of
   the winning symmetry, so it equals the reference to float64 rounding (≤ 1e-9 relative;
   absolute near 0).

Bounds are compared with a tolerance that exceeds any rounding difference between the forms
(≈ 1e-13 mm, ≈ 1e-9 px), so a symmetry is only pruned if its exact value cannot be smaller; a
near-tie can only change which of two equal (to rounding) values is returned.

**NaN/inf (MSPD).** Vertices on the camera plane (z = 0) project to inf/nan. The reference then
returns NaN when its first (identity) term is NaN (``np.max`` propagates NaN; Python's ``min``
keeps a NaN first element and never picks a later NaN) and otherwise the minimum over the
non-NaN terms (inf included). Poses whose vertices may come within 1e-6 (relative) of the
camera plane under any symmetry are therefore evaluated exhaustively (all symmetries, all
vertices, true division) and combined with exactly this rule. Which vertices give inf/NaN
there depends on the last bit of ``w``, as in the reference.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from bopsurg.metrics._pairs import PosePairs, chunks
from bopsurg.metrics.point_subsets import extreme_point_order, hull_vertex_indices

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]

EPS = float(np.finfo(np.float64).eps)

#: Vertices per (pose, symmetry) in the first, exhaustive bound stage.
GRID_POINTS = 4
#: Vertices of the later bound stages, for the candidates that survive the previous one.
LEVEL_POINTS = (32,)
#: Symmetries per pose whose bounds are refined before the first full evaluation.
FIRST_PICKS = 8
#: Doubles per temporary work block (512 KiB, cache-sized).
WORK = 1 << 16
#: MSSD computes the convex hull only for at least this many (pose, symmetry) evaluations.
HULL_MIN_EVALS = 256
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

    def __init__(self, pts: F64, X_c: F64, order: I64, R_sym: F64, t_sym: F64) -> None:
        self.X_c = np.ascontiguousarray(X_c)
        self.X_ch = _homogeneous_t(self.X_c)  # (4, H)
        self.R_sym, self.t_sym = R_sym, t_sym
        self.order = order
        self.m1 = min(GRID_POINTS, order.size)
        self.Y1 = _sym_points(R_sym, t_sym, self.X_c[order[: self.m1]])  # (4, m1·S)
        # Nested farthest-point subsets, each smaller than the full set.
        sizes = {min(m, order.size) for m in LEVEL_POINTS}
        self.levels = sorted(m for m in sizes if self.m1 < m < self.X_c.shape[0])
        self.levels_h = [np.ascontiguousarray(self.X_ch[:, order[:m]]) for m in self.levels]
        rho2 = max(np.einsum("ij,ij->i", pts, pts).max(), np.einsum("ij,ij->i", X_c, X_c).max())
        self.rho = float(np.sqrt(rho2))  # ≥ ‖x‖
        sig = np.linalg.norm(R_sym, ord=2, axis=(1, 2))
        tn = np.linalg.norm(t_sym, axis=1)
        self.rho_sym = float(np.max(sig * self.rho + tn))  # ≥ ‖R_s x + t_s‖ for all s, x
        self.sym_frob = float(np.linalg.norm(R_sym, axis=(1, 2)).max())
        self.sym_t = float(tn.max())


class _Kernel:
    """One chunk of pose pairs; subclasses define the distance (3-D or projected).

    Every ``pairs_*`` method takes flat pairs: local pose indices ``i`` and symmetry indices
    ``s`` (both (k,)). Values are squared distances, except in :meth:`final`.
    """

    c: _Common
    n: int
    s: int
    tol: F64  # (n,) pruning tolerance, distance units
    unsafe: B  # (n,) poses that need the exhaustive path

    def grid_lb(self) -> F64:
        """(n, S) squared maxima over the first ``GRID_POINTS`` vertices of ``order``."""
        raise NotImplementedError

    def pairs_lb(self, i: I64, s: I64, level: int) -> F64:
        """(k,) squared maxima over the subset ``order[:levels[level]]``."""
        raise NotImplementedError

    def pairs_full(self, i: I64, s: I64, exact: bool = False) -> tuple[F64, I64]:
        """(k,) squared maxima over all of ``X_c`` and (k,) their indices into ``X_c``.

        ``exact``: evaluate with the reference's arithmetic where the fast form could differ
        in its inf/NaN pattern (MSPD near the camera plane).
        """
        raise NotImplementedError

    def pairs_at(self, i: I64, s: I64, jj: I64) -> F64:
        """(k,) squared maxima over the vertices ``X_c[jj]``, jj (k, m)."""
        raise NotImplementedError

    def final(self, i: I64, s: I64, j: I64) -> F64:
        """(k,) distances at vertex ``X_c[j]`` by the reference's formula."""
        raise NotImplementedError


class _Kernel3D(_Kernel):
    """``‖(R_e x + t_e) − (R_g R_s x + R_g t_s + t_g)‖`` over the candidate vertices."""

    def __init__(self, c: _Common, R_e: F64, te: F64, R_g: F64, tg: F64) -> None:
        self.c = c
        self.R_e, self.te = np.ascontiguousarray(R_e), np.ascontiguousarray(te)
        self.R_g, self.tg = np.ascontiguousarray(R_g), np.ascontiguousarray(tg)
        self.n, self.s = R_e.shape[0], c.R_sym.shape[0]
        fe = np.linalg.norm(self.R_e, axis=(1, 2))
        fg = np.linalg.norm(self.R_g, axis=(1, 2))
        scale = (
            (fe + fg * c.sym_frob) * c.rho
            + fg * c.sym_t
            + np.linalg.norm(self.te, axis=1)
            + np.linalg.norm(self.tg, axis=1)
        )
        # Any two float64 evaluations of one distance differ by far less than this.
        self.tol = 64.0 * EPS * scale
        self.unsafe = np.zeros(self.n, dtype=bool)

    def grid_lb(self) -> F64:
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
        R_g = self.R_g[i]
        A = np.empty((i.size, 3, 4))
        A[:, :, :3] = self.R_e[i] - np.matmul(R_g, self.c.R_sym[s])
        t_gs = np.matmul(R_g, self.c.t_sym[s][:, :, None])[:, :, 0] + self.tg[i]
        A[:, :, 3] = self.te[i] - t_gs
        return A

    def _pairs_max(self, i: I64, s: I64, X_h: F64) -> tuple[F64, I64]:
        p = X_h.shape[1]
        A = self._diff_mats(i, s)
        val, arg = np.empty(i.size), np.empty(i.size, dtype=np.int64)
        kb = max(1, WORK // (3 * p))
        buf, sqbuf = np.empty((min(kb, i.size) * 3, p)), np.empty((min(kb, i.size), p))
        for b in chunks(i.size, kb):
            k = b.stop - b.start
            diff = np.matmul(A[b].reshape(-1, 4), X_h, out=buf[: 3 * k]).reshape(k, 3, p)
            val[b], arg[b] = _rowwise_max(np.einsum("kip,kip->kp", diff, diff, out=sqbuf[:k]))
        return val, arg

    def pairs_lb(self, i: I64, s: I64, level: int) -> F64:
        return self._pairs_max(i, s, self.c.levels_h[level])[0]

    def pairs_full(self, i: I64, s: I64, exact: bool = False) -> tuple[F64, I64]:
        return self._pairs_max(i, s, self.c.X_ch)  # finite inputs: no inf/NaN to mirror

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
    """``‖π(K, R_e, t_e, x) − π(K, R_g R_s, R_g t_s + t_g, x)‖`` over all vertices."""

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
        # Bounds on w = k3·X over all vertices and symmetries, to keep away from z = 0.
        k3 = self.K[:, 2, :]
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
        kmax = np.maximum(
            np.linalg.norm(self.K[:, 0], axis=1), np.linalg.norm(self.K[:, 1], axis=1)
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            r = scale / w_min
            # Rounding of u = U / W, relative to the magnitudes involved, with a wide margin.
            self.tol = np.where(self.unsafe, np.inf, 256.0 * EPS * kmax * r * (1.0 + k3n * r))

    def grid_lb(self) -> F64:
        c, m1, S = self.c, self.c.m1, self.s
        # K (R_g (R_s q + t_s) + t_g): rows u, v, w of the GT-sym projections of the subset.
        P_g = np.matmul(self.K, np.concatenate([self.R_g, self.tg[:, :, None]], axis=2))
        est = self.est_sub[:, :, :m1, None]  # (n, 2, m1, 1)
        out = np.empty((self.n, S))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for b in chunks(self.n, max(1, WORK // (3 * S * m1))):
                k = b.stop - b.start
                uvw = (P_g[b].reshape(k * 3, 4) @ c.Y1).reshape(k, 3, m1, S)
                uv = uvw[:, :2]
                uv *= np.divide(1.0, uvw[:, 2])[:, None]
                uv -= est[b]
                out[b] = np.einsum("kiqs,kiqs->kqs", uv, uv).max(axis=1)
        return out

    def _proj_mats(self, i: I64, s: I64) -> F64:
        """``K [R_g R_s | R_g t_s + t_g]`` per pair, as the reference builds P: (k, 3, 4)."""
        R_g = self.R_g[i]
        R_t = np.empty((i.size, 3, 4))
        R_t[:, :, :3] = np.matmul(R_g, self.c.R_sym[s])
        R_t[:, :, 3] = np.matmul(R_g, self.c.t_sym[s][:, :, None])[:, :, 0] + self.tg[i]
        result: F64 = np.matmul(self.K[i], R_t)
        return result

    def pairs_lb(self, i: I64, s: I64, level: int) -> F64:
        m = self.c.levels[level]
        X_h = self.c.levels_h[level]
        P = self._proj_mats(i, s)
        val = np.empty(i.size)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for b in chunks(i.size, max(1, WORK // (3 * m))):
                uvw = (P[b].reshape(-1, 4) @ X_h).reshape(-1, 3, m)
                uv = uvw[:, :2]
                uv *= np.divide(1.0, uvw[:, 2])[:, None]
                uv -= self.est_sub[i[b], :, :m]
                val[b] = np.einsum("kip,kip->kp", uv, uv).max(axis=1)
        return val

    def pairs_full(self, i: I64, s: I64, exact: bool = False) -> tuple[F64, I64]:
        p = self.c.X_ch.shape[1]
        # Estimate and GT-sym projection matrices, stacked so one product serves both.
        P = np.concatenate([self.P_e[i], self._proj_mats(i, s)], axis=1)  # (k, 6, 4)
        val, arg = np.empty(i.size), np.empty(i.size, dtype=np.int64)
        kb = max(1, WORK // (6 * p))
        n0 = min(kb, i.size)
        # Reused work buffers: fresh ~MB-sized temporaries per block cost page faults.
        buf, rbuf, sqbuf = np.empty((n0 * 6, p)), np.empty((n0, 2, p)), np.empty((n0, p))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for b in chunks(i.size, kb):
                k = b.stop - b.start
                uvw = np.matmul(P[b].reshape(-1, 4), self.c.X_ch, out=buf[: 6 * k])
                uvw = uvw.reshape(k, 2, 3, p)
                # u = U / W as U · (1 / W): within the tolerance, and numpy divides slowly
                # when broadcasting; the returned value is recomputed by division in final().
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

    def _dist_sq(self, i: I64, s: I64, jj: I64) -> F64:
        """(k, m) squared projection distances at vertices ``X_c[jj]`` (reference's formula)."""
        X = self.c.X_ch[:, jj]  # (4, k, m)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ue = np.einsum("kij,jkm->kim", self.P_e[i], X)
            ug = np.einsum("kij,jkm->kim", self._proj_mats(i, s), X)
            d = ue[:, :2] / ue[:, 2:3] - ug[:, :2] / ug[:, 2:3]
            result: F64 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
            return result

    def pairs_at(self, i: I64, s: I64, jj: I64) -> F64:
        result: F64 = self._dist_sq(i, s, jj).max(axis=1)
        return result

    def final(self, i: I64, s: I64, j: I64) -> F64:
        with np.errstate(invalid="ignore"):
            return np.sqrt(self._dist_sq(i, s, j[:, None])[:, 0])


def _search(k: _Kernel, g: I64, lbd: F64) -> F64:
    """Branch and bound for the poses ``g`` of a chunk, given their bounds ``lbd`` (ng, S)."""
    ng, S = lbd.shape
    rows = np.arange(ng)
    tol = k.tol[g]
    # Round 0: every pose evaluates its most promising symmetry in full, chosen by the bounds
    # of a larger subset for the few symmetries with the smallest first bounds.
    if k.c.levels and FIRST_PICKS < S:
        top = np.argpartition(lbd, FIRST_PICKS, axis=1)[:, :FIRST_PICKS]
        ci = np.repeat(rows, FIRST_PICKS)
        cs = top.reshape(-1)
        lbd[ci, cs] = np.maximum(lbd[ci, cs], np.sqrt(k.pairs_lb(g[ci], cs, 0)))
    s0 = np.argmin(lbd, axis=1)
    v, j = k.pairs_full(g, s0)
    best, win_s, win_j = np.sqrt(v), s0, j
    done = np.zeros((ng, S), dtype=bool)
    done[rows, s0] = True
    # Tighten the bounds of the surviving candidates: the maximising vertex of round 0 (near
    # symmetries tend to peak at the same vertex), then larger farthest-point subsets.
    for level in range(-1, len(k.c.levels)):
        ci, cs = np.nonzero(~done & (lbd - best[:, None] < tol[:, None]))
        if not ci.size:
            break
        sq = k.pairs_at(g[ci], cs, j[ci, None]) if level < 0 else k.pairs_lb(g[ci], cs, level)
        lbd[ci, cs] = np.maximum(lbd[ci, cs], np.sqrt(sq))
    alive = rows
    while alive.size:
        sub = np.where(done[alive], np.inf, lbd[alive])
        sn = np.argmin(sub, axis=1)
        go = sub[np.arange(alive.size), sn] - best[alive] < tol[alive]
        alive, sn = alive[go], sn[go]
        if not alive.size:
            break
        v, j = k.pairs_full(g[alive], sn)
        d = np.sqrt(v)
        done[alive, sn] = True
        imp = d < best[alive]
        ai = alive[imp]
        best[ai], win_s[ai], win_j[ai] = d[imp], sn[imp], j[imp]
        # The new maximiser bounds the other candidates of the same pose.
        ci, cs = np.nonzero(~done[alive] & (lbd[alive] - best[alive, None] < tol[alive, None]))
        if ci.size:
            rr = alive[ci]
            lbd[rr, cs] = np.maximum(lbd[rr, cs], np.sqrt(k.pairs_at(g[rr], cs, j[ci, None])))
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
        lb = k.grid_lb()[g]
        ok = np.all(np.isfinite(lb), axis=1)
        brute[g[~ok]] = True
        g, lb = g[ok], lb[ok]
        if g.size:
            out[g] = _search(k, g, np.sqrt(lb))
    brute[g[~np.isfinite(out[g])]] = True  # overflow: redo exhaustively
    b = np.flatnonzero(brute)
    if b.size:
        out[b] = _exhaustive(k, b)
    return out


def _default_chunk(n_syms: int) -> int:
    # ~16 MB of per-chunk arrays: the (pose, symmetry) bound grids and their masks.
    per_pose = 8 * (8 * n_syms + 256)
    return int(np.clip((16 << 20) // per_pose, 1, 512))


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
        X_c = pts[hull_vertex_indices(pts)]
    else:  # too few evaluations to pay for Qhull (up to ~10 ms for 5,000 vertices)
        X_c = pts
    c = _Common(pts, X_c, extreme_point_order(X_c, max(LEVEL_POINTS)), R_sym, t_sym)
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
        chunk_size: Poses per chunk (default from a ~16 MB budget).

    Returns:
        (N,) float64, px (NaN/inf where the reference gives them, see the module docstring).
    """
    # Bound subsets from extreme vertices: projected distances tend to peak there (not always,
    # so the full evaluations still cover every vertex).
    order = extreme_point_order(pts, max(LEVEL_POINTS) if R_sym.shape[0] > 1 else 1)
    c = _Common(pts, pts, order, R_sym, t_sym)
    size = chunk_size or _default_chunk(R_sym.shape[0])
    out = np.empty(pairs.n)
    for sl in chunks(pairs.n, size):
        k = _KernelProj(c, pairs.R_est[sl], pairs.t_est[sl], pairs.R_gt[sl], pairs.t_gt[sl], K[sl])
        out[sl] = _solve(k)
    return out
