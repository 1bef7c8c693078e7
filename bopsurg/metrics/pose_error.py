"""Batched BOP pose errors: RE, TE, MSSD, MSPD, ADD, ADD-S (ADI) and the projection error.

Each function takes N (estimate, GT) pose pairs, ``R`` (N, 3, 3) and ``t`` (N, 3) in mm (a
single pose (3, 3) / (3,) / (3, 1) works too, and a batch of 1 broadcasts against N), and
returns a float64 (N,) array equal to ``bop_toolkit_lib.pose_error`` applied pose by pose, to
float64 rounding (≤ 1e-9 relative, or absolute for values near 0). Pose: ``x_cam = R x + t``.

Definitions (``P_e x = R_e x + t_e``, ``P_g x = R_g x + t_g``, ``π`` the pinhole projection
``K [R | t]`` with a homogeneous divide and no z check, ``S`` the symmetry set):

* ``re``: ``acos(clip((tr(R_e R_g⁻¹) − 1) / 2, −1, 1))`` in degrees.
* ``te``: ``‖t_g − t_e‖`` in mm.
* ``mssd``: ``min_{s∈S} max_x ‖P_e x − (R_g R_s x + R_g t_s + t_g)‖`` in mm (BOP19).
* ``mspd``: ``min_{s∈S} max_x ‖π(P_e x) − π(R_g R_s x + R_g t_s + t_g)‖`` in px (BOP19).
* ``add``: ``mean_x ‖P_e x − P_g x‖`` in mm (Hinterstoisser et al., ACCV'12).
* ``adi`` (ADD-S): ``mean_x min_y ‖P_g x − P_e y‖`` in mm: for every GT-posed vertex, the
  nearest estimate-posed vertex (one-directional, as the reference's
  ``cKDTree(pts_est).query(pts_gt)``).
* ``proj``: ``mean_x ‖π(P_e x) − π(P_g x)‖`` in px (Brachmann et al., CVPR'16).

Memory is bounded by processing poses in chunks (``chunk_size``); nothing of size
N·S·V is ever allocated.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.errors import InputError
from bopsurg.geometry import as_points, as_rotations, as_translations, batch_size
from bopsurg.metrics._pairs import PosePairs, check_chunk_size, chunks, intrinsics, pose_pairs
from bopsurg.metrics.max_distance import WORK, min_max_distance_3d, min_max_distance_proj
from bopsurg.metrics.symmetry import Symmetries, as_symmetries

F64 = NDArray[np.float64]
SymsLike = Symmetries | Sequence[Mapping[str, ArrayLike]] | None

#: ADD-S maps GT vertices into the estimate's model frame when ``R_est``'s singular values
#: differ by at most this ratio (files give rotations to ~1e-8); else a tree per pose.
ROTATION_RATIO_TOL = 1e-6
#: Query points per cKDTree call in :func:`adi`.
ADI_QUERY_BLOCK = 1 << 18


def _pose_block(n_vertices: int) -> int:
    """Poses per cache-sized block when all V vertices are transformed per pose."""
    return max(1, WORK // (6 * n_vertices))


def re(R_est: ArrayLike, R_gt: ArrayLike) -> F64:
    """Rotation error in degrees, ``acos((tr(R_e R_g⁻¹) − 1) / 2)``, in [0, 180].

    Uses ``np.linalg.inv`` (not the transpose) and the same matrix product as the reference,
    so even tiny angles (where ``acos`` amplifies rounding) match it.

    Args:
        R_est: (N, 3, 3) or (3, 3) estimated rotations.
        R_gt: (N, 3, 3) or (3, 3) GT rotations (invertible).

    Returns:
        (N,) float64, degrees.

    Raises:
        ShapeError: Wrong shape, non-finite values or batch sizes that do not broadcast.
        InputError: A singular ``R_gt``.

    Example:
        >>> import numpy as np
        >>> Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        >>> re(Rz, np.eye(3)).round(9).tolist()
        [90.0]
    """
    R_e = as_rotations(R_est, "R_est")
    R_g = as_rotations(R_gt, "R_gt")
    n = batch_size(R_e, R_g)
    try:
        inv = np.linalg.inv(R_g)
    except np.linalg.LinAlgError as err:
        raise InputError("singular matrix", field="R_gt") from err
    prod = np.matmul(np.broadcast_to(R_e, (n, 3, 3)), np.broadcast_to(inv, (n, 3, 3)))
    error_cos = 0.5 * (np.trace(prod, axis1=1, axis2=2) - 1.0)
    error_cos = np.minimum(1.0, np.maximum(-1.0, error_cos))
    result: F64 = 180.0 * np.arccos(error_cos) / np.pi
    return result


def te(t_est: ArrayLike, t_gt: ArrayLike) -> F64:
    """Translation error ``‖t_g − t_e‖`` in mm.

    Unlike the reference's ``te``, (3,) and (3, 1) inputs never broadcast to a 3×3 difference.

    Args:
        t_est: (N, 3), (3,) or (3, 1) estimated translations, mm.
        t_gt: (N, 3), (3,) or (3, 1) GT translations, mm.

    Returns:
        (N,) float64, mm.

    Example:
        >>> te([3.0, 4.0, 0.0], [0.0, 0.0, 0.0]).tolist()
        [5.0]
    """
    a = as_translations(t_est, "t_est")
    b = as_translations(t_gt, "t_gt")
    batch_size(a, b)
    d = b - a
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])


def _candidates(candidates: ArrayLike | None) -> F64 | None:
    if candidates is None:
        return None
    return as_points(candidates, "candidates")


def mssd(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    pts: ArrayLike,
    syms: SymsLike = None,
    *,
    candidates: ArrayLike | None = None,
    chunk_size: int | None = None,
) -> F64:
    """Maximum Symmetry-aware Surface Distance (BOP19), in mm.

    ``min_{s} max_x ‖(R_e x + t_e) − (R_g R_s x + R_g t_s + t_g)‖``, evaluated with the exact
    shortcuts of :mod:`bopsurg.metrics.max_distance` (convex hull, branch and bound over
    symmetries); about 1000× faster than the reference's loop, same values.

    Args:
        R_est: (N, 3, 3) or (3, 3) estimated rotations.
        t_est: (N, 3), (3,) or (3, 1) estimated translations, mm.
        R_gt: (N, 3, 3) or (3, 3) GT rotations.
        t_gt: (N, 3), (3,) or (3, 1) GT translations, mm.
        pts: (V, 3) model vertices, mm.
        syms: ``(R_sym (S, 3, 3), t_sym (S, 3))`` from
            :func:`~bopsurg.metrics.symmetry.symmetry_transforms`, the reference's list of
            ``{"R", "t"}`` dicts, or None (identity only).
        candidates: (H, 3) points whose convex hull contains ``pts`` (e.g.
            :func:`~bopsurg.metrics.point_subsets.hull_vertices` of the model, computed once
            and reused across calls); default: the hull is computed here when it is small
            (a probe decides; see :mod:`bopsurg.metrics.max_distance`), else all of ``pts``.
            Passing points whose hull does not contain ``pts`` gives wrong results.
        chunk_size: Poses per chunk (memory bound); default from a ~16 MB budget.

    Returns:
        (N,) float64, mm.

    Example:
        >>> import numpy as np
        >>> pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
        >>> mssd(np.eye(3), [3.0, 4.0, 100.0], np.eye(3), [0.0, 0.0, 100.0], pts).tolist()
        [5.0]
    """
    pairs = pose_pairs(R_est, t_est, R_gt, t_gt)
    p = as_points(pts)
    R_sym, t_sym = as_symmetries(syms)
    size = None if chunk_size is None else check_chunk_size(chunk_size, 1)
    return min_max_distance_3d(
        pairs, p, R_sym, t_sym, candidates=_candidates(candidates), chunk_size=size
    )


def mspd(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    K: ArrayLike,
    pts: ArrayLike,
    syms: SymsLike = None,
    *,
    chunk_size: int | None = None,
) -> F64:
    """Maximum Symmetry-aware Projection Distance (BOP19), in px.

    ``min_{s} max_x ‖π(K, R_e, t_e, x) − π(K, R_g R_s, R_g t_s + t_g, x)‖`` with the
    reference's projection (``K [R | t]``, homogeneous divide, no z check). All vertices are
    evaluated (the projected distance is not convex); the branch and bound over symmetries of
    :mod:`bopsurg.metrics.max_distance` keeps the values exact.

    NaN/inf: a vertex on the camera plane (z = 0) projects to inf/nan, as in the reference;
    the result is NaN when the reference's is (its identity term is NaN), otherwise the
    minimum over the other terms (inf included). Such poses take a slower exhaustive path.

    Args:
        R_est: (N, 3, 3) or (3, 3) estimated rotations.
        t_est: (N, 3), (3,) or (3, 1) estimated translations, mm.
        R_gt: (N, 3, 3) or (3, 3) GT rotations.
        t_gt: (N, 3), (3,) or (3, 1) GT translations, mm.
        K: (3, 3) or (N, 3, 3) camera matrices.
        pts: (V, 3) model vertices, mm.
        syms: Symmetry set as for :func:`mssd`, or None (identity only).
        chunk_size: Poses per chunk (memory bound); default from a ~32 MB budget.

    Returns:
        (N,) float64, px.
    """
    pairs = pose_pairs(R_est, t_est, R_gt, t_gt)
    K_m = intrinsics(K, pairs.n)
    p = as_points(pts)
    R_sym, t_sym = as_symmetries(syms)
    size = None if chunk_size is None else check_chunk_size(chunk_size, 1)
    return min_max_distance_proj(pairs, K_m, p, R_sym, t_sym, chunk_size=size)


def _stacked_pose_mats(pairs: PosePairs, sl: slice) -> F64:
    """``[R | t]`` of the estimates, then of the GTs, of the pairs ``sl``: (2k, 3, 4)."""
    k = sl.stop - sl.start
    R_t = np.empty((2 * k, 3, 4))
    R_t[:k, :, :3], R_t[:k, :, 3] = pairs.R_est[sl], pairs.t_est[sl]
    R_t[k:, :, :3], R_t[k:, :, 3] = pairs.R_gt[sl], pairs.t_gt[sl]
    return R_t


def _transform_both(pairs: PosePairs, sl: slice, X_h: F64) -> tuple[F64, F64]:
    """Estimate- and GT-posed vertices of the pairs ``sl``: two (k, 3, V) arrays, mm."""
    k = sl.stop - sl.start
    X = (_stacked_pose_mats(pairs, sl).reshape(-1, 4) @ X_h).reshape(2 * k, 3, X_h.shape[1])
    return X[:k], X[k:]


def _norm3(d: F64) -> F64:
    """Row norms of (k, 3, V) differences, summed in the reference's order: (k, V)."""
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])


def _homogeneous(p: F64) -> F64:
    X_h = np.ones((4, p.shape[0]))
    X_h[:3] = p.T
    return X_h


def add(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    pts: ArrayLike,
    *,
    chunk_size: int | None = None,
) -> F64:
    """ADD: mean distance between corresponding vertices in the two poses, in mm.

    Args:
        R_est, t_est, R_gt, t_gt: Pose pairs as for :func:`mssd`.
        pts: (V, 3) model vertices, mm.
        chunk_size: Poses per block (default: a cache-sized block).

    Returns:
        (N,) float64, mm.
    """
    pairs = pose_pairs(R_est, t_est, R_gt, t_gt)
    p = as_points(pts)
    X_h = _homogeneous(p)
    size = check_chunk_size(chunk_size, _pose_block(p.shape[0]))
    out = np.empty(pairs.n)
    for sl in chunks(pairs.n, size):
        est, gt = _transform_both(pairs, sl, X_h)
        out[sl] = _norm3(est - gt).mean(axis=1)
    return out


def _nearest_brute(
    gt: F64, est: F64, rows: NDArray[np.int64], cols: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Index of the nearest estimate-posed vertex for GT vertices ``gt[rows, :, cols]``."""
    out = np.empty(rows.size, dtype=np.int64)
    v = est.shape[2]
    for b in chunks(rows.size, max(1, WORK // (3 * v))):
        d = gt[rows[b], :, cols[b], None] - est[rows[b]]  # (m, 3, V)
        out[b] = np.argmin(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2], axis=1)
    return out


def adi(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    pts: ArrayLike,
    *,
    chunk_size: int | None = None,
    workers: int = -1,
) -> F64:
    """ADD-S (ADI): mean over GT-posed vertices of the distance to the nearest estimate-posed one.

    One-directional like the reference (``cKDTree(pts_est).query(pts_gt)``). Fast and exact:
    ``‖R_g x + t_g − (R_e y + t_e)‖ = ‖R_e⁻¹(R_g x + t_g − t_e) − y‖`` when ``R_e`` is a rotation,
    so one k-d tree on the model vertices answers all N·V queries. ``R_e`` read from files is
    a rotation only to ~1e-8, which scales model-frame distances by at most its singular-value
    ratio κ; the found vertex is provably the nearest whenever the second-nearest one is more
    than κ times farther, and the few queries that fail this test (near-ties) are answered by
    brute force. Distances are then recomputed in the camera frame with the reference's formula.
    Poses whose ``R_est`` is far from a rotation (κ > 1 + 1e-6) get the reference's own
    per-pose tree.

    Args:
        R_est, t_est, R_gt, t_gt: Pose pairs as for :func:`mssd`.
        pts: (V, 3) model vertices, mm.
        chunk_size: Poses per k-d tree query (default: ≈ 262k query points).
        workers: Threads for ``cKDTree.query`` (−1: all cores).

    Returns:
        (N,) float64, mm.
    """
    pairs = pose_pairs(R_est, t_est, R_gt, t_gt)
    p = as_points(pts)
    v = p.shape[0]
    size = check_chunk_size(chunk_size, max(1, ADI_QUERY_BLOCK // v))
    sv = np.linalg.svd(np.asarray(pairs.R_est), compute_uv=False)  # (N, 3), descending
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = sv[:, 0] / sv[:, 2]
    rotation_like = kappa <= 1.0 + ROTATION_RATIO_TOL
    rho = float(np.sqrt(np.einsum("ij,ij->i", p, p).max()))
    # Rounding of the model-frame query points and distances, mm (generous).
    slack = 1e-12 * (rho + np.linalg.norm(pairs.t_est, axis=1) + np.linalg.norm(pairs.t_gt, axis=1))
    # Sliding-midpoint splits and larger leaves: 2x faster queries on thin curved models
    # (needles), the same on compact ones; the nearest neighbour is exact either way.
    from scipy.spatial import cKDTree  # on first use: 'eval --help' lists metrics, light

    tree = cKDTree(p, leafsize=64, balanced_tree=False, compact_nodes=False)
    p_t = np.ascontiguousarray(p.T)
    out = np.empty(pairs.n)
    for sl in chunks(pairs.n, size):
        k = sl.stop - sl.start
        R_e, t_e = pairs.R_est[sl], pairs.t_est[sl][:, :, None]
        R_g, t_g = pairs.R_gt[sl], pairs.t_gt[sl][:, :, None]
        # einsum, not BLAS: OpenBLAS threads spin after a call and would steal the cores
        # of the k-d tree's workers (measured: 1.6x slower queries).
        gt = np.einsum("nij,jv->niv", R_g, p_t) + t_g  # (k, 3, V), as the reference
        est = np.einsum("nij,jv->niv", R_e, p_t) + t_e
        ok_pose = rotation_like[sl]
        # GT-posed vertices in the estimate's model frame: R_e⁻¹ R_g x + R_e⁻¹ (t_g − t_e)
        R_inv = np.linalg.inv(np.where(ok_pose[:, None, None], R_e, np.eye(3)))
        R_rel = np.einsum("nij,njk->nik", R_inv, R_g)
        c = np.einsum("nij,njk->nik", R_inv, t_g - t_e)
        y = np.einsum("nij,jv->nvi", R_rel, p_t) + np.swapaxes(c, 1, 2)  # (k, V, 3)
        dd, ii = tree.query(y.reshape(-1, 3), k=2, workers=workers)
        nn = ii[:, 0].reshape(k, v)
        # Certified nearest: the runner-up is farther by more than distortion and rounding.
        limit = (kappa[sl] * (1.0 + 1e-12))[:, None] * dd[:, 0].reshape(k, v) + slack[sl, None]
        doubt = (dd[:, 1].reshape(k, v) <= limit) & ok_pose[:, None]
        rows, cols = np.nonzero(doubt)
        if rows.size:
            nn[rows, cols] = _nearest_brute(gt, est, rows, cols)
        flat = nn + (np.arange(k) * v)[:, None]
        sq = np.zeros((k, v))
        for i in range(3):  # distance to the nearest estimate vertex, summed as the reference
            d = gt[:, i] - est[:, i].reshape(-1)[flat]
            sq += d * d
        out[sl] = np.sqrt(sq).mean(axis=1)
        for r in np.flatnonzero(~ok_pose):  # not a rotation: the reference's per-pose tree
            out[sl.start + r] = cKDTree(est[r].T).query(gt[r].T, k=1)[0].mean()
    return out


def proj(
    R_est: ArrayLike,
    t_est: ArrayLike,
    R_gt: ArrayLike,
    t_gt: ArrayLike,
    K: ArrayLike,
    pts: ArrayLike,
    *,
    chunk_size: int | None = None,
) -> F64:
    """Mean projection distance of the vertices (Brachmann et al., CVPR'16), in px.

    Same projection as the reference (no z check: z = 0 gives inf/nan).

    Args:
        R_est, t_est, R_gt, t_gt: Pose pairs as for :func:`mssd`.
        K: (3, 3) or (N, 3, 3) camera matrices.
        pts: (V, 3) model vertices, mm.
        chunk_size: Poses per block (default: a cache-sized block).

    Returns:
        (N,) float64, px.
    """
    pairs = pose_pairs(R_est, t_est, R_gt, t_gt)
    K_m = intrinsics(K, pairs.n)
    p = as_points(pts)
    X_h = _homogeneous(p)
    size = check_chunk_size(chunk_size, _pose_block(p.shape[0]))
    out = np.empty(pairs.n)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for sl in chunks(pairs.n, size):
            k = sl.stop - sl.start
            K_b = np.concatenate([K_m[sl], K_m[sl]])
            P = np.matmul(K_b, _stacked_pose_mats(pairs, sl))  # K [R | t], as the reference
            uvw = (P.reshape(-1, 4) @ X_h).reshape(2 * k, 3, -1)
            uv = uvw[:, :2] / uvw[:, 2:3]
            d = uv[:k] - uv[k:]
            out[sl] = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).mean(axis=1)
    return out
