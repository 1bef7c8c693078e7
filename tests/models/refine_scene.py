"""A small deterministic RGB-D scene for the needle refiner: three needles rendered from the
exact mesh into one 640 x 480 frame (their union is the segmenter's mask, the nearest wire
surface point per pixel the depth image), and pose-head starts off by known amounts.

The batched fit's reference outputs (``data/refine_reference.json``) were captured on this
scene from the per-ROI numpy fit it replaced; :func:`variants` names the settings each was
captured with (every depth point: that fit had no cap on them)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from bopsurg.models.predict_config import DepthSettings, FitSettings
from bopsurg.models.refine.arc import ArcModel
from bopsurg.needle import needle_mesh
from bopsurg.silhouette import project_silhouette

K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
MODEL = needle_mesh()
ARC = ArcModel.from_keypoints(MODEL.pts[0], MODEL.pts[-1])


def rot(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors → (..., 3, 3) rotations, numpy."""
    w = np.asarray(w, np.float64)
    return Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(*w.shape, 3)


def pose(view_deg: float, spin_deg: float, t: tuple[float, float, float]):
    """A needle whose arc plane is tilted ``view_deg`` from the line of sight."""
    R = rot(np.array([np.deg2rad(90.0 - view_deg), 0.0, 0.0])) @ rot(
        np.array([0.0, 0.0, np.deg2rad(spin_deg)])
    )
    return R, np.array(t, float)


def silhouette(R, t, k: int = 4) -> np.ndarray:
    """The needle's mask (480, 640): pixels at least half covered (a k x finer fill)."""
    Kf = np.diag([k, k, 1.0]) @ K
    Kf[:2, 2] += 0.5 * (k - 1)
    fine = project_silhouette(MODEL.pts, MODEL.faces, Kf, R, t, (480 * k, 640 * k), closed=True)
    return fine.reshape(480, k, 640, k).mean(axis=(1, 3)) >= 0.5


def depth_image(R, t, seed: int, n: int = 40_000) -> np.ndarray:
    """(480, 640) mm, 0 off the wire: its camera-facing surface, nearest sample per pixel."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(0, ARC.arc_rad, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    radial = np.stack([np.cos(s), np.sin(s), np.zeros(n)], axis=1)
    off = ARC.wire_radius * (np.cos(phi)[:, None] * radial + np.sin(phi)[:, None] * [0, 0, 1.0])
    P = (ARC.radius * radial + off) @ R.T + t
    P = P[np.einsum("ni,ni->n", off @ R.T, P) < 0]
    uv = np.round((P @ K.T)[:, :2] / P[:, 2:]).astype(int)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    depth = np.full((480, 640), np.inf)
    np.minimum.at(depth, (uv[ok, 1], uv[ok, 0]), P[ok, 2])
    depth[~np.isfinite(depth)] = 0.0
    return depth


class Scene(NamedTuple):
    """Masks (visible, full) (480, 640), depth (480, 640) mm, boxes (n, 4) px, GT and start
    poses (n, 3, 3), (n, 3) mm."""

    visible: np.ndarray
    full: np.ndarray
    depth: np.ndarray
    boxes: np.ndarray
    R: np.ndarray
    t: np.ndarray
    R0: np.ndarray
    t0: np.ndarray


def scene() -> Scene:
    """Three needles; the third's right quarter hidden in the visible mask. Starts: 3 mm /
    5 deg off, 1 mm / 2 deg off, and lost (40 deg, 8 mm); a fourth ROI on an empty corner."""
    truth = [pose(30.0, 20.0, (-25.0, -12.0, 95.0)), pose(60.0, 110.0, (22.0, 10.0, 85.0))]
    truth.append(pose(45.0, 30.0, (-2.0, 8.0, 75.0)))
    full = np.zeros((480, 640), bool)
    visible = np.zeros((480, 640), bool)
    depth = np.zeros((480, 640))
    boxes = []
    for i, (R, t) in enumerate(truth):
        m = silhouette(R, t)
        ys, xs = np.nonzero(m)
        boxes.append([xs.min(), ys.min(), np.ptp(xs), np.ptp(ys)])
        full |= m
        v = m.copy()
        if i == 2:
            v[:, int(np.quantile(xs, 0.75)) :] = False
        visible |= v
        d = depth_image(R, t, seed=i)
        near = (d > 0) & ((depth == 0) | (d < depth))
        depth[near] = d[near]
    turns = [(0.0, 0.0, 5.0), (2.0, 0.0, 0.0), (0.0, 40.0, 0.0)]
    shifts = [(0.0, 0.0, 3.0), (0.5, -0.5, 0.5), (0.0, 0.0, 8.0)]
    R = np.stack([p[0] for p in truth])
    t = np.stack([p[1] for p in truth])
    R0 = np.stack([rot(np.deg2rad(np.array(w))) @ r for w, r in zip(turns, R, strict=True)])
    t0 = t + np.array(shifts)
    # a fourth box on an empty corner: too little evidence, the start stays
    boxes.append([560.0, 20.0, 50.0, 40.0])
    R, t = np.concatenate([R, R[:1]]), np.concatenate([t, [[28.0, -24.0, 90.0]]])
    R0, t0 = np.concatenate([R0, R[3:]]), np.concatenate([t0, t[3:]])
    return Scene(visible, full, depth, np.array(boxes, float), R, t, R0, t0)


#: ``DepthSettings.max_points`` that keeps every point of the scene (the reference fit's).
ALL_POINTS = 10**9


def variants() -> dict[str, tuple[FitSettings, DepthSettings, bool, bool]]:
    """Named (fit, depth settings, with depth, two mask planes) of the reference outputs."""
    fit, dep = FitSettings(), DepthSettings(max_points=ALL_POINTS)
    return {
        "rgb": (fit, dep, False, False),
        "rgbd": (fit, dep, True, False),
        "rgb_full": (fit, dep, False, True),
        "rgbd_full": (fit, dep, True, True),
    }
