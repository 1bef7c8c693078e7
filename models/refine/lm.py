"""Levenberg-Marquardt for poses, from several starts in lockstep.

Both needle fits use it: the image (and RGB-D) fit of :mod:`.fit`, whose state is a pose
increment per start with a Gaussian prior on it, and the depth-only fit of :mod:`.depth_fit`,
whose state is the poses themselves. The objective gives, per start, the robust cost, the
residuals, their IRLS weights and the Jacobian of the residuals with respect to a step
(ω, δt) (rad, mm); ``apply`` moves the state by a step. Every start takes a damped
Gauss-Newton step at once (one batched solve); a step that does not lower its start's cost is
rejected and that start's damping raised.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
State = TypeVar("State", F64, tuple[F64, ...])

#: (cost (B,), residuals (B, M), IRLS weights (B, M), Jacobian (B, M, 6)) of a state.
Evaluation = tuple[F64, F64, F64, F64]


def levenberg_marquardt(
    objective: Callable[[State], Evaluation],
    state: State,
    apply: Callable[[State, F64], State],
    iterations: int,
    lambda0: float,
    *,
    prior: Callable[[State], tuple[F64, F64]] | None = None,
    floor: float = 0.0,
    rtol: float | None = 1e-6,
) -> tuple[State, F64]:
    """Minimise ``objective`` from ``state`` (B starts); returns (state, cost (B,)).

    Args:
        objective: The state's :data:`Evaluation`; its cost includes the prior's, if any.
        state: (B, ...) array, or a tuple of them, one row per start.
        apply: The state moved by steps (B, 6).
        iterations: At most this many steps.
        lambda0: The damping at the start (× the Hessian's diagonal; × 0.3 after a step
            taken, × 10 after one rejected).
        prior: A Gaussian prior's Hessian (6, 6) and gradient (B, 6) at a state, added to
            the data's.
        floor: Added to the diagonal before the damping scales it, so that a Hessian
            singular in some direction (points on a line, no prior) still gives a step.
        rtol: Stop when every start's last accepted step lowered its cost by less than this
            share, or its damping reached 1 after a rejected one; None: run every iteration.
    """
    lam = np.full(len(_rows(state)[0]), lambda0)
    cost, r, w, J = objective(state)
    for _ in range(iterations):
        JtW = J.transpose(0, 2, 1) * w[:, None, :]
        H = JtW @ J
        grad = (JtW @ r[..., None])[..., 0]
        if prior is not None:
            prior_H, prior_grad = prior(state)
            H, grad = H + prior_H, grad + prior_grad
        diag = np.einsum("bii->bi", H)
        A = H + (lam[:, None] * (diag + floor))[..., None] * np.eye(6)
        moved = apply(state, -np.linalg.solve(A, grad[..., None])[..., 0])
        c_new, r_new, w_new, J_new = objective(moved)
        better = np.isfinite(c_new) & (c_new < cost)
        cost_before = cost
        state = _where(better, moved, state)
        cost = np.where(better, c_new, cost)
        r = np.where(better[:, None], r_new, r)
        w = np.where(better[:, None], w_new, w)
        J = np.where(better[:, None, None], J_new, J)
        lam_before = lam
        lam = np.where(better, lam * 0.3, lam * 10.0)
        if rtol is None:
            continue
        converged = np.where(better, cost_before - cost < rtol * cost_before, lam_before >= 1.0)
        if converged.all():  # every start stopped moving: the rest would be rejected steps
            break
    return state, cost


def _rows(state: F64 | tuple[F64, ...]) -> tuple[F64, ...]:
    return state if isinstance(state, tuple) else (state,)


def _where(take: NDArray[np.bool_], new: State, old: State) -> State:
    """``new``'s rows where ``take`` (B,), else ``old``'s."""
    out = tuple(
        np.where(take.reshape(-1, *([1] * (a.ndim - 1))), a, b)
        for a, b in zip(_rows(new), _rows(old), strict=True)
    )
    return out if isinstance(new, tuple) else out[0]
