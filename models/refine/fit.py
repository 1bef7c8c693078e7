"""Least-squares fit of the exact needle arc to foreground evidence at full image resolution.

The needle's centre line is a circular arc of known radius and extent in the model XY plane
(:mod:`bopsurg.needle`). Its projection must explain the foreground pixels of the image and
lie on them; robust residuals in image px, in both directions, say so:

- *reverse* (evidence → model): every foreground pixel's distance to the projected wire, a
  tube of the wire's radius (``wire_radius · f / z`` px) around the projected centre line (a
  polyline), linearised point-to-line as in ICP; zero inside the tube. The silhouette of a
  wire is its centre line dilated by that radius, not the line itself: where the arc's
  projection turns back (a needle seen edge-on) or ends, the foreground runs a wire radius
  past the centre line, and a line-only residual lengthens the arc, i.e. pulls it closer
  (measured at the true pose on ground-truth masks seen edge-on: 3 mm median, up to 20 mm).
- *forward* (model → evidence): the distance transform of the evidence sampled at the
  projected centre-line points, so the arc does not run past the needle's ends, and the
  signed distance to the evidence's outline sampled on the tube's two sides, so the tube is
  as wide as the wire in the image: its width is a depth cue of its own, the only one left
  when the arc is seen edge-on. Occluded parts are far from any evidence; a redescending
  (Geman-McClure) loss makes them cost a constant without pulling the arc towards the
  visible part.

Gauss-Newton with Levenberg-Marquardt damping and analytic Jacobians runs several starts in
lockstep (vectorised over starts): the network's pose and its mirror image through the line
of sight (a circle and its tilt-mirrored twin project to the same ellipse). The best start
wins only if its cost beats the cost of the network's own pose; otherwise the caller keeps
the network's pose. Units: mm, px; poses model-to-camera, ``x_cam = R x_model + t``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from bopsurg.bop.dataset import BopDataset
from bopsurg.errors import BopsurgError
from bopsurg.models.refine.lm import levenberg_marquardt
from bopsurg.models.refine.wire3d import wire_residuals

F64 = NDArray[np.float64]

#: Fewest foreground pixels a fit needs; fewer and the pose is left as it is.
MIN_EVIDENCE = 12


@dataclass(frozen=True)
class ArcModel:
    """The needle's centre line: an arc of ``radius`` mm from angle 0 (tail) to ``arc_rad``,
    and its wire: radius ``wire_radius`` mm, tapering to a point over the last ``tip_rad``."""

    radius: float = 10.18
    arc_rad: float = float(np.deg2rad(128.5))
    wire_radius: float = 0.36
    tip_rad: float = float(np.deg2rad(8.5))

    @classmethod
    def from_keypoints(cls, tail: F64, tip: F64) -> ArcModel:
        """The arc of a :func:`bopsurg.needle.needle_mesh` model from its tail and tip (mm).

        The tail-cap centre lies on the centre line at angle 0 and the tip at the arc's end.
        """
        tail, tip = np.asarray(tail, float), np.asarray(tip, float)
        radius = float(np.hypot(tail[0], tail[1]))
        arc = float(np.arctan2(tip[1], tip[0]) % (2 * np.pi))
        if not (radius > 0 and arc > 0):
            raise ValueError(f"keypoints do not describe an arc (tail {tail}, tip {tip})")
        return cls(radius=radius, arc_rad=arc)

    def points(self, n: int) -> F64:
        """(n, 3) centre-line points from tail to tip, mm."""
        s = np.linspace(0.0, self.arc_rad, n)
        return np.stack([self.radius * np.cos(s), self.radius * np.sin(s), np.zeros(n)], axis=1)

    def wire_radii(self, n: int) -> F64:
        """(n,) wire radius at the :meth:`points`, mm (linear taper to 0 at the tip)."""
        s = np.linspace(0.0, self.arc_rad, n)
        taper = np.clip((self.arc_rad - s) / max(self.tip_rad, 1e-9), 0.0, 1.0)
        return self.wire_radius * taper


def dataset_arc(dataset: BopDataset, obj_id: int) -> ArcModel:
    """The arc of needle ``obj_id`` of a dataset, from its ``models_info`` tip and tail
    keypoints.

    Raises:
        BopsurgError: The keypoints are missing or do not describe an arc (one line naming
            models_info.json).
    """
    try:
        kp = dataset.models_info[obj_id]["keypoints"]
        return ArcModel.from_keypoints(kp["tail"], kp["tip"])
    except (KeyError, ValueError) as err:
        raise BopsurgError(
            f"{dataset.models_dir / 'models_info.json'}: obj {obj_id} needs tip and tail "
            f"keypoints ({err})"
        ) from err


@dataclass(frozen=True)
class Evidence:
    """Foreground evidence of one ROI, on a square grid of image px.

    Grid pixel (row i, col j) sits at image ``(x0 + j·step, y0 + i·step)`` (OpenCV pixel
    centres), the convention of :func:`bopsurg.models.pose.roi.roi_grid_to_image`.

    Attributes:
        points: (N, 2) image px of the foreground grid pixels used by the reverse term.
        dist: (S, S) distance (image px) of every grid pixel to the nearest foreground pixel.
        grad: (2, S, S) its gradient along image x and y (per image px).
        origin: (2,) image px of grid pixel (0, 0).
        step: image px per grid pixel.
        sdf: (S, S) signed distance (image px) to the foreground's outline, negative inside;
            bilinear interpolation crosses 0 half-way between a foreground pixel and its
            background neighbour, where the outline lies.
        sdf_grad: (2, S, S) its gradient along image x and y.
    """

    points: F64
    dist: F64
    grad: F64
    origin: F64
    step: float
    sdf: F64
    sdf_grad: F64

    @classmethod
    def from_mask(
        cls,
        mask: NDArray[np.bool_],
        origin: F64,
        step: float,
        max_points: int = 400,
        explain: NDArray[np.bool_] | None = None,
    ) -> Evidence:
        """Evidence from a boolean foreground grid; at most ``max_points`` pixels, evenly
        strided in scan order (deterministic) for the reverse term.

        ``explain`` (same grid; default ``mask``) names the pixels the wire must explain (the
        reverse term), while ``mask`` sets where it may lie (the distance and outline terms):
        the visible and the full (amodal) mask of a needle, so that a wrongly completed hidden
        part is not pulled on, and the arc may still run behind an occluder."""
        import cv2  # the core's dependency; imported here to keep module import light

        mask = np.asarray(mask, bool)
        rows, cols = np.nonzero(mask if explain is None else np.asarray(explain, bool))
        if len(rows) > max_points:
            keep = np.linspace(0, len(rows) - 1, max_points).round().astype(np.int64)
            rows, cols = rows[keep], cols[keep]
        origin = np.asarray(origin, float)
        points = origin + step * np.stack([cols, rows], axis=1).astype(np.float64)
        if mask.any():
            bg = (~mask).astype(np.uint8)
            dist = cv2.distanceTransform(bg, cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(float)
            inside = cv2.distanceTransform(
                mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
            ).astype(float)
        else:
            dist = np.full(mask.shape, float(max(mask.shape)))
            inside = np.zeros(mask.shape)
        dist *= step
        sdf = dist - step * inside
        gy, gx = np.gradient(dist, step)
        sy, sx = np.gradient(sdf, step)
        return cls(points, dist, np.stack([gx, gy]), origin, float(step), sdf, np.stack([sx, sy]))

    @property
    def size(self) -> int:
        """Number of foreground pixels in the reverse term."""
        return int(self.points.shape[0])

    @cached_property
    def distance_stack(self) -> F64:
        """(3, S, S): ``dist`` and its x, y gradient, sampled together (one gather, not 3)."""
        return np.concatenate([self.dist[None], self.grad])

    @cached_property
    def outline_stack(self) -> F64:
        """(3, S, S): ``sdf`` and its x, y gradient."""
        return np.concatenate([self.sdf[None], self.sdf_grad])


@dataclass(frozen=True)
class FitSettings:
    """Knobs of :func:`refine_pose` (px for scales)."""

    samples: int = 40  # centre-line points of the model polyline
    iterations: int = 12
    scale_reverse: float = 2.0  # Cauchy scale of the evidence → line distances, px
    # Geman-McClure (redescending) scale of the line → evidence distances, px: a centre-line
    # sample behind an occluder lies far from the visible evidence and must neither cost
    # more the farther it is nor pull the arc; a Cauchy loss still pulls with force ~1/r,
    # which shrinks and shifts the arc towards the visible part. Started at the true pose on
    # ground-truth visible masks, without prior, the median depth drift is 5.8 mm with
    # Cauchy at 3 px, 4.3 mm with this loss at 3 px, 3.0 mm at 1.5 px (the rest is arcs
    # seen edge-on, where the image does not fix the depth and the prior must). With the
    # tube below, the same drift is 1.1 mm (232 held-out needles; a scratch script, no bench)
    scale_forward: float = 1.5
    forward_weight: float = 1.0  # weight of the forward term's mean against the reverse one
    # the wire as a tube: the reverse term measures to the tube, the outline term samples
    # the tube's sides; off, the centre line alone explains the foreground (the first fit).
    # bench_refine on the 478 held-out needles, from the pose head's poses: segmenter masks RE
    # 5.44 -> 4.92 deg, MSSD 3.54 -> 3.41 mm, TE 2.85 -> 2.98 mm; ground-truth masks RE 4.77 ->
    # 3.79 deg, TE 2.84 -> 2.63 mm, MSSD 3.52 -> 2.97 mm
    tube: bool = True
    scale_outline: float = 1.0  # Geman-McClure scale of the tube-side residuals, px
    outline_weight: float = 1.0  # weight of the outline term's mean against the reverse one
    lambda0: float = 1e-3  # initial LM damping (relative to the diagonal)
    mirror_start: bool = False  # also start from the tilt-mirrored pose
    # Gaussian prior around the start (the network's pose, its typical errors): the image pins
    # the arc's projection, not its depth when the arc is seen edge-on, where depth and the
    # rotation in the arc's plane trade off; the prior keeps those directions where they were.
    # The tube's unbiased image cost needs less of it: 0.3 (the first fit's) gives TE 3.30 mm,
    # 0.05 gives 3.00 mm, 0.02 gives 3.12 mm (every 2nd held-out image, GT visible boxes; a
    # scratch sweep: bench_refine --fit prior_weight=... redoes it with the detector's boxes)
    prior_deg: float = 8.0
    prior_mm: tuple[float, float, float] = (1.5, 1.5, 4.0)  # camera x, y, z
    prior_weight: float = 0.05  # against the mean image cost (px²-like units)
    # Out-of-domain guard: the fitted wire must explain this share of the evidence pixels
    # (within explained_tol_px of its tube), else the network's pose is kept. A segmenter
    # that marks a groove or an instrument edge as needle makes a fit that leaves much of
    # its mask unexplained. On the seven AMBF frames (bench_transfer, oracle boxes) 0.7 takes
    # the median TE from 25.4 to 15.3 mm (the network's); on the model card's 478 held-out
    # needles (bench_refine) it kept 22 of 499 fits: RE 4.92 deg either way, TE 2.98 -> 2.97
    # mm, MSSD 3.41 -> 3.40 mm. 0 turns the guard off.
    min_explained: float = 0.7
    explained_tol_px: float = 1.5
    # The refiner (:class:`~bopsurg.models.refine.refiner.NeedleRefiner`) resamples the
    # evidence probabilities this many times finer (bilinear) before the 0.5 threshold: the
    # outline then falls between grid pixels, where the probabilities cross 0.5, instead of
    # on the grid, and the wire's width and the arc's size (the depth cues) are read finer.
    # It pays where the grid is about an image pixel, as the segmenter's is (the estimator's
    # REFINE_FIT says by how much); 1 uses the grid as it is.
    evidence_upsample: int = 1
    # RGB-D: with camera points of the wire's visible pixels (``refine_pose``'s ``points``,
    # from a depth image) a third term measures each point's distance to the wire's surface
    # (:mod:`.wire3d`), mm, Cauchy at ``depth_scale_mm``, its mean weighted by
    # ``depth_weight`` against the image terms' (px²-like; 1 mm is about 7 px at 50 mm).
    # The image alone cannot tell the arc's tilt from its mirror's, the points can: with
    # points the fit also starts from the tilt mirror.
    depth_weight: float = 16.0
    depth_scale_mm: float = 0.5
    # The network's pose as the prior's centre is right where the network is (our renders)
    # and wrong where it is lost (another renderer). With points, the fit is also run with
    # each start's prior on itself (``refine_pose(own_priors=True)``), and that fit is kept
    # only when it puts clearly more of the points on its wire (within depth_inlier_mm): a
    # share larger by depth_unheld_share.
    depth_inlier_mm: float = 0.5
    depth_unheld_share: float = 0.15
    # A network whose own pose puts fewer than depth_lost_share of the points within
    # depth_lost_mm of its wire is lost (on our renders 7 % of the needles, median 6.9 deg /
    # 4.7 mm off; on the AMBF frames six of seven, 39-137 deg off): there the fit without
    # its prior needs only depth_unheld_share_lost more points on its wire.
    depth_lost_mm: float = 1.5
    depth_lost_share: float = 0.05
    depth_unheld_share_lost: float = 0.05


@dataclass(frozen=True)
class FitResult:
    """Outcome of one fit: the pose (the start's when not ``improved``) and the costs."""

    R: F64
    t: F64
    cost: float
    start_cost: float
    improved: bool


def cauchy(r: F64, c: float) -> tuple[F64, F64]:
    """Cauchy loss ρ(r) = c²/2 · log(1 + (r/c)²) and its IRLS weight ρ'(r)/r."""
    q = (r / c) ** 2
    return 0.5 * c * c * np.log1p(q), 1.0 / (1.0 + q)


def _geman_mcclure(r: F64, c: float) -> tuple[F64, F64]:
    """Geman-McClure loss ρ(r) = c²/2 · r²/(c² + r²) and its IRLS weight ρ'(r)/r.

    Redescending: a residual far beyond ``c`` costs a constant and pulls with ~zero force.
    """
    q = (r / c) ** 2
    return 0.5 * c * c * q / (1.0 + q), 1.0 / (1.0 + q) ** 2


def _skew(v: F64) -> F64:
    """(..., 3) → (..., 3, 3) cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def _exp_so3(w: F64) -> F64:
    """(..., 3) rotation vectors → (..., 3, 3) rotations (Rodrigues)."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    Kx = _skew(w)
    small = theta < 1e-12
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)
    b = np.where(small, 0.5, (1.0 - np.cos(th)) / th**2)
    return np.eye(3) + a * Kx + b * (Kx @ Kx)


def _on_segments(p: F64, a: F64, ab: F64) -> tuple[F64, F64]:
    """Closest points of segments ``a + τ·ab`` (τ in [0, 1]) to points ``p`` (broadcast over
    the leading axes): τ and ``p`` minus the closest point."""
    ap = p - a
    tau = np.clip((ap * ab).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12), 0.0, 1.0)
    return tau, ap - tau[..., None] * ab


def _bilinear(grid: F64, xy: F64) -> F64:
    """Sample (..., S, S) grids at (B, M, 2) grid coordinates (clamped to the border)."""
    S = grid.shape[-1]
    x = np.clip(xy[..., 0], 0.0, S - 1.0)
    y = np.clip(xy[..., 1], 0.0, S - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), S - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), S - 2)
    fx, fy = x - x0, y - y0
    g00, g01 = grid[..., y0, x0], grid[..., y0, x0 + 1]
    g10, g11 = grid[..., y0 + 1, x0], grid[..., y0 + 1, x0 + 1]
    return (g00 * (1 - fx) + g01 * fx) * (1 - fy) + (g10 * (1 - fx) + g11 * fx) * fy


class _Problem:
    """Residuals, costs and Jacobians for a batch of poses against one evidence."""

    def __init__(
        self, arc: ArcModel, ev: Evidence, K: F64, s: FitSettings, points: F64 | None = None
    ) -> None:
        self.model, self.ev, self.K, self.s = arc.points(s.samples), ev, K, s
        self.arc, self.points = arc, points
        self.wire_mm = arc.wire_radii(s.samples)  # the wire itself (what explains pixels)
        self.wire = self.wire_mm if s.tube else np.zeros(s.samples)  # what the cost fits
        self.fx, self.fy = K[0, 0], K[1, 1]

    def project(self, R: F64, t: F64) -> tuple[F64, F64, F64]:
        """Camera points (B, M, 3), their object-centred part R·X (B, M, 3), pixels (B, M, 2)."""
        rx = np.einsum("bij,mj->bmi", R, self.model)
        X = rx + t[:, None, :]
        z = np.maximum(X[..., 2], 1e-6)
        uv = np.stack(
            [
                self.fx * X[..., 0] / z + self.K[0, 1] * X[..., 1] / z + self.K[0, 2],
                self.fy * X[..., 1] / z + self.K[1, 2],
            ],
            -1,
        )
        return X, rx, uv

    def jac_points(self, X: F64, rx: F64) -> F64:
        """d(pixel)/d(ω, δt) of each model point, (B, M, 2, 6) for X → exp(ω)·rx + t + δt."""
        z = np.maximum(X[..., 2], 1e-6)
        P = np.zeros((*X.shape[:-1], 2, 3))
        P[..., 0, 0] = self.fx / z
        P[..., 0, 1] = self.K[0, 1] / z
        P[..., 0, 2] = -(self.fx * X[..., 0] + self.K[0, 1] * X[..., 1]) / z**2
        P[..., 1, 1] = self.fy / z
        P[..., 1, 2] = -self.fy * X[..., 1] / z**2
        dX = np.concatenate([-_skew(rx), np.broadcast_to(np.eye(3), (*X.shape[:-1], 3, 3))], -1)
        return P @ dX

    def wire_px(self, X: F64, rx: F64) -> tuple[F64, F64]:
        """Wire radius in image px at each model point (B, M) and its d/d(ω, δt) (B, M, 6)."""
        z = np.maximum(X[..., 2], 1e-6)
        rho = self.radius_px(self.wire, z)
        dz = np.zeros((*X.shape[:-1], 6))  # dz/dω = (R·X)_y, −(R·X)_x, 0; dz/dδt = (0, 0, 1)
        dz[..., 0], dz[..., 1], dz[..., 5] = rx[..., 1], -rx[..., 0], 1.0
        return rho, -(rho / z)[..., None] * dz

    def radius_px(self, wire_mm: F64, z: F64) -> F64:
        """Image radius (px) of wire radii ``wire_mm`` at depths ``z`` mm."""
        return wire_mm * np.sqrt(self.fx * self.fy) / z

    def explained(self, R: F64, t: F64, tol_px: float) -> float:
        """Share of the evidence pixels within ``tol_px`` of the projected wire's tube at the
        pose ``R`` (3, 3), ``t`` (3,) mm."""
        X, _, uv = self.project(R[None], t[None])
        rho = self.radius_px(self.wire_mm, np.maximum(X[0, :, 2], 1e-6))
        a, ab = uv[0, :-1], np.diff(uv[0], axis=0)  # (M-1, 2) segments
        tau, diff = _on_segments(self.ev.points[:, None, :], a[None], ab[None])  # (N, M-1)
        d = np.linalg.norm(diff, axis=-1)
        tube = (1 - tau) * rho[:-1] + tau * rho[1:]
        return float(((d - tube) <= tol_px).any(axis=1).mean())

    def evaluate(
        self, R: F64, t: F64, with_jacobian: bool
    ) -> tuple[F64, F64 | None, F64 | None, F64 | None]:
        """Robust image cost (B,) and, with the Jacobian, residuals (B, N+3M), IRLS weights and
        J (B, N+3M, 6)."""
        s, ev = self.s, self.ev
        X, rx, uv = self.project(R, t)
        rho, drho = self.wire_px(X, rx)
        e = ev.points  # (N, 2)
        n, m = e.shape[0], uv.shape[1]
        # nearest centre-line sample, then the closest point on its two adjacent segments:
        # O(N·M) small arithmetic instead of a point-to-every-segment distance
        d2s = (e**2).sum(-1)[None, :, None] + (uv**2).sum(-1)[:, None, :]
        d2s = d2s - 2.0 * np.einsum("nk,bmk->bnm", e, uv)
        k0 = d2s.argmin(-1)  # (B, N)
        seg = np.clip(np.stack([k0 - 1, k0], -1), 0, m - 2)  # (B, N, 2) candidate segments
        bi = np.arange(len(R))[:, None, None]
        a, b = uv[bi, seg], uv[bi, seg + 1]  # (B, N, 2, 2)
        ab = b - a
        tau, diff = _on_segments(e[None, :, None, :], a, ab)
        d2 = (diff**2).sum(-1)
        pick = d2.argmin(-1)[..., None]  # (B, N, 1)
        d_line = np.sqrt(np.take_along_axis(d2, pick, -1)[..., 0])
        k = np.take_along_axis(seg, pick, -1)[..., 0]  # (B, N) chosen segment
        tk = np.take_along_axis(tau, pick, -1)  # (B, N, 1)
        bj = np.arange(len(R))[:, None]
        rho_c = (1 - tk[..., 0]) * rho[bj, k] + tk[..., 0] * rho[bj, k + 1]
        d_rev = np.maximum(d_line - rho_c, 0.0)  # zero inside the tube
        grid_xy = (uv - ev.origin) / ev.step
        fwd = _bilinear(ev.distance_stack, grid_xy)  # (3, B, M): distance, d/dx, d/dy
        d_fwd = fwd[0]
        # the tube's two sides: ±rho along the projected centre line's normal
        tangent = np.gradient(uv, axis=1)  # (B, M, 2), px per sample
        t_len = np.linalg.norm(tangent, axis=-1, keepdims=True)
        normal = np.stack([-tangent[..., 1], tangent[..., 0]], -1) / np.maximum(t_len, 1e-9)
        sides = np.concatenate([uv + rho[..., None] * normal, uv - rho[..., None] * normal], 1)
        side_xy = (sides - ev.origin) / ev.step
        side = _bilinear(ev.outline_stack, side_xy)  # (3, B, 2M): signed distance, d/dx, d/dy
        d_side = side[0]
        # a side is defined where the centre line runs across the view (not where it turns
        # back towards the camera) and the wire is wider than a pixel
        use = (t_len[..., 0] > 0.25) & (rho > 0.5) & s.tube
        use2 = np.concatenate([use, use], 1)
        rho_r, w_r = cauchy(d_rev, s.scale_reverse)
        rho_f, w_f = _geman_mcclure(d_fwd, s.scale_forward)
        rho_s, w_s = _geman_mcclure(d_side, s.scale_outline)
        rho_s = np.where(use2, rho_s, 0.0)
        cost = rho_r.mean(-1) + s.forward_weight * rho_f.mean(-1)
        cost = cost + s.outline_weight * rho_s.sum(-1) / (2 * m)
        if self.points is not None:
            r_d, J_d = wire_residuals(R, t, self.points, self.arc)
            rho_d, w_d = cauchy(r_d, s.depth_scale_mm)
            cost = cost + s.depth_weight * rho_d.mean(-1)
        if not with_jacobian:
            return cost, None, None, None
        # reverse: r = û·(e − c) − rho_c with c the closest point (moving with the pose) and û
        # the segment normal towards e, or the direction from c where c is an end of the arc
        dv = np.take_along_axis(diff, pick[..., None], -2)[..., 0, :]  # e − c, (B, N, 2)
        sv = np.take_along_axis(ab, pick[..., None], -2)[..., 0, :]
        Jp = self.jac_points(X, rx)  # (B, M, 2, 6)
        Jc = (1 - tk[..., None]) * Jp[bj, k] + tk[..., None] * Jp[bj, k + 1]  # (B, N, 2, 6)
        seg_n = np.stack([-sv[..., 1], sv[..., 0]], -1)
        seg_n /= np.maximum(np.linalg.norm(seg_n, axis=-1, keepdims=True), 1e-12)
        seg_n *= np.where((seg_n * dv).sum(-1, keepdims=True) < 0, -1.0, 1.0)
        interior = (tk > 0) & (tk < 1)
        unit = dv / np.maximum(d_line[..., None], 1e-9)
        u_hat = np.where(interior | (d_line[..., None] < 1e-9), seg_n, unit)
        drho_c = (1 - tk) * drho[bj, k] + tk * drho[bj, k + 1]  # (B, N, 6)
        J_rev = -np.einsum("bnk,bnkp->bnp", u_hat, Jc) - drho_c
        J_rev *= (d_rev > 0)[..., None]
        # forward: r = dist(uv); dr/dp = ∇dist · d(uv)/dp
        g = np.moveaxis(fwd[1:], 0, -1)
        J_fwd = np.einsum("bmk,bmkp->bmp", g, Jp)
        # sides: r = sdf(uv ± rho·n); the normal's own turn with the pose is left out
        gs = np.moveaxis(side[1:], 0, -1)
        Js = np.concatenate(
            [
                Jp + normal[..., None] * drho[..., None, :],
                Jp - normal[..., None] * drho[..., None, :],
            ],
            1,
        )
        J_side = np.einsum("bmk,bmkp->bmp", gs, Js)
        r = np.concatenate([d_rev, d_fwd, d_side], 1)
        w_side = s.outline_weight * np.where(use2, w_s, 0.0) / (2 * m)
        w = np.concatenate([w_r / n, s.forward_weight * w_f / m, w_side], 1)
        J = np.concatenate([J_rev, J_fwd, J_side], 1)
        if self.points is not None:
            r = np.concatenate([r, r_d], 1)
            w = np.concatenate([w, s.depth_weight * w_d / r_d.shape[1]], 1)
            J = np.concatenate([J, J_d], 1)
        return cost, r, w, J


def _log_so3(R: F64) -> F64:
    """(3, 3) rotation → rotation vector (angles below π)."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-9:
        return 0.5 * v
    return v * theta / (2.0 * np.sin(theta)) if theta < np.pi - 1e-6 else v * 0.0 + np.pi * _axis(R)


def _axis(R: F64) -> F64:
    """Rotation axis of a half-turn."""
    _, V = np.linalg.eigh(0.5 * (R + R.T))
    return V[:, -1]


def half_turn(arc: ArcModel) -> F64:
    """(3, 3) the half turn S about the arc's bisector (model frame): ``R S`` is the swapped
    pose of ``R`` (the arc's centre is the model origin, so ``t`` stays)."""
    b = np.array([np.cos(arc.arc_rad / 2), np.sin(arc.arc_rad / 2), 0.0])
    return 2.0 * np.outer(b, b) - np.eye(3)


def same_ends(R: F64, t: F64, R_ref: F64, t_ref: F64, arc: ArcModel) -> F64:
    """``R`` or its half turn (the same arc, tip and tail swapped; ``t`` stays): the one
    whose tip lies on the nearer line of sight to the tip of the pose ``(R_ref, t_ref)``.

    A fit of the arc's shape alone (to points, or from a tilt-mirrored start) cannot tell the
    ends apart; this keeps the reference's (the pose head's: the end check judges it after)."""
    tip = arc.points(2)[-1]

    def sight(v: F64) -> F64:
        return v / max(float(np.linalg.norm(v)), 1e-12)

    R_h = R @ half_turn(arc)
    seen = sight(R_ref @ tip + t_ref)
    return R_h if sight(R_h @ tip + t) @ seen > sight(R @ tip + t) @ seen else R


def mirror_pose(R: F64, t: F64) -> F64:
    """The rotation whose arc plane is ``R``'s mirrored through the line of sight to ``t``.

    A circle tilted by +θ or −θ about an axis across the line of sight projects to (almost)
    the same ellipse; this is the other branch of that two-fold ambiguity: the plane normal
    n goes to ``2(n·v)v − n`` (v the unit line of sight), by the smallest rotation.
    """
    v = t / np.linalg.norm(t)
    n = R[:, 2]
    n2 = 2.0 * (n @ v) * v - n
    axis = np.cross(n, n2)
    s, c = np.linalg.norm(axis), float(np.clip(n @ n2, -1.0, 1.0))
    if s < 1e-9:  # normal along the line of sight: the mirror is the pose itself
        return R.copy()
    return _exp_so3(axis / s * np.arctan2(s, c)) @ R


def refine_pose(
    R_init: F64,
    t_init: F64,
    K: F64,
    evidence: Evidence,
    arc: ArcModel,
    settings: FitSettings | None = None,
    points: F64 | None = None,
    starts: tuple[tuple[F64, F64], ...] = (),
    own_priors: bool = False,
) -> FitResult:
    """Fit the arc's pose to ``evidence``, starting from ``(R_init, t_init)`` (and its mirror).

    Args:
        R_init: (3, 3) starting rotation, model → camera.
        t_init: (3,) starting translation, mm.
        K: (3, 3) intrinsics, px.
        evidence: the ROI's foreground evidence.
        arc: the needle's centre line.
        settings: fit knobs (defaults when None).
        points: (N, 3) camera points of the wire's visible surface, mm (RGB-D: the depth term
            of :class:`FitSettings`; with them the fit also starts from the tilt mirror).
        starts: More starting poses (R (3, 3), t (3,) mm), e.g. a fit to the points alone.
        own_priors: With ``points``: centre each start's prior on itself instead of on the
            first start (the network's pose), so that a start far from it is not held back
            (for when the network's pose disagrees with the points).

    Returns:
        The fitted pose when it beats the start's cost (``improved``), else the start.
        Deterministic; never NaN (a non-finite fit returns the start).
    """
    s = settings or FitSettings()
    R_init, t_init, K = np.asarray(R_init, float), np.asarray(t_init, float), np.asarray(K, float)
    if evidence.size < MIN_EVIDENCE or not (
        np.isfinite(R_init).all() and np.isfinite(t_init).all()
    ):
        return FitResult(R_init, t_init, float("inf"), float("inf"), False)
    if points is not None:
        points = np.asarray(points, float).reshape(-1, 3)
    prob = _Problem(arc, evidence, K, s, points)
    mirror = s.mirror_start or points is not None
    R_starts = [R_init] + ([mirror_pose(R_init, t_init)] if mirror else [])
    t_starts = [t_init] * len(R_starts)
    for R_x, t_x in starts:
        R_starts.append(np.asarray(R_x, float))
        t_starts.append(np.asarray(t_x, float))
    # the data cost hardly tells tip from tail: every start takes the network's ends
    R_starts = [
        same_ends(R_x, t_x, R_init, t_init, arc)
        for R_x, t_x in zip(R_starts, t_starts, strict=True)
    ]
    R_s, t_s = np.stack(R_starts), np.stack(t_starts)
    # x = (ω, δt): R = exp(ω)·R_start, t = t_start + δt. The prior holds the directions the
    # image does not fix (depth, tilt) near the network's pose: every start pays its distance
    # from the first (ω = 0, δt = 0 there), unless ``own_priors``
    b = len(R_s)
    sigma = np.array([np.deg2rad(s.prior_deg)] * 3 + list(s.prior_mm), float)
    sq = np.sqrt(s.prior_weight) / sigma  # prior residual = sq · (x − x_prior)
    x_prior = np.zeros((b, 6))
    for i in range(1, 1 if own_priors and points is not None else b):
        x_prior[i, :3] = -_log_so3(R_s[i] @ R_init.T)
        x_prior[i, 3:] = t_init - t_s[i]

    def total(x: F64) -> tuple[F64, F64, F64, F64]:
        R, t = _exp_so3(x[:, :3]) @ R_s, t_s + x[:, 3:]
        c, r, w, J = prob.evaluate(R, t, True)
        rp = sq * (x - x_prior)
        return c + 0.5 * (rp**2).sum(-1), r, w, J  # type: ignore[return-value]

    start_cost = float(total(np.zeros((b, 6)))[0][0])
    prior_H = np.diag(sq**2)

    def prior(x: F64) -> tuple[F64, F64]:
        return prior_H, sq**2 * (x - x_prior)

    x, cost = levenberg_marquardt(
        total, np.zeros((b, 6)), np.add, s.iterations, s.lambda0, prior=prior
    )
    best = int(np.argmin(cost))
    R_best = _exp_so3(x[best, :3]) @ R_s[best]
    t_best = t_s[best] + x[best, 3:]
    ok = bool(np.isfinite(cost[best]) and cost[best] < start_cost)
    ok = ok and bool(np.isfinite(R_best).all() and np.isfinite(t_best).all())
    if not ok:
        return FitResult(R_init, t_init, start_cost, start_cost, False)
    U, _, Vt = np.linalg.svd(R_best)
    R_fit = U @ Vt
    if s.min_explained > 0 and prob.explained(R_fit, t_best, s.explained_tol_px) < s.min_explained:
        return FitResult(R_init, t_init, start_cost, start_cost, False)
    return FitResult(R_fit, t_best, float(cost[best]), start_cost, True)
