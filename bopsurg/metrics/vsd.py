"""Visible Surface Discrepancy (VSD; Hodan, Michel et al., ECCV'18), for all τ at once.

Rendering is not done here: the caller passes the test depth image and the model's depth
rendered in the estimated and in the GT pose (a renderer plugin produces them). Then, as in
``bop_toolkit_lib.pose_error.vsd``:

1. distance images ``dist = depth_to_distance(depth, K)`` of the three depth images;
2. ``V_g = visib(dist_test, dist_gt)``,
   ``V_e = visib(dist_test, dist_est) | (V_g & dist_est > 0)`` (rule ``bop19`` by default, see
   :mod:`bopsurg.metrics.visibility_mask`);
3. on ``∩ = V_g ∧ V_e``: ``d = |dist_g − dist_e|``, divided by the diameter when given;
4. ``e_τ = (Σ_{p∈∩} c_τ(d_p) + |∪| − |∩|) / |∪|`` with ``c_τ(d) = [d ≥ τ]`` (``step``) or
   ``min(1, d / τ)`` (``tlinear``); 1.0 for every τ when ``|∪| = 0``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.errors import InputError, ShapeError
from bopsurg.geometry import depth_to_distance
from bopsurg.metrics.visibility_mask import (
    VisibMode,
    estimate_visib_mask_est,
    estimate_visib_mask_gt,
)

F64 = NDArray[np.float64]
VsdCost = Literal["step", "tlinear"]


def _depth(a: ArrayLike, name: str, shape: tuple[int, ...] | None) -> NDArray[np.floating]:
    arr = np.asarray(a)
    if arr.ndim != 2:
        raise ShapeError(f"expected an (H, W) depth image, got shape {arr.shape}", field=name)
    if shape is not None and arr.shape != shape:
        raise ShapeError(f"shape {arr.shape} differs from depth_test {shape}", field=name)
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ShapeError(f"expected real numbers, got dtype {arr.dtype}", field=name)
    if not np.all(np.isfinite(arr)):
        raise ShapeError("contains NaN or inf", field=name)
    return arr


def _positive(x: float, name: str) -> float:
    v = float(x)
    if not (np.isfinite(v) and v > 0):
        raise InputError(f"must be a finite number > 0, got {x!r}", field=name)
    return v


def _taus(taus: Sequence[float] | ArrayLike, cost: str) -> F64:
    """The tolerances τ as a finite (T,) array, checked against the pixel cost."""
    tau: F64 = np.atleast_1d(np.asarray(taus, dtype=np.float64))
    if tau.ndim != 1 or not np.all(np.isfinite(tau)):
        raise InputError("expected a finite 1-D sequence", field="taus")
    if cost not in ("step", "tlinear"):
        raise InputError(
            f"unknown pixel cost {cost!r} (expected 'step' or 'tlinear')", field="cost"
        )
    if cost == "tlinear" and np.any(tau <= 0):
        raise InputError("tlinear needs every tau > 0", field="taus")
    return tau


def _window_origin(window: tuple[slice, slice]) -> tuple[int, int]:
    """(row, column) of a window's top-left pixel."""
    return int(window[0].start), int(window[1].start)


def _support_window(a: NDArray[np.floating], b: NDArray[np.floating]) -> tuple[slice, slice] | None:
    """Rows and columns of the bounding box of the pixels where ``a`` or ``b`` is > 0.

    Only there can a pixel be visible (both visibility masks need d_model > 0), so VSD works
    on this window: same values, as depth_to_distance is bit-identical on windows.
    """
    rows = np.flatnonzero((a > 0).any(axis=1) | (b > 0).any(axis=1))
    if rows.size == 0:
        return None
    r = slice(int(rows[0]), int(rows[-1]) + 1)
    cols = np.flatnonzero((a[r] > 0).any(axis=0) | (b[r] > 0).any(axis=0))
    return r, slice(int(cols[0]), int(cols[-1]) + 1)


def vsd(
    depth_test: ArrayLike,
    depth_est: ArrayLike,
    depth_gt: ArrayLike,
    K: ArrayLike,
    delta: float,
    taus: Sequence[float] | ArrayLike,
    diameter: float | None = None,
    cost: VsdCost = "step",
    *,
    visib_mode: VisibMode = "bop19",
) -> F64:
    """VSD errors for every misalignment tolerance τ, in [0, 1].

    Args:
        depth_test: (H, W) measured depth of the test image, mm (0 = missing).
        depth_est: (H, W) model depth rendered in the estimated pose, mm (0 = background).
        depth_gt: (H, W) model depth rendered in the GT pose, mm (0 = background).
        K: (3, 3) camera matrix of the image.
        delta: Visibility tolerance δ, mm (BOP19: 15; ITODD: 5).
        taus: (T,) misalignment tolerances τ: fractions of the diameter when ``diameter`` is
            given (BOP19: ``np.arange(0.05, 0.51, 0.05)``), else mm.
        diameter: Object diameter, mm; when given, pixel distances are divided by it (the
            reference's ``normalized_by_diameter=True``).
        cost: ``"step"`` (BOP, SIXD 2017 onwards) or ``"tlinear"`` (ECCVW'16).
        visib_mode: Visibility rule, ``"bop19"`` (default, as the reference's VSD) or ``"bop18"``.

    Returns:
        (T,) float64 errors, one per τ; all 1.0 when neither pose has a visible pixel.

    Raises:
        ShapeError: Images not 2-D, of different shapes, or with non-finite values; bad ``K``.
        InputError: Bad ``delta``, ``taus``, ``diameter`` or ``cost``.

    Example:
        >>> import numpy as np
        >>> d = np.full((4, 4), 500.0)
        >>> K = np.array([[500.0, 0, 2], [0, 500.0, 2], [0, 0, 1]])
        >>> vsd(d, d, d, K, 15.0, [0.05, 0.5], diameter=100.0).tolist()
        [0.0, 0.0]
    """
    test, est, gt, K_m, tau, diam = _checked(depth_test, depth_est, depth_gt, K, delta, taus,
                                             diameter, cost)  # fmt: skip
    return _vsd_window(test, est, gt, K_m, (0, 0), delta, tau, diam, cost, visib_mode)


def vsd_in_window(
    depth_test: ArrayLike,
    depth_est: ArrayLike,
    depth_gt: ArrayLike,
    K: ArrayLike,
    origin: tuple[int, int],
    delta: float,
    taus: Sequence[float] | ArrayLike,
    diameter: float | None = None,
    cost: VsdCost = "step",
    *,
    visib_mode: VisibMode = "bop19",
) -> F64:
    """:func:`vsd` of whole images, given the same window of the three.

    When both rendered depths are 0 outside the window, the errors equal those of
    :func:`vsd` on the whole images, bit for bit: only pixels where a model is rendered can
    be visible, and distances do not depend on the window.

    Args:
        depth_test, depth_est, depth_gt: (h, w) windows of the images, mm.
        K: (3, 3) camera matrix of the whole image.
        origin: (row, column) of the window's top-left pixel in the whole image.
        delta, taus, diameter, cost, visib_mode: As for :func:`vsd`.

    Returns:
        (T,) float64 errors, one per τ.
    """
    test, est, gt, K_m, tau, diam = _checked(depth_test, depth_est, depth_gt, K, delta, taus,
                                             diameter, cost)  # fmt: skip
    origin_rc = (int(origin[0]), int(origin[1]))
    return _vsd_window(test, est, gt, K_m, origin_rc, delta, tau, diam, cost, visib_mode)


def _checked(
    depth_test: ArrayLike,
    depth_est: ArrayLike,
    depth_gt: ArrayLike,
    K: ArrayLike,
    delta: float,
    taus: Sequence[float] | ArrayLike,
    diameter: float | None,
    cost: str,
) -> tuple[
    NDArray[np.floating], NDArray[np.floating], NDArray[np.floating], F64, F64, float | None
]:
    """The inputs of :func:`vsd` checked and converted (see its Raises)."""
    test = _depth(depth_test, "depth_test", None)
    est = _depth(depth_est, "depth_est", test.shape)
    gt = _depth(depth_gt, "depth_gt", test.shape)
    K_m = np.asarray(K, dtype=np.float64)
    if K_m.shape != (3, 3) or not np.all(np.isfinite(K_m)):
        raise ShapeError(f"expected a finite (3, 3) matrix, got shape {K_m.shape}", field="K")
    if not np.isfinite(delta):
        raise InputError(f"must be finite, got {delta!r}", field="delta")
    tau = _taus(taus, cost)
    diam = None if diameter is None else _positive(diameter, "diameter")
    return test, est, gt, K_m, tau, diam


def _vsd_window(
    test: NDArray[np.floating],
    est: NDArray[np.floating],
    gt: NDArray[np.floating],
    K_m: F64,
    origin: tuple[int, int],
    delta: float,
    tau: F64,
    diam: float | None,
    cost: str,
    visib_mode: VisibMode,
) -> F64:
    """VSD of checked images that are the window at ``origin`` of the whole images."""
    window = _support_window(est, gt)
    if window is None:
        return np.ones(tau.size)
    r0, c0 = _window_origin(window)
    at = (origin[0] + r0, origin[1] + c0)
    dist_test, dist_est, dist_gt = (depth_to_distance(d[window], K_m, at)
                                    for d in (test, est, gt))  # fmt: skip
    visib_gt = estimate_visib_mask_gt(dist_test, dist_gt, delta, visib_mode)
    visib_est = estimate_visib_mask_est(dist_test, dist_est, visib_gt, delta, visib_mode)
    inter = np.logical_and(visib_gt, visib_est)
    union_count = int(np.logical_or(visib_gt, visib_est).sum())
    comp_count = union_count - int(inter.sum())
    if union_count == 0:
        return np.ones(tau.size)
    dists = np.abs(dist_gt[inter] - dist_est[inter])
    if diam is not None:
        dists /= diam
    if cost == "step":
        # #{d ≥ τ} for all τ at once: d sorted, then one binary search per τ.
        n_ge = dists.size - np.searchsorted(np.sort(dists), tau, side="left")
        result: F64 = (n_ge + comp_count) / float(union_count)
        return result
    out = np.empty(tau.size)
    for k, t in enumerate(tau):  # T sums over the pixels, in the reference's order
        out[k] = (np.sum(np.minimum(dists / t, 1.0)) + comp_count) / float(union_count)
    return out
