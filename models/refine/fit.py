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

Gauss-Newton with Levenberg-Marquardt damping and analytic Jacobians runs several starts of
every needle of a batch at once (:mod:`.lm`; batched torch on the caller's device): the
network's pose and its mirror image through the line of sight (a circle and its tilt-mirrored
twin project to the same ellipse). The best start of a needle wins only if its cost beats the
cost of the network's own pose; otherwise the caller keeps the network's pose. Each needle's
evidence is prepared once (numpy, cv2: :class:`Evidence`) and stacked (:class:`EvidenceBatch`);
everything the fit evaluates per iteration is batched over needles × starts.
Units: mm, px; poses model-to-camera, ``x_cam = R x_model + t``.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray
from torch import Tensor

from bopsurg.models.predict_config import DepthSettings, FitSettings
from bopsurg.models.refine.arc import ArcModel, exp_so3, log_so3, mirror_pose, same_ends
from bopsurg.models.refine.lm import fit_threads, levenberg_marquardt, normal_equations
from bopsurg.models.refine.wire3d import (
    camera_normal_equations,
    stack_points,
    wire_residuals_model,
)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Evidence:
    """Foreground evidence of one ROI, on a square grid of image px.

    Grid pixel (row i, col j) sits at image ``(x0 + j·step, y0 + i·step)`` (OpenCV pixel
    centres), the convention of :func:`bopsurg.models.pose.roi.roi_grid_to_image`.

    Attributes:
        points: (N, 2) image px of the foreground grid pixels used by the reverse term.
        dist: (S, S) distance (image px) of every grid pixel to the nearest foreground pixel.
        origin: (2,) image px of grid pixel (0, 0).
        step: image px per grid pixel.
        sdf: (S, S) signed distance (image px) to the foreground's outline, negative inside;
            bilinear interpolation crosses 0 half-way between a foreground pixel and its
            background neighbour, where the outline lies.

    The fit samples both maps and their gradients (``numpy.gradient``'s: central differences,
    one-sided at the border), the latter taken at the pixels it reads
    (:meth:`_Problem._bilinear`).
    """

    points: F64
    dist: F64
    origin: F64
    step: float
    sdf: F64

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
            dist *= step
            sdf = dist.copy()
            box = _inside_box(mask)  # the exact transform of the mask and its border alone
            inside = cv2.distanceTransform(
                mask[box].astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
            )
            sdf[box] -= step * inside.astype(float)
        else:
            dist = np.full(mask.shape, float(max(mask.shape))) * step
            sdf = dist - 0.0
        return cls(points, dist, origin, float(step), sdf)

    @property
    def size(self) -> int:
        """Number of foreground pixels in the reverse term."""
        return int(self.points.shape[0])


_HOST = threading.local()


def _host_buffer(shape: tuple[int, ...]) -> Tensor:
    """A float64 CPU tensor of ``shape`` on storage this thread reuses from call to call."""
    need = int(np.prod(shape))
    buf: Tensor | None = getattr(_HOST, "maps", None)
    if buf is None or buf.numel() < need:
        with torch.inference_mode(False):  # a normal tensor: writable in and out of that mode
            buf = torch.empty(need, dtype=torch.float64)
        _HOST.maps = buf
    return buf[:need].view(shape)


def _inside_box(mask: NDArray[np.bool_]) -> tuple[slice, slice]:
    """The foreground's bounding box grown by one pixel (within the grid): every foreground
    pixel's nearest background pixel lies in it (the box's ring is background, and a pixel
    outside it is farther than the ring's pixel nearest it), so an exact distance transform
    of the foreground on it equals the transform on the whole grid."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    h, w = mask.shape
    return (
        slice(max(rows[0] - 1, 0), min(rows[-1] + 2, h)),
        slice(max(cols[0] - 1, 0), min(cols[-1] + 2, w)),
    )


class EvidenceBatch(NamedTuple):
    """The evidence of n ROIs stacked for the batched fit (torch, one device, float64).

    Attributes:
        points: (n, N, 2) image px of each ROI's reverse-term pixels, padded to the most.
        valid: (n, N) bool: which of them are real.
        real: (n,) how many are real.
        maps: (2, n, S, S) distance and signed outline distance, padded to the largest grid
            side S.
        size: (n,) each grid's own side.
        origin: (n, 2) image px of grid pixel (0, 0).
        step: (n,) image px per grid pixel.
    """

    points: Tensor
    valid: Tensor
    real: Tensor
    maps: Tensor
    size: Tensor
    origin: Tensor
    step: Tensor

    @classmethod
    def stack(
        cls, evidence: Sequence[Evidence], device: torch.device, reuse: bool = False
    ) -> EvidenceBatch:
        """The ROIs' evidence on ``device``.

        ``reuse``: on the CPU, the maps go into a buffer this thread keeps for the next
        call's (so they hold only until this thread's next ``stack`` with ``reuse``): they
        are tens of megabytes, and memory that size is fresh pages from the OS at every
        allocation, whose first touch costs more than the copy into them."""
        points, valid = stack_points([e.points for e in evidence], device)
        side = max([1, *(e.dist.shape[-1] for e in evidence)])
        shape = (2, len(evidence), side, side)
        on_host = reuse and device.type == "cpu"
        maps = _host_buffer(shape) if on_host else torch.empty(shape, dtype=torch.float64)
        for i, e in enumerate(evidence):  # preparation: a copy per ROI, once per fit
            s = e.dist.shape[-1]
            maps[:, i, s:], maps[:, i, :s, s:] = 0.0, 0.0  # a smaller grid's padding
            for c, plane in enumerate((e.dist, e.sdf)):
                maps[c, i, :s, :s] = torch.from_numpy(np.ascontiguousarray(plane, np.float64))

        def f64(a: ArrayLike) -> Tensor:
            return torch.as_tensor(np.asarray(a, np.float64), device=device)

        return cls(
            points,
            valid,
            valid.sum(-1).to(torch.float64),
            maps.to(device),
            torch.as_tensor([e.dist.shape[-1] for e in evidence], device=device),
            f64([e.origin for e in evidence]).reshape(-1, 2),
            f64([e.step for e in evidence]),
        )


@dataclass(frozen=True)
class FitResult:
    """Outcome of one fit: the pose (the start's when not ``improved``) and the costs."""

    R: F64
    t: F64
    cost: float
    start_cost: float
    improved: bool


class FitResults(NamedTuple):
    """Outcomes of the fits of n ROIs (:func:`refine_poses`), numpy on the host."""

    R: F64  # (n, 3, 3)
    t: F64  # (n, 3) mm
    cost: F64  # (n,)
    start_cost: F64  # (n,)
    improved: NDArray[np.bool_]  # (n,)

    def row(self, i: int) -> FitResult:
        """ROI ``i``'s outcome."""
        return FitResult(
            self.R[i],
            self.t[i],
            float(self.cost[i]),
            float(self.start_cost[i]),
            bool(self.improved[i]),
        )


def cauchy(r: Tensor, c: float) -> tuple[Tensor, Tensor]:
    """Cauchy loss ρ(r) = c²/2 · log(1 + (r/c)²) and its IRLS weight ρ'(r)/r."""
    q = (r / c) ** 2
    return 0.5 * c * c * torch.log1p(q), 1.0 / (1.0 + q)


def _geman_mcclure(r: Tensor, c: float) -> tuple[Tensor, Tensor]:
    """Geman-McClure loss ρ(r) = c²/2 · r²/(c² + r²) and its IRLS weight ρ'(r)/r.

    Redescending: a residual far beyond ``c`` costs a constant and pulls with ~zero force.
    """
    q = (r / c) ** 2
    return 0.5 * c * c * q / (1.0 + q), 1.0 / (1.0 + q) ** 2


def _argmin_last(x: Tensor) -> Tensor:
    """``x.argmin(-1)`` (the first of equal minima; int64), by numpy's vectorised argmin on
    the CPU: torch's reduction along a short last axis is several times slower."""
    if x.device.type != "cpu":
        return x.argmin(-1)
    return torch.from_numpy(np.ascontiguousarray(x.numpy().argmin(-1), np.int64))


class _Rows(NamedTuple):
    """Per batch row (a start of one ROI): its ROI's intrinsics, grid and points."""

    roi: Tensor  # (B,) ROI index
    K: Tensor  # (B, 3, 3)
    points: Tensor  # (B, N, 2) evidence px
    valid: Tensor  # (B, N)
    real: Tensor  # (B,) how many are real
    origin: Tensor  # (B, 1, 2)
    step: Tensor  # (B, 1, 1)
    size: Tensor  # (B, 1) grid side


class _Problem:
    """Residuals, costs and Jacobians of B rows (poses), each against its ROI's evidence.

    Args:
        arc, ev, K, s: The needle, the ROIs' evidence, their intrinsics (n, 3, 3), the fit.
        roi: (B,) each row's ROI.
        points: (n, P, 3) camera points of the wires' surfaces, mm, and which are real
            (n, P), for the depth term; an ROI without points has none real.
        depth: the depth term's settings.
    """

    def __init__(
        self,
        arc: ArcModel,
        ev: EvidenceBatch,
        K: Tensor,
        s: FitSettings,
        roi: Tensor,
        points: tuple[Tensor, Tensor] | None = None,
        depth: DepthSettings | None = None,
    ) -> None:
        opts = {"dtype": torch.float64, "device": K.device}
        self.arc, self.ev, self.s = arc, ev, s
        self.model = torch.as_tensor(arc.points(s.samples), **opts)  # type: ignore[arg-type]
        wire_mm = arc.wire_radii(s.samples)
        self.wire_mm = torch.as_tensor(wire_mm, **opts)  # type: ignore[arg-type]
        # the wire itself explains pixels; the cost fits the tube only with ``tube``
        self.wire = self.wire_mm if s.tube else torch.zeros_like(self.wire_mm)
        self.rows = _Rows(
            roi,
            K[roi],
            ev.points[roi],
            ev.valid[roi],
            ev.real[roi],
            ev.origin[roi][:, None],
            ev.step[roi][:, None, None],
            ev.size[roi][:, None],
        )
        # the evidence in single precision about its grid's origin, as (x, y, 1) (B, N, 3),
        # for the nearest-sample search alone (it only picks which segments the float64
        # distances are taken to; see _nearest)
        p32 = (self.rows.points - self.rows.origin).float()
        self.points32 = torch.cat([p32, torch.ones_like(p32[..., :1])], -1)
        # the points by component (2, B, N, 1), for the arithmetic against both candidates
        self.points_xy = self.rows.points.permute(2, 0, 1)[..., None].contiguous()
        self.depth = depth or DepthSettings()
        self.points = None
        if points is not None:
            P, ok = points[0][roi].transpose(1, 2).contiguous(), points[1][roi]  # by axis
            self.points = (P, ok, ok.sum(-1).clamp(min=1).to(torch.float64))

    def project(self, R: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Camera points (B, M, 3), their object-centred part R·X (B, M, 3), pixels (B, M, 2)."""
        rx = self.model @ R.transpose(1, 2)
        X = rx + t[:, None, :]
        z = X[..., 2].clamp(min=1e-6)
        K = self.rows.K[:, None]
        u = K[..., 0, 0] * X[..., 0] / z + K[..., 0, 1] * X[..., 1] / z + K[..., 0, 2]
        v = K[..., 1, 1] * X[..., 1] / z + K[..., 1, 2]
        return X, rx, torch.stack([u, v], -1)

    def jac_points(self, X: Tensor, rx: Tensor) -> Tensor:
        """d(pixel)/d(ω, δt) of each model point by component, (2, 6, B, M): (u, v) × (ω, δt),
        for X → exp(ω)·rx + t + δt. Component-major: every product after it is of contiguous
        (B, M) blocks (a trailing axis of 2 or 6 makes each broadcast op several times slower)."""
        z = X[..., 2].clamp(min=1e-6)
        K = self.rows.K[:, None]
        zero = torch.zeros_like(z)
        fx, skew_, fy = K[..., 0, 0] / z, K[..., 0, 1] / z, K[..., 1, 1] / z
        # d(pixel)/dX: rows p_u, p_v; d(pixel)/dω = p·(−[rx]×) = rx × p, d(pixel)/dδt = p
        # (written out: a batched matmul of 2×3 by 3×3 per point costs more than its sums)
        p_u = (fx, skew_, -(fx * X[..., 0] + skew_ * X[..., 1]) / z)
        p_v = (zero, fy, -fy * X[..., 1] / z)
        a0, a1, a2 = rx.unbind(-1)

        def row(p: tuple[Tensor, Tensor, Tensor]) -> list[Tensor]:
            p0, p1, p2 = p
            return [a1 * p2 - a2 * p1, a2 * p0 - a0 * p2, a0 * p1 - a1 * p0, p0, p1, p2]

        return torch.stack([*row(p_u), *row(p_v)]).view(2, 6, *z.shape)

    def wire_px(self, X: Tensor, rx: Tensor) -> tuple[Tensor, Tensor]:
        """Wire radius in image px at each model point (B, M) and its d/d(ω, δt) (6, B, M)."""
        z = X[..., 2].clamp(min=1e-6)
        rho = self.radius_px(self.wire, z)
        zero = torch.zeros_like(z)
        # dz/dω = ((R·X)_y, −(R·X)_x, 0), dz/dδt = (0, 0, 1)
        dz = torch.stack([rx[..., 1], -rx[..., 0], zero, zero, zero, torch.ones_like(z)])
        return rho, -(rho / z) * dz

    def radius_px(self, wire_mm: Tensor, z: Tensor) -> Tensor:
        """Image radius (px) of wire radii ``wire_mm`` at depths ``z`` (B, M) mm."""
        K = self.rows.K
        return wire_mm * torch.sqrt(K[:, 0, 0] * K[:, 1, 1])[:, None] / z

    def _nearest(self, uv: Tensor, rho: Tensor) -> _Nearest:
        """Each evidence point's closest point on its row's projected wire (M samples)."""
        b, m = uv.shape[:2]
        # nearest centre-line sample, then the closest point on its two adjacent segments:
        # O(N·M) small arithmetic instead of a point-to-every-segment distance. The sample
        # minimises |uv|²/2 − e·uv (|e − uv|² less a per-point constant): one product of
        # (e, 1) and (−uv, |uv|²/2), in single precision (a near tie between two samples
        # picks the segment between them either way)
        uv32 = (uv - self.rows.origin).float()
        q = torch.cat([-uv32, 0.5 * (uv32 * uv32).sum(-1, keepdim=True)], -1)
        k0 = _argmin_last(torch.bmm(self.points32, q.transpose(1, 2)))
        seg = torch.stack([k0 - 1, k0], -1).clamp(0, m - 2)  # (B, N, 2) candidate segments
        # the samples' x, y and radius by component, (3, B·M), looked up at both candidates'
        # ends: (3, B, N, 2) blocks, contiguous per component
        table = torch.cat([uv.permute(2, 0, 1), rho[None]]).reshape(3, b * m)
        at = (seg + torch.arange(b, device=uv.device)[:, None, None] * m).reshape(-1)
        a, c = (torch.gather(table, 1, i.expand(3, -1)).view(3, *seg.shape) for i in (at, at + 1))
        ab = c[:2] - a[:2]
        ap = self.points_xy - a[:2]
        dot, len2 = ap[0] * ab[0] + ap[1] * ab[1], ab[0] * ab[0] + ab[1] * ab[1]
        tau = (dot / len2.clamp(min=1e-12)).clamp(0.0, 1.0)  # (B, N, 2)
        d = ap - tau * ab  # (2, B, N, 2): e − the closest point
        d2 = d[0] * d[0] + d[1] * d[1]
        second = d2[..., 1] < d2[..., 0]  # the first of equals, as argmin

        def pick(x: Tensor) -> Tensor:
            return torch.where(second, x[..., 1], x[..., 0])

        d_line = torch.sqrt(pick(d2))
        tk = pick(tau)  # (B, N) where on the chosen segment
        rho_c = pick(a[2] + tau * (c[2] - a[2]))
        # zero inside the tube, and for padding
        d_rev = (d_line - rho_c).clamp(min=0.0) * self.rows.valid
        return _Nearest(d_rev, d_line, pick(d), pick(ab), pick(seg), tk)

    def _sides(self, uv: Tensor, rho: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The distance transform at the samples (3, B, M), the signed outline distance on the
        tube's two sides (3, B, 2M) (values and x, y gradients), the sides' normals by
        component (2, B, M) and which side samples count (B, 2M)."""
        # the tube's two sides: ±rho along the projected centre line's normal
        tangent = _gradient(uv)  # (B, M, 2), px per sample
        t_len = torch.linalg.vector_norm(tangent, dim=-1, keepdim=True)
        normal = torch.stack([-tangent[..., 1], tangent[..., 0]], -1) / t_len.clamp(min=1e-9)
        off = rho[..., None] * normal
        m = uv.shape[1]
        # one sampling: the distance at the samples, the outline distance on both sides
        plane = torch.zeros(3 * m, dtype=torch.long, device=uv.device)
        plane[m:] = 1
        both = self._bilinear(plane, torch.cat([uv, uv + off, uv - off], 1))
        fwd, side = both[..., :m], both[..., m:]  # (3, B, M): value, d/dx, d/dy; (3, B, 2M)
        # a side is defined where the centre line runs across the view (not where it turns
        # back towards the camera) and the wire is wider than a pixel
        use = (t_len[..., 0] > 0.25) & (rho > 0.5) & self.s.tube
        return fwd, side, normal.permute(2, 0, 1), torch.cat([use, use], 1)

    def _bilinear(self, plane: Tensor, uv: Tensor) -> Tensor:
        """Maps ``plane`` (Q,) (0: distance, 1: signed outline distance) of each row's ROI and
        their x, y gradient, bilinearly sampled at image px ``uv`` (B, Q, 2) (clamped to the
        grid's border): (3, B, Q). The gradient is ``numpy.gradient``'s (central differences,
        one-sided at the border) at the four pixels read, from their 4 × 4 neighbourhood."""
        rows, maps = self.rows, self.ev.maps
        side = maps.shape[-1]
        xy = (uv - rows.origin) / rows.step
        last = rows.size - 1
        x = torch.minimum(xy[..., 0].clamp(min=0.0), last.to(xy.dtype))
        y = torch.minimum(xy[..., 1].clamp(min=0.0), last.to(xy.dtype))
        x0 = torch.minimum(torch.floor(x).long(), rows.size - 2)
        y0 = torch.minimum(torch.floor(y).long(), rows.size - 2)
        fx, fy = x - x0, y - y0
        # columns x0 - 1 .. x0 + 2 and rows y0 - 1 .. y0 + 2 (the four pixels read and one each
        # side), clamped to the grid, and the maps there, laid out (4, 4, B, Q): a row and
        # column of them is one contiguous (B, Q) block
        off = torch.arange(-1, 3, device=uv.device)[:, None, None]
        cols = torch.minimum((x0 + off).clamp(min=0), last)  # (4, B, Q)
        lines = torch.minimum((y0 + off).clamp(min=0), last)
        grid = (plane * maps.shape[1] + rows.roi[:, None]) * side + lines
        at = grid[:, None] * side + cols[None]
        f = maps.reshape(-1).index_select(0, at.reshape(-1)).reshape(at.shape)
        # the value, and the differences over the neighbours' distance (2 steps inside, 1 at
        # the border), at the pixels read (rows y0, y0 + 1; columns x0, x0 + 1)
        dx = (cols[2:] - cols[:2]).to(f.dtype) * rows.step[..., 0]  # (2, B, Q)
        dy = (lines[2:] - lines[:2]).to(f.dtype)[:, None] * rows.step[..., 0]
        g = torch.stack(
            [f[1:3, 1:3], (f[1:3, 2:] - f[1:3, :2]) / dx, (f[2:, 1:3] - f[:2, 1:3]) / dy], 2
        )
        top_row = g[0, 0] * (1 - fx) + g[0, 1] * fx  # (3, B, Q)
        return top_row * (1 - fy) + (g[1, 0] * (1 - fx) + g[1, 1] * fx) * fy

    def evaluate(self, R: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Robust cost (B,), the normal equations of its IRLS-weighted residuals (JᵀWJ
        (B, 6, 6), JᵀWr (B, 6); :func:`.lm.normal_equations`) and the image residuals
        (B, N+3M): reverse (px), forward (px), the tube's sides (signed px)."""
        s, rows = self.s, self.rows
        X, rx, uv = self.project(R, t)
        rho, drho = self.wire_px(X, rx)
        m = uv.shape[1]
        near = self._nearest(uv, rho)
        fwd, side, normal, use2 = self._sides(uv, rho)
        d_fwd, d_side = fwd[0], side[0]
        rho_r, w_r = cauchy(near.d_rev, s.scale_reverse)
        rho_f, w_f = _geman_mcclure(d_fwd, s.scale_forward)
        rho_s, w_s = _geman_mcclure(d_side, s.scale_outline)
        rho_s = torch.where(use2, rho_s, 0.0)
        cost = (rho_r * rows.valid).sum(-1) / rows.real + s.forward_weight * rho_f.mean(-1)
        cost = cost + s.outline_weight * rho_s.sum(-1) / (2 * m)
        Jp = self.jac_points(X, rx)  # (2, 6, B, M)
        J_rev = _reverse_jacobian(near, Jp, drho)
        # forward: r = dist(uv); dr/dp = ∇dist · d(uv)/dp
        J_fwd = fwd[1] * Jp[0] + fwd[2] * Jp[1]  # (6, B, M)
        # sides: r = sdf(uv ± rho·n); the normal's own turn with the pose is left out
        dn = normal[:, None] * drho  # (2, 6, B, M)
        on_sides = torch.cat([Jp + dn, Jp - dn], -1)
        J_side = side[1] * on_sides[0] + side[2] * on_sides[1]  # (6, B, 2M)
        w_side = s.outline_weight * torch.where(use2, w_s, 0.0) / (2 * m)
        w_rev = w_r * rows.valid / rows.real[:, None]
        terms = [
            (near.d_rev, w_rev, J_rev),
            (d_fwd, s.forward_weight * w_f / m, J_fwd),
            (d_side, w_side, J_side),
        ]
        H, g = normal_equations(*terms[0], by_component=True)
        for term in terms[1:]:
            H_k, g_k = normal_equations(*term, by_component=True)
            H, g = H + H_k, g + g_k
        if self.points is not None:
            P, ok, count = self.points
            r_d, J_d = wire_residuals_model(R, t, P, self.arc)
            r_d = r_d * ok
            rho_d, w_d = cauchy(r_d, self.depth.scale_mm)
            cost = cost + self.depth.weight * (rho_d * ok).sum(-1) / count
            w_d = self.depth.weight * w_d * ok / count[:, None]
            H_d, g_d = camera_normal_equations(*normal_equations(r_d, w_d, J_d, by_row=True), R)
            H, g = H + H_d, g + g_d
        return cost, H, g, torch.cat([near.d_rev, d_fwd, d_side], 1)


def _gradient(uv: Tensor) -> Tensor:
    """d(uv)/d(sample) along the samples (B, M, 2): central differences, one-sided at the
    ends (as ``numpy.gradient``)."""
    inner = 0.5 * (uv[:, 2:] - uv[:, :-2])
    return torch.cat([uv[:, 1:2] - uv[:, :1], inner, uv[:, -1:] - uv[:, -2:-1]], 1)


class _Nearest(NamedTuple):
    """Evidence points (N) against the projected wire of B poses (see :meth:`_Problem._nearest`)."""

    d_rev: Tensor  # (B, N) distance to the tube, px (0 inside, and for padding)
    d_line: Tensor  # (B, N) distance to the centre line, px
    dv: Tensor  # (2, B, N) point minus its closest centre-line point, by component
    sv: Tensor  # (2, B, N) the chosen segment's direction, by component
    k: Tensor  # (B, N) the chosen segment
    tk: Tensor  # (B, N) where on it


def _reverse_jacobian(near: _Nearest, Jp: Tensor, drho: Tensor) -> Tensor:  # noqa: N803
    """d(reverse residual)/d(ω, δt) (6, B, N) from the samples' pixel derivatives ``Jp``
    (2, 6, B, M) and radius derivatives ``drho`` (6, B, M): r = û·(e − c) − rho_c with c the
    closest point (moving with the pose) and û the segment normal towards e, or the direction
    from c where c is an end of the arc."""
    k, tk, (dx, dy), (sx, sy) = near.k, near.tk, near.dv, near.sv
    b, m = drho.shape[1:]
    # a column per sample: its pixel's and its radius's derivatives (18, B·M), so that a
    # point's two samples are two column lookups (a gather: index_select along columns is
    # several times slower)
    table = torch.cat([Jp.reshape(12, b * m), drho.reshape(6, b * m)])
    at = (k + torch.arange(b, device=k.device)[:, None] * m).reshape(-1)
    lo, hi = (torch.gather(table, 1, i.expand(18, -1)).view(18, *k.shape) for i in (at, at + 1))
    length = torch.sqrt(sx * sx + sy * sy).clamp(min=1e-12)
    nx, ny = -sy / length, sx / length
    away = nx * dx + ny * dy < 0  # the segment normal turned towards the point
    nx, ny = torch.where(away, -nx, nx), torch.where(away, -ny, ny)
    interior = (tk > 0) & (tk < 1)
    on_line = interior | (near.d_line < 1e-9)
    inv = 1.0 / near.d_line.clamp(min=1e-9)
    ux = torch.where(on_line, nx, dx * inv)
    uy = torch.where(on_line, ny, dy * inv)
    # −(û·(u, v)' + rho') of c = (1 − τ)·lo + τ·hi, zero inside the tube: the (B, N)
    # coefficients first, then one multiply-add per block of the (6, B, N) result
    outside = (near.d_rev > 0).to(tk.dtype)
    w_lo, w_hi = (tk - 1.0) * outside, -tk * outside
    J_rev = torch.mul(lo[12:], w_lo)
    for block, w in (
        (hi[12:], w_hi),
        (lo[:6], w_lo * ux),
        (lo[6:12], w_lo * uy),
        (hi[:6], w_hi * ux),
        (hi[6:12], w_hi * uy),
    ):
        J_rev.addcmul_(block, w)
    return J_rev


class Starts(NamedTuple):
    """Extra starting poses of a batched fit (e.g. fits to the depth points alone): rotations
    (k, 3, 3), translations (k, 3) mm and the ROI (k,) each starts."""

    R: F64
    t: F64
    roi: NDArray[np.int64]

    @classmethod
    def none(cls) -> Starts:
        """No extra start."""
        return cls(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))


def refine_poses(
    R_init: F64,
    t_init: F64,
    K: F64,
    evidence: Sequence[Evidence],
    arc: ArcModel,
    settings: FitSettings | None = None,
    points: Sequence[F64 | None] | None = None,
    starts: Starts | None = None,
    depth: DepthSettings | None = None,
    device: torch.device | str = "cpu",
) -> FitResults:
    """Fit the arc's poses of n ROIs to their ``evidence``, all at once (see the module
    docstring), each from its ``(R_init, t_init)`` (and its mirror).

    Args:
        R_init: (n, 3, 3) starting rotations, model → camera.
        t_init: (n, 3) starting translations, mm.
        K: (3, 3) or (n, 3, 3) intrinsics, px.
        evidence: each ROI's foreground evidence.
        arc: the needle's centre line.
        settings: the image fit (defaults when None).
        points: per ROI, (N, 3) camera points of the wire's visible surface, mm, or None
            (RGB-D: the depth term, weighted by ``depth``; with them the fit also starts from
            the tilt mirror).
        starts: More starting poses, e.g. fits to the points alone.
        depth: the depth term's settings (defaults when None).
        device: where the fit runs (float64); on a CPU, on the calling thread with one
            intra-op thread (:func:`.lm.fit_threads`).

    Returns:
        Per ROI the fitted pose where it beats the start's cost (``improved``), else the
        start. Deterministic; never NaN (a non-finite fit returns the start).
    """
    s = settings or FitSettings()
    n = len(evidence)
    R_init = np.asarray(R_init, float).reshape(n, 3, 3)
    t_init = np.asarray(t_init, float).reshape(n, 3)
    K = np.broadcast_to(np.asarray(K, float), (n, 3, 3))
    pts = list(points) if points is not None else [None] * n
    finite = np.isfinite(R_init).all(axis=(1, 2)) & np.isfinite(t_init).all(1)
    active = finite & np.array([e.size >= s.min_evidence for e in evidence], bool)
    out = FitResults(
        R_init.copy(),
        t_init.copy(),
        np.full(n, np.inf),
        np.full(n, np.inf),
        np.zeros(n, bool),
    )
    if not active.any():
        return out
    idx = np.flatnonzero(active)
    extra = starts or Starts.none()
    dev, dep = torch.device(device), depth or DepthSettings()
    keep = np.isin(extra.roi, idx)  # the extra starts of the fitted ROIs, renumbered
    remap = np.zeros(n, np.int64)
    remap[idx] = np.arange(len(idx))
    sub = Starts(extra.R[keep], extra.t[keep], remap[extra.roi[keep]])
    ev, p = [evidence[int(i)] for i in idx], [pts[i] for i in idx]
    poses = (R_init[idx], t_init[idx], K[idx])
    with fit_threads(dev):
        res = _fit_batch(dev, arc, s, dep, ev, poses, p, sub)
    for field, value in zip(out, res, strict=True):
        field[idx] = value
    return out


def _fit_batch(
    device: torch.device,
    arc: ArcModel,
    s: FitSettings,
    depth: DepthSettings,
    evidence: list[Evidence],
    poses: tuple[F64, F64, F64],
    points: list[F64 | None],
    starts: Starts,
) -> tuple[F64, F64, F64, F64, NDArray[np.bool_]]:
    """:func:`refine_poses` on ROIs that all have evidence enough: (R, t, cost, start cost,
    improved) per ROI."""
    R0, t0, K = (torch.as_tensor(a, dtype=torch.float64, device=device) for a in poses)
    n = len(evidence)
    mirror = np.array([s.mirror_start or p is not None for p in points], bool)
    roi, R_s, t_s, slot = _start_poses(R0, t0, arc, mirror, starts)
    # x = (ω, δt): R = exp(ω)·R_start, t = t_start + δt. The prior holds the directions the
    # image does not fix (depth, tilt) near the network's pose
    held = (slot > 0)[:, None]
    x_prior = torch.cat([-log_so3(R_s @ R0[roi].transpose(1, 2)), t0[roi] - t_s], -1)
    x_prior = torch.where(held, x_prior, 0.0)
    with_points = [p if p is not None else np.zeros((0, 3)) for p in points]
    stacked = stack_points(with_points, device) if any(p is not None for p in points) else None
    ev = EvidenceBatch.stack(evidence, device, reuse=True)  # used only in this call
    prob = _Problem(arc, ev, K, s, roi, stacked, depth)
    sigma = np.array([np.deg2rad(s.prior_deg)] * 3 + list(s.prior_mm), float)
    sq = torch.as_tensor(np.sqrt(s.prior_weight) / sigma, device=device)
    prior_H = torch.diag(sq**2)

    def total(x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        c, H, g, _ = prob.evaluate(exp_so3(x[:, :3]) @ R_s, t_s + x[:, 3:])
        return c + 0.5 * ((sq * (x - x_prior)) ** 2).sum(-1), H, g

    def prior(x: Tensor) -> tuple[Tensor, Tensor]:
        return prior_H, sq**2 * (x - x_prior)

    x0 = torch.zeros(len(roi), 6, dtype=torch.float64, device=device)
    first = total(x0)
    start_cost = first[0][slot == 0]  # the network's pose: its first start, x_prior 0
    x, cost = levenberg_marquardt(
        total, x0, torch.add, s.iterations, s.lambda0, prior=prior, group=roi, first=first
    )
    best, ok = _best_rows(cost, roi, slot, n)
    R_best = exp_so3(x[best, :3]) @ R_s[best]
    t_best = t_s[best] + x[best, 3:]
    ok &= torch.isfinite(cost[best]) & (cost[best] < start_cost)
    ok &= torch.isfinite(R_best).all(-1).all(-1) & torch.isfinite(t_best).all(-1)
    U, _, Vt = torch.linalg.svd(torch.where(ok[:, None, None], R_best, R0))
    R_out = torch.where(ok[:, None, None], U @ Vt, R0)
    t_out = torch.where(ok[:, None], t_best, t0)
    cost_out = torch.where(ok, cost[best], start_cost)
    return tuple(a.cpu().numpy() for a in (R_out, t_out, cost_out, start_cost, ok))  # type: ignore[return-value]


def _best_rows(cost: Tensor, roi: Tensor, slot: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Each ROI's cheapest row (the first of equals) and whether none of its costs is NaN."""
    table = torch.full((n, int(slot.max()) + 1), torch.inf, dtype=cost.dtype, device=cost.device)
    table[roi, slot] = cost
    nan = torch.isnan(table).any(-1)
    pick = torch.nan_to_num(table, nan=torch.inf).argmin(-1)
    counts = torch.bincount(roi, minlength=n)  # rows are grouped by ROI
    return torch.cumsum(counts, 0) - counts + pick, ~nan


def _start_poses(
    R_init: Tensor, t_init: Tensor, arc: ArcModel, mirror: NDArray[np.bool_], starts: Starts
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The fit's start rows, grouped by ROI: ROI (b,), rotations (b, 3, 3), translations
    (b, 3) mm and each row's place among its ROI's starts (b,). Per ROI: the network's pose,
    its tilt mirror (where ``mirror``) and its ``starts``, each with the network's tip and
    tail (the data cost hardly tells them apart)."""
    dev = R_init.device
    n = len(R_init)
    m = torch.as_tensor(np.flatnonzero(mirror), device=dev)
    roi = torch.cat([torch.arange(n, device=dev), m, torch.as_tensor(starts.roi, device=dev)])
    R = torch.cat(
        [R_init, mirror_pose(R_init[m], t_init[m]), torch.as_tensor(starts.R, device=dev)]
    )
    t = torch.cat([t_init, t_init[m], torch.as_tensor(starts.t, device=dev)])
    order = torch.as_tensor(np.argsort(roi.cpu().numpy(), kind="stable"), device=dev)
    roi, R, t = roi[order], R[order], t[order]
    R = same_ends(R, t, R_init[roi], t_init[roi], arc)
    counts = torch.bincount(roi, minlength=n)
    first = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(roi), device=dev) - first[roi]
    return roi, R, t, slot


def refine_pose(
    R_init: F64,
    t_init: F64,
    K: F64,
    evidence: Evidence,
    arc: ArcModel,
    settings: FitSettings | None = None,
    points: F64 | None = None,
    starts: tuple[tuple[F64, F64], ...] = (),
    depth: DepthSettings | None = None,
) -> FitResult:
    """:func:`refine_poses` of one ROI: the pose ``R_init`` (3, 3), ``t_init`` (3,) mm fitted
    to ``evidence`` (``points`` (N, 3) mm: its depth term), also from ``starts``."""
    extra = Starts(
        np.asarray([r for r, _ in starts], float).reshape(-1, 3, 3),
        np.asarray([t for _, t in starts], float).reshape(-1, 3),
        np.zeros(len(starts), np.int64),
    )
    pts = None if points is None else [np.asarray(points, float).reshape(-1, 3)]
    out = refine_poses(
        np.asarray(R_init, float)[None],
        np.asarray(t_init, float)[None],
        K,
        [evidence],
        arc,
        settings,
        pts,
        extra,
        depth,
    )
    return out.row(0)
