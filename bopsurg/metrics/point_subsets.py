"""Vertex subsets that make MSSD/MSPD fast without changing their values.

* :func:`hull_vertices`: the maximum of a convex function of ``x`` (such as
  ``x ↦ ‖A x + b‖``, the MSSD vertex distance) over a point set is attained at a vertex of the
  set's convex hull, so MSSD only needs the hull vertices (≈ 100 of 5,000 random points in a
  box; about half of a thin curved needle's).
* :func:`extreme_point_order`: a few extreme vertices (maximisers along directions spread over
  the sphere) in farthest-point order; its prefixes are small, well-spread subsets whose
  maxima are tight lower bounds of the maximum over all points (used by the branch and bound
  over symmetries in :mod:`bopsurg.metrics.max_distance`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from bopsurg.geometry import as_points

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def hull_vertex_indices(pts: F64) -> I64:
    """Indices of the vertices of the convex hull of ``pts``, sorted ascending.

    Falls back to all indices when Qhull cannot build a 3-D hull (fewer than 4 points,
    coplanar or collinear sets): the maximum over all points is trivially exact.

    Args:
        pts: (V, 3) float64 points, mm.

    Returns:
        (H,) int64 indices into ``pts``.
    """
    pts = as_points(pts)
    if pts.shape[0] < 5:
        return np.arange(pts.shape[0], dtype=np.int64)
    # scipy on first use: importing the metrics (the registry, 'eval --help') stays light.
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError):
        return np.arange(pts.shape[0], dtype=np.int64)
    return np.sort(np.asarray(hull.vertices, dtype=np.int64))


def hull_probe(pts: F64, probe: int = 250) -> tuple[I64, float]:
    """The hull of an evenly strided sample: which points can be hull vertices, and how many.

    Points strictly inside the sample's hull (by a relative margin of 1e-9, far above Qhull's
    rounding) are inside the hull of all points, so they are not its vertices: the rest is a
    superset of the hull vertices, for the price of one small product. The share of the sample
    on its hull tells solid clouds (a small hull, worth Qhull on the rest) from thin or surface
    models (half or more on the hull: Qhull would cost more than it saves, ≈ 10 ms for a thin
    5,000-vertex needle).

    Args:
        pts: (V, 3) float64 points, mm.
        probe: Points of the sample (every ⌈V / probe⌉-th point).

    Returns:
        ``(candidates, share)``: (C,) int64 sorted indices into ``pts`` that include every
        vertex of their convex hull, and the share in [0, 1] of the sample on its hull (1 with
        all indices when the sample's hull is degenerate).
    """
    pts = as_points(pts)
    sample = pts[:: max(1, -(-pts.shape[0] // probe))]
    everything = np.arange(pts.shape[0], dtype=np.int64)
    if sample.shape[0] < 5:
        return everything, 1.0
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(sample)
    except (QhullError, ValueError):
        return everything, 1.0
    eq = np.asarray(hull.equations)  # (F, 4): n · x + c ≤ 0 inside, unit normals
    margin = 1e-9 * (1.0 + float(np.abs(pts).max()))
    pts_t = np.ascontiguousarray(pts.T)
    height = np.full(pts.shape[0], -np.inf)  # the largest signed distance to a facet plane
    step = 8  # facets per product: a cache-sized result, one thread (OpenBLAS)
    for k in range(0, eq.shape[0], step):
        d = eq[k : k + step, :3] @ pts_t
        d += eq[k : k + step, 3:4]
        np.maximum(height, d.max(axis=0), out=height)
    return np.flatnonzero(height >= -margin), hull.vertices.size / sample.shape[0]


def hull_vertices(pts: F64) -> F64:
    """The vertices of the convex hull of ``pts`` (all points if the hull is degenerate).

    Pass the result as ``candidates=`` to :func:`bopsurg.metrics.mssd` to reuse it across
    calls with the same model.

    Args:
        pts: (V, 3) float64 model points, mm.

    Returns:
        (H, 3) float64 points, a subset of ``pts`` whose convex hull contains all of ``pts``.
    """
    pts = as_points(pts)
    return pts[hull_vertex_indices(pts)]


def farthest_point_order(pts: F64, m: int) -> I64:
    """Greedy farthest-point ordering of up to ``m`` points (deterministic).

    Starts with the point farthest from the centroid, then repeatedly adds the point farthest
    from those chosen so far. Every prefix of the result is a well-spread subset.

    Args:
        pts: (V, 3) float64 points, mm.
        m: How many indices to return (at most V).

    Returns:
        (min(m, V),) int64 indices into ``pts``, no repeats.
    """
    v = pts.shape[0]
    m = min(int(m), v)
    order = np.empty(m, dtype=np.int64)
    if m == 0:
        return order
    centred = pts - pts.mean(axis=0)
    nxt = int(np.argmax(np.einsum("ij,ij->i", centred, centred)))
    d = np.full(v, np.inf)
    for k in range(m):  # m iterations over vertex arrays; m is small (≤ 64)
        order[k] = nxt
        diff = pts - pts[nxt]
        d = np.minimum(d, np.einsum("ij,ij->i", diff, diff))
        d[order[: k + 1]] = -1.0  # never pick a point twice, even among duplicates
        nxt = int(np.argmax(d))
    return order


def sphere_directions(m: int) -> F64:
    """``m`` unit vectors spread evenly over the sphere (Fibonacci lattice), (m, 3)."""
    k = np.arange(m) + 0.5
    z = 1.0 - 2.0 * k / m
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def extreme_point_order(pts: F64, m: int) -> I64:
    """Up to ``m`` extreme points of ``pts``, ordered farthest-point first (deterministic).

    The points are the maximisers of ``⟨d, x⟩`` for ``4m`` directions ``d`` spread over the
    sphere (so vertices of the convex hull), found with one matrix product: far cheaper than
    :func:`farthest_point_order` on all points or a full hull, and as well spread.

    Args:
        pts: (V, 3) float64 points, mm.
        m: How many indices to return at most.

    Returns:
        (≤ m,) int64 indices into ``pts``, no repeats.
    """
    centred_t = np.ascontiguousarray((pts - pts.mean(axis=0)).T)
    dirs = sphere_directions(4 * m)
    # (directions, V) so that argmax runs along contiguous rows (fast in numpy); blocks of
    # directions keep each product small enough for OpenBLAS to run it on one thread.
    step = max(1, (1 << 19) // (3 * pts.shape[0]))
    ext = [np.argmax(dirs[k : k + step] @ centred_t, axis=1) for k in range(0, dirs.shape[0], step)]
    idx = np.unique(np.concatenate(ext))
    return idx[farthest_point_order(pts[idx], m)]
