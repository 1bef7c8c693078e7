"""Torch (GPU) path of the batched pose errors: MSSD, MSPD, ADD, RE and TE.

The only core module that may import torch, and it does so inside its functions, so importing
:mod:`bopsurg.metrics` never imports torch (install the ``torch`` extra to use this module).

Inputs may be numpy arrays or torch tensors, with the shapes of :mod:`bopsurg.metrics`
(``R`` (N, 3, 3) or (3, 3), ``t`` (N, 3), (3,) or (3, 1) in mm, ``K`` (3, 3) or (N, 3, 3),
``pts`` (V, 3) in mm; batches of 1 broadcast). Results are torch tensors of shape (N,) on the
chosen device, float64 by default: they equal the numpy path to 1e-9 (relative, or absolute
near 0). ``dtype=torch.float32`` runs the bulk work (the N·S·V distance evaluations) in
float32; the returned values are still recomputed in float64 at the chosen symmetry and
vertex, so they differ from float64 only where two symmetries tie to float32 rounding.

MSSD and MSPD, ``min_s max_x d(s, x)``, are not a port of the reference's loop but a search
that a GPU runs as a few large batched steps over all poses × symmetries at once, and whose
result is exact:

1. **Fewer vertices.** MSSD's ``x ↦ ‖A x + b‖`` is convex, so its maximum over the model is
   attained at a vertex of the convex hull (computed once per model, cached). MSPD (a
   projection, not convex) uses all vertices.
2. **Squared distances as one matrix product** (MSSD): ``‖A y + b‖² = yᵀ(AᵀA)y + 2 bᵀA y +
   bᵀb`` is a dot product of 10 coefficients per (pose, symmetry) with 10 monomials per
   vertex, so all symmetries of a pose chunk are one GEMM followed by a max-reduction. The
   vertices are centred first (``y = x − x̄``) so that the terms stay of the size of the
   result; the value returned is recomputed with the reference's direct formula.
3. **Bounds prune symmetries.** The maximum over a subset of vertices is a lower bound of the
   maximum over all of them. Every (pose, symmetry) gets a bound from 32 extreme vertices;
   each pose's most promising symmetry is evaluated in full (an upper bound of the result);
   its maximising vertex tightens every bound of that pose; the survivors get a bound from
   256 vertices, and only the (pose, symmetry) pairs whose bound is still below the upper
   bound are evaluated in full. Comparisons carry a tolerance above any rounding difference
   between the forms, so a symmetry is only pruned when its exact value cannot be smaller.

MSPD NaN/inf: poses whose vertices may come near the camera plane (where the reference's
projection gives inf/NaN) are handed to the numpy path (:func:`bopsurg.metrics.mspd`), which
reproduces the reference's NaN rule, as are any non-finite results.
"""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from bopsurg.errors import InputError, ShapeError
from bopsurg.metrics import pose_error
from bopsurg.metrics.point_subsets import extreme_point_order, hull_vertex_indices

if TYPE_CHECKING:
    import torch

#: Elements of the temporaries of one batched step (float64: 512 MB on CUDA, 8 MB on the CPU,
#: where cache-sized chunks are much faster than large ones).
CUDA_BUDGET = 1 << 26
CPU_BUDGET = 1 << 20
#: Vertices of the bound that every (pose, symmetry) pair gets.
BOUND_POINTS = 32
#: Vertices of the second bound, for the pairs that survive the first.
REFINE_POINTS = 256
#: Models whose vertex subsets are kept (hull, extreme-point order), keyed by content.
MODEL_CACHE_SIZE = 32
#: Relative distance to the camera plane below which MSPD goes to the numpy path.
PLANE_GUARD = 1e-6
#: Device types whose small batched matrix products are computed as broadcast sums (:func:`_mm`).
BROADCAST_PRODUCTS = frozenset({"cuda"})
EPS64 = float(np.finfo(np.float64).eps)
EPS32 = float(np.finfo(np.float32).eps)

_MODELS: dict[tuple[str, bool], tuple[np.ndarray, np.ndarray]] = {}


def _torch() -> Any:
    try:
        import torch
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(
            "bopsurg.metrics.torch_backend needs torch: pip install 'bopsurg[torch]'"
        ) from err
    return torch


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """``"auto"`` → CUDA when available, else the CPU; anything else as ``torch.device``."""
    torch = _torch()
    if isinstance(device, str) and device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def _tensor(x: Any, name: str, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    torch = _torch()
    if isinstance(x, torch.Tensor):
        t = x.to(device=device, dtype=dtype)
    else:
        try:
            a = np.asarray(x, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ShapeError(f"not a numeric array: {err}", field=name) from err
        t = torch.as_tensor(a, device=device).to(dtype)
    if not bool(torch.isfinite(t).all()):
        raise ShapeError("contains NaN or inf", field=name)
    return t


def _rotations(x: Any, name: str, dev: torch.device, dt: torch.dtype) -> torch.Tensor:
    t = _tensor(x, name, dev, dt)
    if t.shape == (3, 3):
        t = t[None]
    if t.ndim != 3 or tuple(t.shape[1:]) != (3, 3):
        raise ShapeError(f"expected shape (3, 3) or (N, 3, 3), got {tuple(t.shape)}", field=name)
    return t


def _translations(x: Any, name: str, dev: torch.device, dt: torch.dtype) -> torch.Tensor:
    t = _tensor(x, name, dev, dt)
    if tuple(t.shape) in ((3,), (3, 1)):
        t = t.reshape(1, 3)
    elif t.ndim == 3 and tuple(t.shape[1:]) == (3, 1):
        t = t[:, :, 0]
    if t.ndim != 2 or t.shape[1] != 3:
        raise ShapeError(f"expected shape (3,), (3, 1) or (N, 3), got {tuple(t.shape)}", field=name)
    return t


def _points(x: Any, name: str) -> np.ndarray:
    """(V, 3) float64 numpy points (model data is prepared on the CPU, then moved)."""
    torch = _torch()
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x
    try:
        p = np.ascontiguousarray(a, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ShapeError(f"not a numeric array: {err}", field=name) from err
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise ShapeError(f"expected shape (V, 3) with V >= 1, got {p.shape}", field=name)
    if not np.isfinite(p).all():
        raise ShapeError("contains NaN or inf", field=name)
    return p


def _broadcast(*ts: torch.Tensor) -> tuple[int, list[torch.Tensor]]:
    n = max(int(t.shape[0]) for t in ts)
    for t in ts:
        if t.shape[0] not in (1, n):
            raise ShapeError(f"batch sizes {[int(x.shape[0]) for x in ts]} do not broadcast")
    return n, [t.expand(n, *t.shape[1:]).contiguous() for t in ts]


def _setup(device: str | torch.device, dtype: Any) -> tuple[torch.device, torch.dtype, int]:
    torch = _torch()
    dev = resolve_device(device)
    dt = torch.float64 if dtype is None else dtype
    if dt not in (torch.float64, torch.float32):
        raise InputError(f"expected torch.float64 or torch.float32, got {dt}", field="dtype")
    return dev, dt, CUDA_BUDGET if dev.type == "cuda" else CPU_BUDGET


def _pairs(
    R_est: Any, t_est: Any, R_gt: Any, t_gt: Any, dev: torch.device, dt: torch.dtype
) -> tuple[int, list[torch.Tensor]]:
    return _broadcast(
        _rotations(R_est, "R_est", dev, dt),
        _translations(t_est, "t_est", dev, dt),
        _rotations(R_gt, "R_gt", dev, dt),
        _translations(t_gt, "t_gt", dev, dt),
    )


def _syms(syms: Any, dev: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    torch = _torch()
    f64 = torch.float64
    if syms is None:
        return torch.eye(3, device=dev, dtype=f64)[None], torch.zeros((1, 3), device=dev, dtype=f64)
    if not isinstance(syms, (list, tuple)) or len(syms) != 2:
        raise ShapeError("expected (R_sym, t_sym)", field="syms")
    R = _tensor(syms[0], "syms", dev, f64)
    t = _tensor(syms[1], "syms", dev, f64).reshape(-1, 3)
    if R.ndim != 3 or tuple(R.shape[1:]) != (3, 3) or R.shape[0] == 0 or t.shape[0] != R.shape[0]:
        raise ShapeError("expected R_sym (S, 3, 3) and t_sym (S, 3)", field="syms")
    return R, t


def _model_subsets(pts: np.ndarray, hull: bool) -> tuple[np.ndarray, np.ndarray]:
    """(Candidate vertices, indices of their bound subsets in extreme-point order) of a model:
    the hull vertices (MSSD) or all vertices (MSPD); computed once per model content."""
    digest = hashlib.blake2b(pts.tobytes(), digest_size=16).hexdigest()
    key = (f"{pts.shape}:{digest}", hull)
    if key not in _MODELS:
        X = pts[hull_vertex_indices(pts)] if hull else pts
        order = extreme_point_order(X, min(REFINE_POINTS, X.shape[0]))
        if len(_MODELS) >= MODEL_CACHE_SIZE:
            _MODELS.clear()
        _MODELS[key] = (np.ascontiguousarray(X), order)
    return _MODELS[key]


def _mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for a small inner dimension (3 or 4; batch dimensions broadcast).

    On the devices in :data:`BROADCAST_PRODUCTS`, a sum of broadcast products: cuBLAS runs
    batched 3x3 products far below the memory bandwidth (on an H200 they took 90 % of MSSD's
    GPU time), elementwise kernels near it. The CPU's batched products are faster as they are.
    """
    if a.device.type not in BROADCAST_PRODUCTS:
        return a @ b
    out = a[..., :, 0:1] * b[..., 0:1, :]
    for j in range(1, a.shape[-1]):
        out = out + a[..., :, j : j + 1] * b[..., j : j + 1, :]
    return out


def _chunks(n: int, size: int) -> list[tuple[int, int]]:
    size = max(1, size)
    return [(a, min(n, a + size)) for a in range(0, n, size)]


class _Distance:
    """``max_x`` of a squared distance for flat (pose ``i``, symmetry ``s``) pairs.

    Subclasses hold the poses (float64, on the device) and the candidate vertices ``X``.
    """

    n: int
    S: int
    V: int
    budget: int
    #: Elements of the temporaries per (pair, vertex) of :meth:`max_over`.
    per_vertex: int

    def max_over(
        self, i: torch.Tensor, s: torch.Tensor, idx: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(k,) squared maxima over the vertices ``idx`` (None: all) and their positions."""
        raise NotImplementedError

    def at_all(self, a: int, b: int, v: torch.Tensor) -> torch.Tensor:
        """(b − a, S) squared distances of poses a..b−1 under every symmetry at the vertex
        ``v`` (b − a,) of each pose."""
        raise NotImplementedError

    def keep(self, lb: torch.Tensor, ub: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
        """Pairs whose bound ``lb`` may still beat their pose's best value ``ub`` (squared)."""
        raise NotImplementedError

    def final(self, i: torch.Tensor, s: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """(k,) float64 distances at vertex ``v`` by the reference's formula."""
        raise NotImplementedError

    def chunked_max(
        self, i: torch.Tensor, s: torch.Tensor, idx: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`max_over` in chunks that keep the temporaries within the budget."""
        torch = _torch()
        m = self.V if idx is None else int(idx.shape[0])
        val = torch.empty(i.shape[0], dtype=torch.float64, device=i.device)
        arg = torch.empty(i.shape[0], dtype=torch.long, device=i.device)
        for a, b in _chunks(int(i.shape[0]), self.budget // (self.per_vertex * m + 32)):
            v, j = self.max_over(i[a:b], s[a:b], idx)
            val[a:b] = v
            arg[a:b] = j if idx is None else idx[j]
        return val, arg


def _all_pairs_bound(k: _Distance, q: torch.Tensor) -> torch.Tensor:
    """(n, S) squared maxima over the vertices ``q`` for every pose and symmetry."""
    torch = _torch()
    dev = q.device
    lb = torch.empty((k.n, k.S), dtype=torch.float64, device=dev)
    step = max(1, k.budget // (k.S * (k.per_vertex * int(q.shape[0]) + 32)))
    for a, b in _chunks(k.n, step):
        i = torch.arange(a, b, device=dev).repeat_interleave(k.S)
        s = torch.arange(k.S, device=dev).repeat(b - a)
        lb[a:b] = k.chunked_max(i, s, q)[0].view(b - a, k.S)
    return lb


def _min_max(k: _Distance, order: torch.Tensor) -> torch.Tensor:
    """``min_s max_x`` of every pose, exact, by bounds over symmetries (module docstring)."""
    torch = _torch()
    dev = order.device
    poses = torch.arange(k.n, device=dev)
    if k.n == 0:
        return torch.empty(0, dtype=torch.float64, device=dev)
    if k.S == 1:
        zero = torch.zeros(k.n, dtype=torch.long, device=dev)
        return k.final(poses, zero, k.chunked_max(poses, zero, None)[1])
    lb = _all_pairs_bound(k, order[:BOUND_POINTS])
    s0 = lb.argmin(dim=1)
    ub, v0 = k.chunked_max(poses, s0, None)
    full = torch.full_like(lb, float("inf"))
    full_arg = torch.zeros(lb.shape, dtype=torch.long, device=dev)
    full[poses, s0], full_arg[poses, s0] = ub, v0
    done = torch.zeros(lb.shape, dtype=torch.bool, device=dev)
    done[poses, s0] = True
    # The first maximiser bounds the other symmetries of its pose (neighbours peak nearby).
    for a, b in _chunks(k.n, max(1, k.budget // (16 * k.S))):
        lb[a:b] = torch.maximum(lb[a:b], k.at_all(a, b, v0[a:b]))
    # A larger subset for the survivors (unless it is all vertices), then all vertices.
    for idx in (order, None) if order.numel() < k.V else (None,):
        ci, cs = torch.nonzero(~done & k.keep(lb, ub[:, None], poses[:, None]), as_tuple=True)
        if ci.numel() == 0:
            break
        val, arg = k.chunked_max(ci, cs, idx)
        if idx is not None:
            lb[ci, cs] = torch.maximum(lb[ci, cs], val)
        else:
            full[ci, cs], full_arg[ci, cs] = val, arg
    s_best = full.argmin(dim=1)
    return k.final(poses, s_best, full_arg[poses, s_best])


class _Surface(_Distance):
    """MSSD's ``‖(R_e x + t_e) − (R_g R_s x + R_g t_s + t_g)‖`` over the hull vertices."""

    per_vertex = 2

    def __init__(self, poses: list[torch.Tensor], X: np.ndarray, syms: Any, dt: Any) -> None:
        torch = _torch()
        self.R_e, self.te, self.R_g, self.tg = poses
        dev = self.R_e.device
        self.n, self.V, self.dt = int(self.R_e.shape[0]), X.shape[0], dt
        self.R_s, self.ts = syms
        self.S = int(self.R_s.shape[0])
        self.X = torch.as_tensor(X, device=dev)
        centre = X.mean(axis=0)
        y = X - centre
        self.centre = torch.as_tensor(centre, device=dev)
        mono = np.stack([y[:, 0] ** 2, y[:, 1] ** 2, y[:, 2] ** 2, y[:, 0] * y[:, 1],
                         y[:, 0] * y[:, 2], y[:, 1] * y[:, 2], y[:, 0], y[:, 1], y[:, 2],
                         np.ones(len(y))])  # fmt: skip
        self.mono = torch.as_tensor(mono, device=dev)  # (10, V), float64
        self.mono_dt = self.mono.to(dt)
        # Any two evaluations of one squared distance differ by less than this (mm²).
        rho = float(np.sqrt(np.einsum("ij,ij->i", y, y).max()))
        frob = torch.linalg.norm
        fa = frob(self.R_e, dim=(1, 2)) + frob(self.R_g, dim=(1, 2)) * float(
            frob(self.R_s, dim=(1, 2)).max()
        )
        scale = (
            fa * (rho + float(np.linalg.norm(centre)))
            + frob(self.te - self.tg, dim=1)
            + frob(self.R_g, dim=(1, 2)) * float(frob(self.ts, dim=1).max())
        )
        eps = EPS64 if dt == torch.float64 else EPS32
        self.tol_sq = 256.0 * eps * scale * scale
        self.budget = CUDA_BUDGET if dev.type == "cuda" else CPU_BUDGET

    def _coeffs(self, i: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """(k, 10) coefficients of ``‖A y + b‖²`` in the monomials of ``y = x − x̄``."""
        torch = _torch()
        R_g = self.R_g[i]
        A = self.R_e[i] - _mm(R_g, self.R_s[s])
        b = self.te[i] - _mm(R_g, self.ts[s][:, :, None])[:, :, 0] - self.tg[i]
        b = b + _mm(A, self.centre[None, :, None])[:, :, 0]
        a_t = A.transpose(1, 2)
        M = _mm(a_t, A)  # noqa: N806 (the matrix AᵀA)
        w = 2.0 * _mm(a_t, b[:, :, None])[:, :, 0]
        return torch.stack(
            [M[:, 0, 0], M[:, 1, 1], M[:, 2, 2], 2.0 * M[:, 0, 1], 2.0 * M[:, 0, 2],
             2.0 * M[:, 1, 2], w[:, 0], w[:, 1], w[:, 2], (b * b).sum(dim=1)], dim=1,
        )  # fmt: skip

    def max_over(
        self, i: torch.Tensor, s: torch.Tensor, idx: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        mono = self.mono_dt if idx is None else self.mono_dt[:, idx]
        val, arg = (self._coeffs(i, s).to(self.dt) @ mono).max(dim=1)
        return val.double(), arg

    def at_all(self, a: int, b: int, v: torch.Tensor) -> torch.Tensor:
        x = self.X[v]  # (k, 3)
        est = _mm(self.R_e[a:b], x[:, :, None])[:, :, 0] + self.te[a:b]  # (k, 3)
        sym = _mm(self.R_s[None], x[:, None, :, None]) + self.ts[None, :, :, None]  # (k, S, 3, 1)
        gt = _mm(self.R_g[a:b, None], sym)[..., 0] + self.tg[a:b, None]  # (k, S, 3)
        d = gt - est[:, None]
        result: torch.Tensor = (d * d).sum(dim=2)
        return result

    def keep(self, lb: torch.Tensor, ub: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
        result: torch.Tensor = lb < ub + 2.0 * self.tol_sq[i]
        return result

    def final(self, i: torch.Tensor, s: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        # The reference's formula: transform both, subtract, norm.
        R_g = self.R_g[i]
        x = self.X[v][:, :, None]
        p_est = _mm(self.R_e[i], x)[:, :, 0] + self.te[i]
        t_gs = _mm(R_g, self.ts[s][:, :, None])[:, :, 0] + self.tg[i]
        p_gt = _mm(_mm(R_g, self.R_s[s]), x)[:, :, 0] + t_gs
        return _norm3(p_est - p_gt)


def _norm3(d: torch.Tensor) -> torch.Tensor:
    """Row norms of (k, 3) differences, summed in the reference's order."""
    result: torch.Tensor = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]).sqrt()
    return result


class _Projected(_Distance):
    """MSPD's ``‖π(K, R_e, t_e, x) − π(K, R_g R_s, R_g t_s + t_g, x)‖`` over all vertices."""

    per_vertex = 10

    def __init__(
        self, poses: list[torch.Tensor], K: torch.Tensor, X: np.ndarray, syms: Any, dt: Any
    ) -> None:
        torch = _torch()
        self.R_e, self.te, self.R_g, self.tg = poses
        dev = self.R_e.device
        self.K, self.dt = K, dt
        self.n, self.V = int(self.R_e.shape[0]), X.shape[0]
        self.R_s, self.ts = syms
        self.S = int(self.R_s.shape[0])
        X_h = np.ones((4, X.shape[0]))
        X_h[:3] = X.T
        self.X_h = torch.as_tensor(X_h, device=dev)
        self.X_h_dt = self.X_h.to(dt)
        self.P_e = _mm(K, torch.cat([self.R_e, self.te[:, :, None]], dim=2))  # as the reference
        self.budget = CUDA_BUDGET if dev.type == "cuda" else CPU_BUDGET
        self.unsafe, tol = self._guard(float(np.sqrt(np.einsum("ij,ij->i", X, X).max())))
        self.tol = tol * (1.0 if dt == torch.float64 else EPS32 / EPS64)

    def _guard(self, rho: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Poses that may come near the camera plane, and the rounding tolerance (px) of the
        others, as :mod:`bopsurg.metrics.max_distance` bounds them."""
        torch = _torch()
        nrm = torch.linalg.norm
        k3 = self.K[:, 2, :]
        k3n = nrm(k3, dim=1)
        sig = torch.linalg.matrix_norm(self.R_s, ord=2)
        rho_sym = float((sig * rho + nrm(self.ts, dim=1)).max())
        ge = nrm(_mm(self.R_e.transpose(1, 2), k3[:, :, None])[:, :, 0], dim=1) * rho
        gg = nrm(_mm(self.R_g.transpose(1, 2), k3[:, :, None])[:, :, 0], dim=1) * rho_sym
        we, wg = (k3 * self.te).sum(dim=1), (k3 * self.tg).sum(dim=1)
        w_min = torch.minimum(torch.maximum(we - ge, -we - ge), torch.maximum(wg - gg, -wg - gg))
        scale = (
            nrm(self.te, dim=1) + nrm(self.tg, dim=1)
            + nrm(self.R_e, dim=(1, 2)) * rho + nrm(self.R_g, dim=(1, 2)) * rho_sym
        )  # fmt: skip
        unsafe = ~(w_min > PLANE_GUARD * k3n * scale)
        kmax = torch.maximum(nrm(self.K[:, 0], dim=1), nrm(self.K[:, 1], dim=1))
        r = scale / w_min.clamp_min(1e-300)
        inf = torch.full_like(r, float("inf"))
        return unsafe, torch.where(unsafe, inf, 256.0 * EPS64 * kmax * r * (1 + k3n * r))

    def _gt_mats(self, i: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """``K [R_g R_s | R_g t_s + t_g]`` per pair, as the reference builds P: (k, 3, 4)."""
        R_g = self.R_g[i]
        t = _mm(R_g, self.ts[s][:, :, None]) + self.tg[i][:, :, None]
        result: torch.Tensor = _mm(self.K[i], _torch().cat([_mm(R_g, self.R_s[s]), t], dim=2))
        return result

    def _sq(self, P: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
        """Squared projection distances for stacked (k, 6, 4) [P_e; P_g] and X (4, m) or
        per-pair X (k, 4, m)."""
        # A shared X is one plain matrix product (not k small ones).
        uvw = (P.reshape(-1, 4) @ X).view(P.shape[0], 6, -1) if X.ndim == 2 else _mm(P, X)
        d = uvw[:, 0:2] / uvw[:, 2:3] - uvw[:, 3:5] / uvw[:, 5:6]
        result: torch.Tensor = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
        return result

    def max_over(
        self, i: torch.Tensor, s: torch.Tensor, idx: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        torch = _torch()
        P = torch.cat([self.P_e[i], self._gt_mats(i, s)], dim=1).to(self.dt)
        X = self.X_h_dt if idx is None else self.X_h_dt[:, idx]
        val, arg = self._sq(P, X).max(dim=1)
        return val.double(), arg

    def _at(self, i: torch.Tensor, s: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """(k,) squared distances at the vertex ``v`` of each pair."""
        torch = _torch()
        P = torch.cat([self.P_e[i], self._gt_mats(i, s)], dim=1)
        return self._sq(P, self.X_h[:, v].T[:, :, None])[:, 0]

    def at_all(self, a: int, b: int, v: torch.Tensor) -> torch.Tensor:
        X = self.X_h[:, v].T  # (k, 4)
        est = _mm(self.P_e[a:b], X[:, :, None])[:, :, 0]  # (k, 3)
        sym = _mm(self.R_s[None], X[:, None, :3, None]) + self.ts[None, :, :, None]  # (k, S, 3, 1)
        R_g, t_g = self.R_g[a:b, None], self.tg[a:b, None, :, None]
        gt = _mm(self.K[a:b, None], _mm(R_g, sym) + t_g)[..., 0]  # (k, S, 3)
        d = gt[..., :2] / gt[..., 2:] - (est[:, :2] / est[:, 2:])[:, None]
        result: torch.Tensor = (d * d).sum(dim=2)
        return result

    def keep(self, lb: torch.Tensor, ub: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
        result: torch.Tensor = lb.sqrt() < ub.sqrt() + self.tol[i]
        return result

    def final(self, i: torch.Tensor, s: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return self._at(i, s, v).sqrt()


def _numpy_fallback(
    out: torch.Tensor, bad: torch.Tensor, fn: Any, args: list[torch.Tensor], rest: list[Any]
) -> torch.Tensor:
    """Recompute the poses ``bad`` with the numpy path (the reference's inf/NaN rules)."""
    torch = _torch()
    idx = torch.nonzero(bad)[:, 0]
    if idx.numel() == 0:
        return out
    sel = [a[idx].cpu().numpy() for a in args]
    host = [tuple(t.cpu().numpy() for t in r) if isinstance(r, tuple) else r for r in rest]
    vals = fn(*sel, *host)
    out[idx] = torch.as_tensor(vals, device=out.device, dtype=out.dtype)
    return out


def mssd_torch(
    R_est: Any,
    t_est: Any,
    R_gt: Any,
    t_gt: Any,
    pts: Any,
    syms: Any = None,
    *,
    candidates: ArrayLike | None = None,
    device: str | torch.device = "auto",
    dtype: Any = None,
) -> torch.Tensor:
    """MSSD in mm on torch: ``min_s max_x ‖(R_e x + t_e) − (R_g R_s x + R_g t_s + t_g)‖``.

    Args:
        R_est, t_est, R_gt, t_gt: Pose pairs (numpy or torch), as :func:`bopsurg.metrics.mssd`.
        pts: (V, 3) model vertices, mm.
        syms: ``(R_sym (S, 3, 3), t_sym (S, 3))`` or None (identity only).
        candidates: (n_c, 3) points whose hull contains ``pts`` (default: the hull of ``pts``,
            computed once per model and cached).
        device: ``"auto"`` (CUDA if available), ``"cpu"``, ``"cuda"``, or a ``torch.device``.
        dtype: ``torch.float64`` (default) or ``torch.float32`` (the bulk work).

    Returns:
        (N,) tensor on ``device``, mm.
    """
    torch = _torch()
    dev, dt, _ = _setup(device, dtype)
    _, poses = _pairs(R_est, t_est, R_gt, t_gt, dev, torch.float64)
    p = _points(pts, "pts")
    if candidates is None:
        X, order = _model_subsets(p, hull=True)
    else:
        X = _points(candidates, "candidates")
        order = extreme_point_order(X, min(REFINE_POINTS, X.shape[0]))
    syms_t = _syms(syms, dev)
    out = _min_max(_Surface(poses, X, syms_t, dt), torch.as_tensor(order, device=dev))
    bad = ~torch.isfinite(out)  # overflow only (inputs are finite)
    return _numpy_fallback(out, bad, pose_error.mssd, poses, [p, syms_t]).to(dt)


def mspd_torch(
    R_est: Any,
    t_est: Any,
    R_gt: Any,
    t_gt: Any,
    K: Any,
    pts: Any,
    syms: Any = None,
    *,
    device: str | torch.device = "auto",
    dtype: Any = None,
) -> torch.Tensor:
    """MSPD in px on torch, with the reference's projection (``K [R | t]``, divide by w).

    Args:
        R_est, t_est, R_gt, t_gt: Pose pairs (numpy or torch), as :func:`bopsurg.metrics.mspd`.
        K: (3, 3) or (N, 3, 3) camera matrices.
        pts: (V, 3) model vertices, mm.
        syms: ``(R_sym (S, 3, 3), t_sym (S, 3))`` or None (identity only).
        device: ``"auto"`` (CUDA if available), ``"cpu"``, ``"cuda"``, or a ``torch.device``.
        dtype: ``torch.float64`` (default) or ``torch.float32`` (the bulk work).

    Returns:
        (N,) tensor on ``device``, px (NaN/inf as the reference, see the module docstring).
    """
    torch = _torch()
    dev, dt, _ = _setup(device, dtype)
    n, poses = _pairs(R_est, t_est, R_gt, t_gt, dev, torch.float64)
    K_t = _tensor(K, "K", dev, torch.float64)
    if K_t.shape == (3, 3):
        K_t = K_t[None]
    if K_t.ndim != 3 or tuple(K_t.shape[1:]) != (3, 3) or K_t.shape[0] not in (1, n):
        raise ShapeError(f"expected shape (3, 3) or ({n}, 3, 3), got {tuple(K_t.shape)}", field="K")
    K_t = K_t.expand(n, 3, 3).contiguous()
    p = _points(pts, "pts")
    X, order = _model_subsets(p, hull=False)
    syms_t = _syms(syms, dev)
    unsafe = _Projected(poses, K_t, X, syms_t, dt).unsafe
    safe = torch.nonzero(~unsafe)[:, 0]
    out = torch.full((n,), float("nan"), dtype=torch.float64, device=dev)
    if safe.numel():
        k = _Projected([a[safe] for a in poses], K_t[safe], X, syms_t, dt)
        out[safe] = _min_max(k, torch.as_tensor(order, device=dev))
    bad = unsafe | ~torch.isfinite(out)
    return _numpy_fallback(out, bad, pose_error.mspd, [*poses, K_t], [p, syms_t]).to(dt)


def add_torch(
    R_est: Any,
    t_est: Any,
    R_gt: Any,
    t_gt: Any,
    pts: Any,
    *,
    device: str | torch.device = "auto",
    dtype: Any = None,
) -> torch.Tensor:
    """ADD in mm on torch: mean over vertices of ``‖(R_e x + t_e) − (R_g x + t_g)‖``.

    Computed as ``‖(R_e − R_g) x + (t_e − t_g)‖`` (one product per pose instead of two).

    Returns:
        (N,) tensor on ``device``, mm.
    """
    torch = _torch()
    dev, dt, budget = _setup(device, dtype)
    n, (R_e, te, R_g, tg) = _pairs(R_est, t_est, R_gt, t_gt, dev, torch.float64)
    X = torch.as_tensor(_points(pts, "pts"), device=dev).to(dt)
    A, b = (R_e - R_g).to(dt), (te - tg).to(dt)
    out = torch.empty(n, device=dev, dtype=dt)
    for a, c in _chunks(n, budget // (4 * X.shape[0])):
        d = (A[a:c].reshape(-1, 3) @ X.T).view(c - a, 3, -1) + b[a:c, :, None]
        out[a:c] = torch.linalg.vector_norm(d, dim=1).mean(dim=1)
    return out


def re_torch(
    R_est: Any, R_gt: Any, *, device: str | torch.device = "auto", dtype: Any = None
) -> torch.Tensor:
    """Rotation error in degrees on torch, ``acos(clip((tr(R_e R_g⁻¹) − 1) / 2))``.

    Returns:
        (N,) tensor on ``device``, degrees.
    """
    torch = _torch()
    dev, dt, _ = _setup(device, dtype)
    _, (R_e, R_g) = _broadcast(
        _rotations(R_est, "R_est", dev, dt), _rotations(R_gt, "R_gt", dev, dt)
    )
    c = 0.5 * (torch.diagonal(R_e @ torch.linalg.inv(R_g), dim1=1, dim2=2).sum(dim=1) - 1.0)
    return 180.0 * torch.arccos(c.clamp(-1.0, 1.0)) / np.pi


def te_torch(
    t_est: Any, t_gt: Any, *, device: str | torch.device = "auto", dtype: Any = None
) -> torch.Tensor:
    """Translation error ``‖t_g − t_e‖`` in mm on torch.

    Returns:
        (N,) tensor on ``device``, mm.
    """
    dev, dt, _ = _setup(device, dtype)
    _, (a, b) = _broadcast(
        _translations(t_est, "t_est", dev, dt), _translations(t_gt, "t_gt", dev, dt)
    )
    return _norm3(b - a)
