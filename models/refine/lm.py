"""Levenberg-Marquardt for poses, batched: many problems, each from several starts, at once.

Both needle fits use it: the image (and RGB-D) fit of :mod:`.fit`, whose state is a pose
increment per start with a Gaussian prior on it, and the depth-only fit of :mod:`.depth_fit`,
whose state is the poses themselves. A batch row is one start of one problem (one needle);
``group`` names each row's problem. The objective gives, per row, the robust cost and the
Gauss-Newton normal equations of its data: the Hessian JᵀWJ and gradient JᵀWr of the IRLS
weighted residuals with respect to a step (ω, δt) (rad, mm) (:func:`normal_equations`,
summed per term by the caller, so that the residuals, padded to one count per batch with
zero weights, are never concatenated or copied between steps); ``apply`` moves the state by
a step. Every row takes a damped Gauss-Newton step at once (one batched solve); a step that
does not lower its row's cost is rejected and that row's damping raised. A problem stops (its
rows stop changing) once all its starts have converged at the same step; the batch stops
when every problem has.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

import torch
from torch import Tensor

State = TypeVar("State", Tensor, tuple[Tensor, ...])

#: (cost (B,), Hessian JᵀWJ (B, 6, 6), gradient JᵀWr (B, 6)) of a state.
Evaluation = tuple[Tensor, Tensor, Tensor]


def normal_equations(
    r: Tensor,
    w: Tensor,
    J: Tensor,  # noqa: N803
    *,
    by_row: bool = False,
    by_component: bool = False,
) -> tuple[Tensor, Tensor]:
    """JᵀWJ (B, 6, 6) and JᵀWr (B, 6) of residuals ``r`` (B, M), IRLS weights ``w`` (B, M)
    and Jacobian ``J`` (B, M, 6), or (B, 6, M) with ``by_row``, or (6, B, M) with
    ``by_component`` (the faster layouts: both products then run along contiguous rows)."""
    if by_component:
        J = J.transpose(0, 1)
    Jt = J if by_row or by_component else J.transpose(1, 2)
    JtW = Jt * w[:, None, :]
    return JtW @ Jt.transpose(1, 2), (JtW * r[:, None, :]).sum(-1)


def levenberg_marquardt(
    objective: Callable[[State], Evaluation],
    state: State,
    apply: Callable[[State, Tensor], State],
    iterations: int,
    lambda0: float,
    *,
    prior: Callable[[State], tuple[Tensor, Tensor]] | None = None,
    floor: float = 0.0,
    rtol: float | None = 1e-6,
    group: Tensor | None = None,
    first: Evaluation | None = None,
) -> tuple[State, Tensor]:
    """Minimise ``objective`` from ``state`` (B rows); returns (state, cost (B,)).

    Args:
        objective: The state's :data:`Evaluation`; its cost includes the prior's, if any.
        state: (B, ...) tensor, or a tuple of them, one row per start.
        apply: The state moved by steps (B, 6).
        iterations: At most this many steps.
        lambda0: The damping at the start (× the Hessian's diagonal; × 0.3 after a step
            taken, × 10 after one rejected).
        prior: A Gaussian prior's Hessian (6, 6) and gradient (B, 6) at a state, added to
            the data's.
        floor: Added to the diagonal before the damping scales it, so that a Hessian
            singular in some direction (points on a line, no prior) still gives a step.
        rtol: A problem stops when each of its starts' last accepted step lowered its cost by
            less than this share, or its damping reached 1 after a rejected one; None: run
            every iteration.
        group: (B,) int64 problem index of each row (default: one problem).
        first: The objective at ``state``, where the caller has it already.
    """
    rows = _rows(state)[0]
    lam = torch.full((len(rows),), lambda0, dtype=rows.dtype, device=rows.device)
    if group is None:
        group = torch.zeros(len(rows), dtype=torch.int64, device=rows.device)
    frozen = torch.zeros(len(rows), dtype=torch.bool, device=rows.device)
    eye = torch.eye(6, dtype=rows.dtype, device=rows.device)
    cost, H_data, g_data = first if first is not None else objective(state)
    for _ in range(iterations):
        H, grad = H_data, g_data
        if prior is not None:
            prior_H, prior_grad = prior(state)
            H, grad = H + prior_H, grad + prior_grad
        diag = H.diagonal(dim1=-2, dim2=-1)
        A = H + (lam[:, None] * (diag + floor))[..., None] * eye
        moved = apply(state, -torch.linalg.solve(A, grad[..., None])[..., 0])
        c_new, H_new, g_new = objective(moved)
        better = torch.isfinite(c_new) & (c_new < cost) & ~frozen
        cost_before = cost
        state = _where(better, moved, state)
        cost = torch.where(better, c_new, cost)
        H_data = torch.where(better[:, None, None], H_new, H_data)
        g_data = torch.where(better[:, None], g_new, g_data)
        lam_before = lam
        lam = torch.where(frozen, lam, torch.where(better, lam * 0.3, lam * 10.0))
        if rtol is None:
            continue
        converged = torch.where(better, cost_before - cost < rtol * cost_before, lam_before >= 1.0)
        frozen = frozen | _all_in_group(converged | frozen, group)
        if bool(frozen.all()):  # every problem stopped moving: the rest would be rejected
            break
    return state, cost


@contextmanager
def fit_threads(device: torch.device) -> Iterator[None]:
    """On the CPU, one intra-op thread while a fit runs: its tensors are small (thousands of
    elements), so handing each op to a second thread costs more than it saves, and far more
    when other processes hold the cores. Restores the thread count after."""
    if device.type != "cpu":
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _all_in_group(flag: Tensor, group: Tensor) -> Tensor:
    """(B,) whether ``flag`` holds for every row of each row's group."""
    missing = torch.zeros(int(group.max()) + 1, dtype=torch.int64, device=flag.device)
    missing.index_add_(0, group, (~flag).to(torch.int64))
    return missing[group] == 0


def _rows(state: Tensor | tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    return state if isinstance(state, tuple) else (state,)


def _where(take: Tensor, new: State, old: State) -> State:
    """``new``'s rows where ``take`` (B,), else ``old``'s."""
    out = tuple(
        torch.where(take.reshape(-1, *([1] * (a.ndim - 1))), a, b)
        for a, b in zip(_rows(new), _rows(old), strict=True)
    )
    return out if isinstance(new, tuple) else out[0]
