"""Fit of the needle's arc to the depth image alone: the wire's visible pixels as 3D points.

The image fit (:mod:`.fit`) places the arc's projection; it cannot see which way the arc's
plane tilts (a circle and its mirror image through the line of sight project to almost the
same ellipse) and reads the depth from the wire's width, a few px. A depth image (every BOP
split carries one; a stereo endoscope gives one) settles both: each visible wire pixel,
back-projected with its depth, is a point on the wire's surface, within ``wire_radius`` of the
arc's centre line (:mod:`.wire3d`). This module fits the arc to those points alone; the
refinement stage uses the result as one more start of its RGB-D fit (:func:`.fit.refine_pose`
with ``points``), which also weighs the image:

- residual: a point's distance to the centre line less the wire's radius, mm; a Cauchy loss,
  so that pixels of the mask's rim that read the tissue behind the wire, or a thread, cost
  little;
- starts: the given pose (the pose head's), its tilt mirror (:func:`.fit.mirror_pose`) and a
  pose from the points alone (their plane and circle), Gauss-Newton with Levenberg-Marquardt
  damping in lockstep; the cheapest wins;
- the arc maps onto itself under the half turn about its bisector (tip and tail swapped), so
  the points cannot tell the ends apart: the fit keeps the given pose's (the end check,
  :mod:`.ends`, judges them after the stage);
- guard: too few points, points on one line, or too few of them on the fitted wire, and the
  given pose is kept.

Units: mm, px; poses model-to-camera in the estimator's needle frame (:class:`.arc.ArcModel`),
``x_cam = R x_model + t``; depth in mm, 0 where there is no reading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from bopsurg.models.predict_config import PointsFitSettings
from bopsurg.models.refine.arc import ArcModel, mirror_pose, same_ends
from bopsurg.models.refine.fit import cauchy
from bopsurg.models.refine.lm import levenberg_marquardt
from bopsurg.models.refine.wire3d import wire_distances, wire_residuals
from bopsurg.needle import fit_circle

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class DepthFit:
    """Result of :func:`fit_depth`.

    Attributes:
        R: (3, 3) rotation; the input's when not ``used``.
        t: (3,) translation, mm.
        inliers: Share of the points within ``inlier_mm`` of the fitted wire.
        points: Number of points fitted.
        used: Whether the fit replaced the input pose.
    """

    R: F64
    t: F64
    inliers: float
    points: int
    used: bool


def pose_from_points(P: F64, arc: ArcModel) -> tuple[F64, F64] | None:
    """A pose whose arc lies on the points ``P`` (N, 3), mm, from their geometry alone: the
    plane through them (least squares), the circle through them in it (algebraic fit; the
    descent then holds it to the arc's radius), the arc centred on the points' mean direction
    about it. Tip and tail are arbitrary. None when the points fix no circle."""
    if len(P) < 3:
        return None
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    e1, e2, n = vt
    xy = np.stack([(P - c) @ e1, (P - c) @ e2], axis=1)
    # the algebraic circle: robust enough to tissue points, and the descent refines it
    centre2 = np.array(fit_circle(xy[:, 0], xy[:, 1], iterations=0)[:2])
    d = xy - centre2
    mid = (d / np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]).mean(axis=0)
    if not (np.isfinite(centre2).all() and np.linalg.norm(mid) > 1e-6):
        return None
    # the arc runs counter-clockwise about n from its tail, centred on the points' direction
    tail = np.arctan2(mid[1], mid[0]) - arc.arc_rad / 2
    x_axis = np.cos(tail) * e1 + np.sin(tail) * e2
    R = np.stack([x_axis, np.cross(n, x_axis), n], axis=1)
    t = c + centre2[0] * e1 + centre2[1] * e2
    return R, t


def _lm(
    R_start: F64, t_start: F64, P: F64, arc: ArcModel, s: PointsFitSettings
) -> tuple[F64, F64, F64]:
    """The Cauchy fit of the wire to the points ``P`` from S starts in lockstep
    (:func:`.lm.levenberg_marquardt`): R (S, 3, 3), t (S, 3) mm, robust cost (S,)."""

    def objective(pose: tuple[F64, ...]) -> tuple[F64, F64, F64, F64]:
        r, J = wire_residuals(pose[0], pose[1], P, arc)
        rho, w = cauchy(r, s.scale)
        return rho.sum(axis=1), r, w, J

    def moved(pose: tuple[F64, ...], step: F64) -> tuple[F64, ...]:
        return Rotation.from_rotvec(step[:, :3]).as_matrix() @ pose[0], pose[1] + step[:, 3:]

    # no prior: the floor keeps a step for points that leave a direction free (a line)
    (R, t), cost = levenberg_marquardt(
        objective, (R_start, t_start), moved, s.iterations, s.lambda0, floor=1e-9, rtol=None
    )
    return R, t, cost


def _collinear(P: F64) -> bool:
    """Whether the points (N, 3) lie on one line (or one point): an arc through them is free
    to turn about that line. A wire's points never do (its surface has width)."""
    spread = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return bool(spread[1] <= 1e-6 * max(spread[0], 1e-9))


def fit_depth(
    R: F64, t: F64, P: F64, arc: ArcModel, settings: PointsFitSettings | None = None
) -> DepthFit:
    """The needle's pose fitted to its wire's 3D points (see the module docstring).

    Args:
        R: (3, 3) the starting rotation (the pose head's), model-to-camera.
        t: (3,) its translation, mm.
        P: (N, 3) camera points on the wire's visible surface, mm
            (:func:`.wire3d.depth_points`).
        arc: The needle's centre line.
        settings: Knobs.

    Returns:
        The fitted pose, or the input one (``used`` False) when the guard refuses the fit.
    """
    s = settings or PointsFitSettings()
    R, t = np.asarray(R, float), np.asarray(t, float)
    P = np.asarray(P, float).reshape(-1, 3)
    if len(P) > s.max_points:
        P = P[np.linspace(0, len(P) - 1, s.max_points).round().astype(np.int64)]
    if len(P) < s.min_points or _collinear(P):
        return DepthFit(R, t, 0.0, len(P), False)
    starts_R, starts_t = [R, mirror_pose(R, t)], [t, t]
    geometric = pose_from_points(P, arc)
    if geometric is not None:
        starts_R.append(geometric[0])
        starts_t.append(geometric[1])
    R_s, t_s, cost = _lm(np.stack(starts_R), np.stack(starts_t), P, arc, s)
    best = int(np.argmin(cost))
    R_b, t_b = R_s[best], t_s[best]
    # the points do not tell tip from tail: keep the start's ends
    R_b = same_ends(R_b, t_b, R, t, arc)
    inliers = float((np.abs(wire_distances(R_b[None], t_b[None], P, arc)[0]) <= s.inlier_mm).mean())
    if inliers < s.min_inliers:
        return DepthFit(R, t, inliers, len(P), False)
    return DepthFit(R_b, t_b, inliers, len(P), True)
