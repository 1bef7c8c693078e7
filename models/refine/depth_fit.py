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
- starts: the given pose (the pose head's), its tilt mirror (:func:`.arc.mirror_pose`) and a
  pose from the points alone (their plane and circle), Gauss-Newton with Levenberg-Marquardt
  damping, every start of every needle of a batch at once (batched torch, :mod:`.lm`); the
  cheapest start of a needle wins;
- the arc maps onto itself under the half turn about its bisector (tip and tail swapped), so
  the points cannot tell the ends apart: the fit keeps the given pose's (the end check,
  :mod:`.ends`, judges them after the stage);
- guard: too few points, points on one line, or too few of them on the fitted wire, and the
  given pose is kept.

Units: mm, px; poses model-to-camera in the estimator's needle frame (:class:`.arc.ArcModel`),
``x_cam = R x_model + t``; depth in mm, 0 where there is no reading.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from bopsurg.models.predict_config import PointsFitSettings
from bopsurg.models.refine.arc import ArcModel, exp_so3, mirror_pose, same_ends
from bopsurg.models.refine.fit import cauchy
from bopsurg.models.refine.lm import fit_threads, levenberg_marquardt, normal_equations
from bopsurg.models.refine.wire3d import (
    camera_normal_equations,
    stack_points,
    strided_points,
    wire_distances,
    wire_residuals_model,
)
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


class DepthFits(NamedTuple):
    """Results of :func:`fit_depths` for n ROIs (numpy, host): the fields of :class:`DepthFit`,
    stacked."""

    R: F64  # (n, 3, 3)
    t: F64  # (n, 3) mm
    inliers: F64  # (n,)
    points: NDArray[np.int64]  # (n,)
    used: NDArray[np.bool_]  # (n,)

    def row(self, i: int) -> DepthFit:
        """ROI ``i``'s result."""
        return DepthFit(
            self.R[i], self.t[i], float(self.inliers[i]), int(self.points[i]), bool(self.used[i])
        )


def _lm(
    R_start: Tensor,
    t_start: Tensor,
    roi: Tensor,
    P: tuple[Tensor, Tensor],
    arc: ArcModel,
    s: PointsFitSettings,
) -> tuple[Tensor, Tensor, Tensor]:
    """The Cauchy fit of the wire to each row's ROI's points ``P`` ((n, N, 3) mm, and which
    are real (n, N)) from B start rows (:func:`.lm.levenberg_marquardt`): R (B, 3, 3),
    t (B, 3) mm, robust cost (B,)."""
    points, ok = P[0][roi].transpose(1, 2).contiguous(), P[1][roi]  # by axis (B, 3, N)

    def objective(pose: tuple[Tensor, ...]) -> tuple[Tensor, Tensor, Tensor]:
        r, J = wire_residuals_model(pose[0], pose[1], points, arc)
        r = r * ok
        rho, w = cauchy(r, s.scale)
        H, g = normal_equations(r, w * ok, J, by_row=True)
        return (rho * ok).sum(-1), *camera_normal_equations(H, g, pose[0])

    def moved(pose: tuple[Tensor, ...], step: Tensor) -> tuple[Tensor, ...]:
        return exp_so3(step[:, :3]) @ pose[0], pose[1] + step[:, 3:]

    # no prior: the floor keeps a step for points that leave a direction free (a line)
    (R, t), cost = levenberg_marquardt(
        objective,
        (R_start, t_start),
        moved,
        s.iterations,
        s.lambda0,
        floor=1e-9,
        rtol=None,
        group=roi,
    )
    return R, t, cost


def _collinear(P: F64) -> bool:
    """Whether the points (N, 3) lie on one line (or one point): an arc through them is free
    to turn about that line. A wire's points never do (its surface has width)."""
    spread = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return bool(spread[1] <= 1e-6 * max(spread[0], 1e-9))


def fit_depths(
    R: F64,
    t: F64,
    P: Sequence[F64],
    arc: ArcModel,
    settings: PointsFitSettings | None = None,
    device: torch.device | str = "cpu",
) -> DepthFits:
    """The poses of n needles fitted to their wires' 3D points, all at once (see the module
    docstring).

    Args:
        R: (n, 3, 3) the starting rotations (the pose head's), model-to-camera.
        t: (n, 3) their translations, mm.
        P: per needle, (N, 3) camera points on the wire's visible surface, mm
            (:func:`.wire3d.depth_points`).
        arc: The needle's centre line.
        settings: Knobs.
        device: Where the fit runs (float64); on a CPU, on the calling thread with one
            intra-op thread (:func:`.lm.fit_threads`).

    Returns:
        Per needle the fitted pose, or the input one (``used`` False) where the guard
        refuses the fit.
    """
    s = settings or PointsFitSettings()
    R, t = np.asarray(R, float).reshape(-1, 3, 3), np.asarray(t, float).reshape(-1, 3)
    pts = [strided_points(np.asarray(p, float).reshape(-1, 3), s.max_points) for p in P]
    out = DepthFits(
        R.copy(),
        t.copy(),
        np.zeros(len(R)),
        np.array([len(p) for p in pts], np.int64),
        np.zeros(len(R), bool),
    )
    idx = [i for i, p in enumerate(pts) if len(p) >= s.min_points and not _collinear(p)]
    if not idx:
        return out
    dev, rows = torch.device(device), np.asarray(idx, np.int64)
    # preparation, once per needle: the pose from the points' own geometry
    geometric = [pose_from_points(pts[i], arc) for i in rows]
    R0, t0 = (torch.as_tensor(a[rows], device=dev) for a in (R, t))
    with fit_threads(dev):
        R_b, t_b, inliers, used = _fit_rows(R0, t0, [pts[i] for i in rows], geometric, arc, s)
    out.inliers[rows] = inliers.cpu().numpy()
    out.used[rows] = used.cpu().numpy()
    out.R[rows] = torch.where(used[:, None, None], R_b, R0).cpu().numpy()
    out.t[rows] = torch.where(used[:, None], t_b, t0).cpu().numpy()
    return out


def _fit_rows(
    R0: Tensor,  # noqa: N803 (math names)
    t0: Tensor,
    P: list[F64],
    geometric: list[tuple[F64, F64] | None],
    arc: ArcModel,
    s: PointsFitSettings,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`fit_depths` of k needles with points enough, from their poses ``R0`` (k, 3, 3),
    ``t0`` (k, 3) mm, their mirrors and their ``geometric`` poses: the best fits (R, t), their
    shares of inliers and whether that is enough (k,)."""
    dev, k = R0.device, len(R0)
    geo = [j for j, g in enumerate(geometric) if g is not None]
    rows = np.concatenate([np.arange(k), np.arange(k), geo]).astype(np.int64)
    order = torch.as_tensor(np.argsort(rows, kind="stable"), device=dev)
    geo_R = np.array([geometric[j][0] for j in geo]).reshape(-1, 3, 3)  # type: ignore[index]
    geo_t = np.array([geometric[j][1] for j in geo]).reshape(-1, 3)  # type: ignore[index]
    R_s = torch.cat([R0, mirror_pose(R0, t0), torch.as_tensor(geo_R, device=dev)])[order]
    t_s = torch.cat([t0, t0, torch.as_tensor(geo_t, device=dev)])[order]
    roi = torch.as_tensor(rows, device=dev)[order]
    stacked = stack_points(P, dev)
    R_f, t_f, cost = _lm(R_s, t_s, roi, stacked, arc, s)
    best = _first_best(cost, roi, k)
    # the points do not tell tip from tail: keep the start's ends
    R_b = same_ends(R_f[best], t_f[best], R0, t0, arc)
    t_b = t_f[best]
    near = wire_distances(R_b, t_b, stacked[0], arc).abs() <= s.inlier_mm
    inliers = (near & stacked[1]).sum(-1) / stacked[1].sum(-1)
    return R_b, t_b, inliers, inliers >= s.min_inliers


def _first_best(cost: Tensor, roi: Tensor, n: int) -> Tensor:
    """Each ROI's cheapest row (rows grouped by ROI; the first of equals, a NaN first)."""
    counts = torch.bincount(roi, minlength=n)
    first = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(roi), device=roi.device) - first[roi]
    table = torch.full((n, int(counts.max())), torch.inf, dtype=cost.dtype, device=cost.device)
    table[roi, slot] = torch.where(torch.isnan(cost), -torch.inf, cost)
    return first + table.argmin(-1)


def fit_depth(
    R: F64, t: F64, P: F64, arc: ArcModel, settings: PointsFitSettings | None = None
) -> DepthFit:
    """:func:`fit_depths` of one needle: ``R`` (3, 3), ``t`` (3,) mm, points ``P`` (N, 3) mm."""
    return fit_depths(
        np.asarray(R, float)[None], np.asarray(t, float)[None], [P], arc, settings
    ).row(0)
