"""MSPD's projected distances in float32 with a rigorous error bound, then float64 where it counts.

For a pose pair with projection matrices ``P_e`` and ``P_g`` (3 × 4, rows ``a, b, w``) and a
homogeneous vertex ``x``, the projected difference is

    ``π_e(x) − π_g(x) = (N_u, N_v) / N_w``,  ``N_u = (a_e·x)(w_g·x) − (a_g·x)(w_e·x)``,
    ``N_v`` likewise with ``b``,  ``N_w = (w_e·x)(w_g·x)``,

three quadratic forms of ``x``: dot products of 10 coefficients with the 10 monomials of the
vertex (:func:`quadric_coefficients`). Their coefficients are formed in float64, after the
cancellation between the two poses, so the float32 evaluation of all vertices (one product,
then ``(N_u² + N_v²) / N_w²``) is accurate to a bound computed per pair
(:func:`screen_bounds`): with ``T = Σ|c_t| max|m_t|`` (the sizes of the terms) each form is
within ``16 u T`` (``u = 2⁻²⁴``: rounding of the coefficients, the monomials and a 10-term
sum, with margin), and ``|d₃₂ − d| ≤ a + b·max(d, d₃₂)`` for the distance ``d`` in px.

:func:`screened_max` evaluates all vertices in float32 and returns the *band*: every vertex
whose float32 distance is close enough to the float32 maximum that it could be the exact
maximiser. The caller evaluates only those in float64 (the reference's formula): their
maximum is the float64 maximum over all vertices. The band is a handful of vertices unless
the distances are near 0 (then the error bound, which scales with the cancelled terms, is
near 0 as well).

The forms are divided by a per-pair scale (``w_min²``, a lower bound of ``|N_w|``) so that
they stay far from float32's range; pairs whose terms would still come near it, or whose
bound is too loose to be useful, are marked unscreenable and take the float64 path.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]

#: Unit roundoffs of float32 and float64.
U32 = 2.0**-24
U64 = 2.0**-53
#: Term sizes (after the per-pair scale) above which float32 is not used: squares of the
#: forms stay below 1e34, far from float32's 3.4e38.
F32_LIMIT = 1e17

#: Index pairs (a ≤ b) of the 10 monomials of a homogeneous point; off-diagonal ones count twice.
MONO_A, MONO_B = np.triu_indices(4)
_MONO_HALF_W = np.where(MONO_A == MONO_B, 0.5, 1.0)


def shared_matmul(a: F64, b: F64) -> F64:
    """``a @ b`` for a stack ``a`` (..., n) and one ``b`` (n,) or (n, p), as one product.

    numpy runs a stacked product as one BLAS call per matrix: slow for many small ones.
    """
    result: F64 = (a.reshape(-1, a.shape[-1]) @ b).reshape(*a.shape[:-1], *b.shape[1:])
    return result


def monomials(X_h: F64) -> F64:
    """The 10 products ``X_a X_b`` (a ≤ b) of homogeneous points (4, V), as (10, V)."""
    result: F64 = X_h[MONO_A] * X_h[MONO_B]
    return result


def quadric_coefficients(P_e: F64, P_g: F64) -> F64:
    """(k, 3, 10) coefficients of ``N_u, N_v, N_w`` (see the module docstring) over monomials.

    Args:
        P_e: (k, 3, 4) estimate projection matrices ``K [R_e | t_e]``.
        P_g: (k, 3, 4) GT(-symmetry) projection matrices.
    """
    # Poses on the last axis: long inner loops (the (4, 4) products per pose are too short to
    # vectorise). np.take keeps each gathered array C-ordered.
    pe = np.ascontiguousarray(P_e.transpose(1, 2, 0))  # (3, 4, k)
    pg = np.ascontiguousarray(P_g.transpose(1, 2, 0))
    e_a, e_b = np.take(pe, MONO_A, axis=1), np.take(pe, MONO_B, axis=1)  # (3, 10, k)
    g_a, g_b = np.take(pg[:2], MONO_A, axis=1), np.take(pg[:2], MONO_B, axis=1)
    # G_r[a, b] = e_ra w_gb − g_ra w_eb (r = u, v), e_wa w_gb (r = w); coefficient of x_a x_b:
    # G_r[a, b] + G_r[b, a] (a < b), G_r[a, a]
    out = np.multiply(e_a, pg[2, MONO_B])
    out[:2] -= g_a * pe[2, MONO_B]
    g_ba = np.multiply(e_b, pg[2, MONO_A])
    g_ba[:2] -= g_b * pe[2, MONO_A]
    out += g_ba
    out *= _MONO_HALF_W[:, None]
    result: F64 = np.ascontiguousarray(out.transpose(2, 0, 1))
    return result


def raw_term_sizes(abs_e: F64, abs_g: F64) -> F64:
    """(k, 3) bounds of ``Σ_t`` (uncancelled term t) for the forms, from row bounds.

    Args:
        abs_e: (k, 3) bounds of ``|a_e|·|x|, |b_e|·|x|, |w_e|·|x|`` over the vertices
            (entrywise absolute values).
        abs_g: (k, 3) the same for the GT(-symmetry) rows.
    """
    t = np.empty_like(abs_e)
    t[:, :2] = abs_e[:, :2] * abs_g[:, 2:] + abs_g[:, :2] * abs_e[:, 2:]
    t[:, 2] = abs_e[:, 2] * abs_g[:, 2]
    return t


def screen_bounds(q: F64, t_raw: F64, mono_max: F64) -> tuple[F64, F64, B]:
    """Error bound of the float32 distances: ``|d₃₂ − d| ≤ a + b·max(d, d₃₂)`` px, per pair.

    Args:
        q: (k, 3, 10) coefficients (float64), scaled so that ``|N_w| ≥ 1`` on every vertex.
        t_raw: (k, 3) sizes of the terms before cancellation (same scale; see
            :func:`raw_term_sizes`): the float64 rounding of forming ``q``.
        mono_max: (10,) largest ``|monomial|`` over the vertices.

    Returns:
        ``(a, b, ok)``: (k,) each; ``ok`` false where float32 must not be used (terms near
        its range, a bound too loose to be useful, or non-finite input).
    """
    sizes = shared_matmul(np.abs(q), mono_max)  # (k, 3) sizes of the cancelled terms
    # 16u where 12u (coefficient, monomial, product, 10-term sum) suffices: the margin, ≥ 4u
    # since |N_w| ≥ 1 makes sizes[:, 2] ≥ 1, also covers |N_w| ≥ 1 holding only to ~1e-8
    # (the bound w_min in float64, the symmetry family's fit).
    err = 16.0 * U32 * sizes + 16.0 * U64 * t_raw  # each form's error, float32 and float64 parts
    ew = np.minimum(err[:, 2], 0.5)
    a = (err[:, 0] + err[:, 1]) / (1.0 - ew)
    b = ew / (1.0 - ew) + 3.0 * U32  # + the 5 float32 operations on the forms
    ok = np.all(sizes < F32_LIMIT, axis=1) & (err[:, 2] < 0.5) & np.isfinite(a)
    return a, b, ok


def band_threshold(d_max: F64, a: F64, b: F64) -> F32:
    """Squared float32 distance above which a vertex may be the exact maximiser, (k,).

    The exact maximiser ``j*`` and the float32 one ``j'`` satisfy ``d(j*) ≥ d(j')``, so
    ``d₃₂(j*) ≥ (1 − b) d(j*) − a ≥ (1 − b)((1 − b) d₃₂(j') − a) − a``.
    """
    tau = (1.0 - b) ** 2 * d_max - (2.0 - b) * a
    # the margin covers rounding the threshold to float32
    thr = np.where(tau > 0.0, tau * tau * (1.0 - 4.0 * U32), 0.0)
    return thr.astype(np.float32)


class ScreenVertices:
    """The vertices' float32 monomials and the largest ``|monomial|`` (float64).

    Args:
        X_h: (4, V) homogeneous vertices, mm.
    """

    def __init__(self, X_h: F64) -> None:
        with np.errstate(over="ignore", invalid="ignore"):
            mono = monomials(X_h)
            self.mono_max: F64 = np.abs(mono).max(axis=1)
        self.usable = bool(np.all(self.mono_max < F32_LIMIT))
        self.v = X_h.shape[1]
        # unusable (float32 would overflow): zeros of the right shape, never evaluated
        self.mono32: F32 = np.ascontiguousarray(
            mono if self.usable else np.zeros_like(mono), np.float32
        )
        self._work: tuple[F32, F32, F32, B] | None = None

    def work(self, k: int) -> tuple[F32, F32, F32, B]:
        """Work buffers for ``k`` pairs: forms (k, 3, V), two (k, V) and a (k, V) mask.

        Kept across calls: fresh MB-sized buffers would cost page faults at every call.
        """
        if self._work is None or self._work[1].shape[0] < k:
            v = self.v
            self._work = (
                np.empty((k, 3, v), np.float32),
                np.empty((k, v), np.float32),
                np.empty((k, v), np.float32),
                np.empty((k, v), np.bool_),
            )
        return self._work


def screened_max(
    q32: F32, verts: ScreenVertices, a: F64, b: F64, per_product: int, per_block: int
) -> tuple[I64, I64]:
    """The band of every pair: vertices whose float32 distance may be the exact maximum's.

    Args:
        q32: (k, 3, 10) float32 coefficients (scaled, see :func:`screen_bounds`).
        verts: The model's float32 monomials.
        a, b: (k,) the error bounds of :func:`screen_bounds`.
        per_product: Pairs per matrix product (bounds its size: one thread).
        per_block: Pairs per block of the elementwise work (bounds its memory).

    Returns:
        ``(pair, vertex)``: (E,) indices of the band entries, sorted by pair; every pair has at
        least one (its float32 maximiser).
    """
    k, v = q32.shape[0], verts.v
    kb = max(1, min(k, per_block))
    buf, sq, tmp, mask = verts.work(kb)
    found = []
    for p0 in range(0, k, kb):
        n = min(kb, k - p0)
        for r in range(0, n, per_product):
            e = min(n, r + per_product)
            q = q32[p0 + r : p0 + e].reshape(-1, 10)
            np.matmul(q, verts.mono32, out=buf[r:e].reshape(-1, v))
        f, s, t = buf[:n], sq[:n], tmp[:n]
        np.multiply(f[:, 0], f[:, 0], out=s)
        np.multiply(f[:, 1], f[:, 1], out=t)
        np.add(s, t, out=s)
        np.multiply(f[:, 2], f[:, 2], out=t)
        np.divide(s, t, out=s)
        d_max = np.sqrt(s.max(axis=1).astype(np.float64))
        thr = band_threshold(d_max, a[p0 : p0 + n], b[p0 : p0 + n])
        np.greater_equal(s, thr[:, None], out=mask[:n])
        found.append(np.flatnonzero(mask[:n]) + p0 * v)
    flat = np.concatenate(found)
    return flat // v, flat % v
