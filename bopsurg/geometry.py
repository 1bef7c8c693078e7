"""Rigid transforms, pinhole projection and input checks for batched pose arrays.

Convention (BOP): a pose maps model to camera, ``x_cam = R @ x_model + t``; ``R`` is a
rotation matrix (stored row-major in files), ``t`` and model points are in mm; the camera is
OpenCV's (x right, y down, looking along +z) and pixel ``(u, v)`` is (column, row).

Every function here works on batches: ``R`` (N, 3, 3), ``t`` (N, 3), ``K`` (N, 3, 3). The
``as_*`` helpers accept a single pose as well ((3, 3), (3,) or (3, 1)) and return the batched
float64 form, raising :class:`~bopsurg.errors.ShapeError` with a one-line message otherwise.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.errors import ShapeError

F64 = NDArray[np.float64]

#: Default tolerance of :func:`is_rotation`: max |RᵀR − I| entry and |det R − 1|. Loose
#: enough for matrices printed with 4 decimals (which the reference toolkit accepts), tight
#: enough to catch scaled, reflected, transposed-garbage or truncated matrices.
ROTATION_ATOL = 1e-3


def _finite(a: F64, name: str) -> F64:
    if not np.all(np.isfinite(a)):
        raise ShapeError("contains NaN or inf", field=name)
    return a


def as_column(value: ArrayLike, shape: tuple[int, ...], name: str, dtype: Any) -> NDArray[Any]:
    """``value`` as an array of ``dtype`` and exactly ``shape`` (empty input takes the shape);
    float columns must be finite.

    Raises:
        ShapeError: Another shape, or NaN / inf in a float column (``field`` = ``name``).
    """
    a = np.asarray(value, dtype=dtype)
    if a.size == 0:
        a = a.reshape(shape)
    if a.shape != shape:
        raise ShapeError(f"expected shape {shape}, got {a.shape}", field=name)
    if a.dtype.kind == "f":
        _finite(a, name)
    return a


def as_rotations(R: ArrayLike, name: str = "R") -> F64:
    """Return ``R`` as a finite float64 (N, 3, 3) array; a single (3, 3) becomes N = 1."""
    a = np.asarray(R, dtype=np.float64)
    if a.shape == (3, 3):
        a = a[None]
    if a.ndim != 3 or a.shape[1:] != (3, 3):
        raise ShapeError(f"expected shape (3, 3) or (N, 3, 3), got {a.shape}", field=name)
    return _finite(a, name)


def as_translations(t: ArrayLike, name: str = "t") -> F64:
    """Return ``t`` (mm) as a finite float64 (N, 3) array.

    Accepts (3,), (3, 1), (N, 3) and (N, 3, 1). Mixing (3,) and (3, 1) cannot silently
    broadcast here, unlike in the reference toolkit's ``te``.
    """
    a = np.asarray(t, dtype=np.float64)
    if a.shape in ((3,), (3, 1)):
        a = a.reshape(1, 3)
    elif a.ndim == 3 and a.shape[1:] == (3, 1):
        a = a[:, :, 0]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ShapeError(f"expected shape (3,), (3, 1) or (N, 3), got {a.shape}", field=name)
    return _finite(a, name)


def as_points(pts: ArrayLike, name: str = "pts") -> F64:
    """Return model points (mm) as a finite float64 (V, 3) array with V ≥ 1."""
    a = np.asarray(pts, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
        raise ShapeError(f"expected shape (V, 3) with V >= 1, got {a.shape}", field=name)
    return _finite(a, name)


def as_intrinsics(K: ArrayLike, n: int, name: str = "K") -> F64:
    """Return camera matrices as float64 (n, 3, 3); a single (3, 3) is broadcast to all n."""
    a = np.asarray(K, dtype=np.float64)
    if a.shape == (3, 3):
        a = np.broadcast_to(a, (n, 3, 3))
    if a.shape != (n, 3, 3):
        raise ShapeError(f"expected shape (3, 3) or ({n}, 3, 3), got {a.shape}", field=name)
    return _finite(a, name)


def batch_size(*arrays: F64) -> int:
    """The common batch size of arrays whose first axis is N or 1."""
    n: int = max(a.shape[0] for a in arrays)
    for a in arrays:
        if a.shape[0] not in (1, n):
            raise ShapeError(f"batch sizes {[x.shape[0] for x in arrays]} do not broadcast")
    return n


def is_rotation(R: ArrayLike, atol: float = ROTATION_ATOL) -> NDArray[np.bool_]:
    """Whether each matrix is a proper rotation: ``RᵀR ≈ I`` and ``det R ≈ +1``.

    Args:
        R: (N, 3, 3) or (3, 3) matrices.
        atol: Largest allowed absolute deviation of any entry of ``RᵀR − I`` and of ``det R − 1``.

    Returns:
        (N,) bool.
    """
    a = as_rotations(R)
    gram = np.einsum("nki,nkj->nij", a, a)
    ortho = np.abs(gram - np.eye(3)).max(axis=(1, 2)) <= atol
    det = np.abs(np.linalg.det(a) - 1.0) <= atol
    result: NDArray[np.bool_] = ortho & det
    return result


def transform_pts(pts: F64, R: F64, t: F64) -> F64:
    """Apply poses to points: ``R @ x + t``.

    Args:
        pts: (V, 3) points in the model frame, mm.
        R: (N, 3, 3) rotations.
        t: (N, 3) translations, mm.

    Returns:
        (N, V, 3) points in the camera frame, mm.
    """
    result: F64 = np.einsum("nij,vj->nvi", R, pts) + t[:, None, :]
    return result


def project_pts(pts: F64, K: F64, R: F64, t: F64) -> F64:
    """Project model points with ``K [R | t]`` as the reference toolkit does.

    Points behind the camera are projected as they are (no z check), z = 0 gives inf/nan,
    exactly like ``bop_toolkit_lib.misc.project_pts``.

    Args:
        pts: (V, 3) model points, mm.
        K: (N, 3, 3) camera matrices.
        R: (N, 3, 3) rotations.
        t: (N, 3) translations, mm.

    Returns:
        (N, V, 2) pixel coordinates (u, v).
    """
    P = np.matmul(K, np.concatenate([R, t[:, :, None]], axis=2))  # (N, 3, 4)
    uvw = np.einsum("nij,vj->nvi", P[:, :, :3], pts) + P[:, None, :, 3]
    result: F64 = uvw[..., :2] / uvw[..., 2:3]
    return result


def rotation_about_axis(axis: ArrayLike, angle: float) -> F64:
    """Rotation matrix of ``angle`` radians about ``axis`` (normalised), Rodrigues' formula.

    Evaluated in the same order as ``bop_toolkit_lib.transform.rotation_matrix`` (diagonal
    cos, plus outer product times (1 − cos), plus sin times the cross-product matrix), so the
    symmetry sets built from it match the reference toolkit's to the last bit.
    """
    import math

    d = np.asarray(axis, dtype=np.float64)[:3]
    d = d / math.sqrt(float(np.dot(d, d)))
    sina, cosa = math.sin(angle), math.cos(angle)
    Rm = np.diag([cosa, cosa, cosa])
    Rm += np.outer(d, d) * (1.0 - cosa)
    d = d * sina
    Rm += np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    return Rm


def depth_to_distance(depth: ArrayLike, K: ArrayLike, origin: tuple[int, int] = (0, 0)) -> F64:
    """Convert a depth image (z, mm) to a distance image (‖X‖ from the camera centre, mm).

    Uses the integer pixel index (no +0.5), as ``bop_toolkit_lib.misc.depth_im_to_dist_im_fast``.
    Pixels with depth 0 stay 0.

    Args:
        depth: (H, W) depth in mm, or a window of a larger image.
        K: (3, 3) camera matrix of the full image.
        origin: (row, column) of the window's top-left pixel in the full image; the values
            are bit-identical to those of the full-image conversion.

    Returns:
        (H, W) float64 distances in mm.
    """
    d = np.asarray(depth)
    Km = np.asarray(K, dtype=np.float64)
    h, w = d.shape
    r0, c0 = origin
    xs = (np.arange(c0, c0 + w) - Km[0, 2]) / np.float64(Km[0, 0])
    ys = (np.arange(r0, r0 + h) - Km[1, 2]) / np.float64(Km[1, 1])
    result: F64 = np.sqrt(
        np.multiply(xs[None, :], d) ** 2
        + np.multiply(ys[:, None], d) ** 2
        + d.astype(np.float64) ** 2
    )
    return result


def intrinsics_from_fov(width: int, height: int, fov_y: float) -> F64:
    """Pinhole K (px) of a ``width``×``height`` camera with vertical field of view ``fov_y`` rad.

    ``f = H / (2 tan(fov_y / 2))``, square pixels, principal point at the image centre
    (the convention of the surgical simulator's cameras).
    """
    f = (height / 2) / np.tan(fov_y / 2)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
