"""Masks of the visible object surface from distance images (``bop_toolkit_lib.visibility``).

A model pixel is visible when the rendered model is not more than ``δ`` behind the measured
scene. Inputs are **distance** images (‖X‖ from the camera centre, mm; see
:func:`bopsurg.geometry.depth_to_distance`), 0 = no model / no measurement. As in the
reference, the difference ``d_model − d_test`` is taken in float32 and compared with ``δ`` cast
to float32 (the reference's numpy < 2 casting).

* ``bop19``: ``visib = ((d_model − d_test ≤ δ) | (d_test == 0)) & (d_model > 0)``: missing
  sensor depth counts as visible (shiny objects).
* ``bop18``: ``visib = (d_model − d_test ≤ δ) & (d_test > 0) & (d_model > 0)``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.errors import InputError, ShapeError

VisibMode = Literal["bop19", "bop18"]

Mask = NDArray[np.bool_]


def _image(a: ArrayLike, name: str) -> NDArray[np.floating]:
    arr = np.asarray(a)
    if arr.ndim != 2:
        raise ShapeError(f"expected an (H, W) image, got shape {arr.shape}", field=name)
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ShapeError(f"expected a real numeric image, got dtype {arr.dtype}", field=name)
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        raise ShapeError("contains NaN or inf", field=name)
    return arr


def estimate_visib_mask(
    dist_test: ArrayLike,
    dist_model: ArrayLike,
    delta: float,
    mode: VisibMode = "bop19",
) -> Mask:
    """Mask of the visible surface of a rendered model in a measured scene.

    Args:
        dist_test: (H, W) distance image of the scene, mm (0 = missing measurement).
        dist_model: (H, W) rendered distance image of the model, mm (0 = background).
        delta: Visibility tolerance δ, mm (BOP19: 15, ITODD 5).
        mode: ``"bop19"`` (missing depth counts as visible) or ``"bop18"``.

    Returns:
        (H, W) bool mask.

    Raises:
        ShapeError: Not 2-D, different shapes, or non-finite values.
        InputError: Unknown ``mode`` or a non-finite ``delta``.
    """
    d_test = _image(dist_test, "dist_test")
    d_model = _image(dist_model, "dist_model")
    if d_test.shape != d_model.shape:
        raise ShapeError(
            f"shape {d_model.shape} differs from dist_test {d_test.shape}", field="dist_model"
        )
    if not np.isfinite(delta):
        raise InputError(f"must be finite, got {delta!r}", field="delta")
    d_diff = d_model.astype(np.float32) - d_test.astype(np.float32)
    close = d_diff <= np.float32(delta)
    if mode == "bop19":
        result: NDArray[np.bool_] = np.logical_and(np.logical_or(close, d_test == 0), d_model > 0)
        return result
    if mode == "bop18":
        return np.logical_and(close, np.logical_and(d_test > 0, d_model > 0))
    raise InputError(
        f"unknown visibility mode {mode!r} (expected 'bop19' or 'bop18')", field="mode"
    )


def estimate_visib_mask_gt(
    dist_test: ArrayLike, dist_gt: ArrayLike, delta: float, mode: VisibMode = "bop19"
) -> Mask:
    """Visible surface of the model in the GT pose: :func:`estimate_visib_mask` itself."""
    return estimate_visib_mask(dist_test, dist_gt, delta, mode)


def estimate_visib_mask_est(
    dist_test: ArrayLike,
    dist_est: ArrayLike,
    visib_gt: ArrayLike,
    delta: float,
    mode: VisibMode = "bop19",
) -> Mask:
    """Visible surface in the estimated pose: also visible where the GT surface is visible.

    ``visib_est = estimate_visib_mask(dist_test, dist_est) | (visib_gt & dist_est > 0)``
    (Hodan et al., ECCVW'16, eq. 14): an estimate is not rewarded for hiding behind the
    occluder that hides the GT surface.

    Args:
        dist_test: (H, W) scene distance image, mm.
        dist_est: (H, W) rendered distance image in the estimated pose, mm.
        visib_gt: (H, W) bool mask from :func:`estimate_visib_mask_gt`.
        delta: Visibility tolerance δ, mm.
        mode: ``"bop19"`` or ``"bop18"``.

    Returns:
        (H, W) bool mask.
    """
    d_est = np.asarray(dist_est)
    vis_gt = np.asarray(visib_gt, dtype=bool)
    visib = estimate_visib_mask(dist_test, d_est, delta, mode)
    if vis_gt.shape != visib.shape:
        raise ShapeError(f"shape {vis_gt.shape} differs from {visib.shape}", field="visib_gt")
    result: NDArray[np.bool_] = np.logical_or(visib, np.logical_and(vis_gt, d_est > 0))
    return result
