"""Model silhouettes by filling projected triangles (OpenCV, sub-pixel vertex precision).

The union of a mesh's projected triangles is its silhouette; no depth buffer is needed, so
this serves pictures (overlays) and the embedded example, not visibility (which needs depth
and lives in :mod:`bopsurg.visibility`).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from bopsurg.geometry import project_pts

#: Fractional bits of the fixed-point vertex coordinates given to ``cv2.fillConvexPoly``.
SUBPIXEL_BITS = 4


def is_closed(faces: NDArray[np.int64]) -> bool:
    """Whether every edge of the mesh is shared by exactly two triangles (a closed surface)."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(len(counts)) and bool(np.all(counts == 2))


def project_silhouette(
    pts: NDArray[np.float64],
    faces: NDArray[np.int64],
    K: NDArray[np.float64],
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    shape: tuple[int, int],
    *,
    closed: bool = False,
) -> NDArray[np.bool_]:
    """Silhouette of a mesh at pose (R, t mm) under K (px), (H, W) bool.

    Args:
        pts, faces: (V, 3) mm and (F, 3) vertex indices.
        K: (3, 3) camera matrix (shift its principal point to render a larger canvas).
        R, t: Model-to-camera rotation and translation, mm.
        shape: (H, W) of the canvas.
        closed: The mesh is closed: then the triangles of one winding in the image already
            cover the silhouette (every silhouette ray enters and leaves the surface), so only
            those are filled, half the work; edges may differ by a pixel.
    """
    mask = np.zeros(shape, np.uint8)
    if t[2] <= 0:
        return mask.astype(bool)
    uv = project_pts(pts, K[None], R[None], t[None])[0]
    if not np.all(np.isfinite(uv)):
        return mask.astype(bool)
    h, w = shape
    uv = np.clip(uv, -4 * max(h, w), 4 * max(h, w))  # keep the fixed-point coordinates in range
    tri = np.round(uv * (1 << SUBPIXEL_BITS)).astype(np.int32)[faces]
    if closed:
        d1 = (tri[:, 1] - tri[:, 0]).astype(np.int64)
        d2 = (tri[:, 2] - tri[:, 0]).astype(np.int64)
        cross = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
        tri = tri[cross > 0] if (cross > 0).sum() <= (cross < 0).sum() else tri[cross < 0]
    for poly in tri:  # OpenCV fills one convex polygon per call
        cv2.fillConvexPoly(mask, poly, 1, lineType=cv2.LINE_8, shift=SUBPIXEL_BITS)
    return mask.astype(bool)
