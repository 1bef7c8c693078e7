"""Numerical inverse kinematics of the dVRK PSM (Large Needle Driver).

Solves ``psm_tip_pose(q) == T_base_tip`` for the six joints ``q = (outer_yaw, outer_pitch,
insertion [m], outer_roll, wrist_pitch, wrist_yaw)`` with damped least squares
(Levenberg–Marquardt) on the geometric Jacobian of
:func:`bopsurg.generators.kinematics.psm_link_frames`. Each step is projected onto the joint
limits, so every answer is within :data:`~bopsurg.generators.kinematics.PSM_JOINT_LIMITS`.

The residual stacks the position error (m, divided by :data:`POSITION_SCALE` so that 1 cm
weighs like 1 rad) and the orientation error as a rotation vector (rad), both in the base frame.
A solve is *converged* when the position error is below ``tol_mm`` and the orientation error
below ``tol_deg``; a pose that no start reaches raises :class:`IKError`.

Warm starts make trajectories cheap: from the previous sample's joints a solve takes 2–3
iterations (about 0.2 ms). A cold start is seeded from the wrist position (the RCM geometry
gives yaw, pitch and insertion in closed form) and retried with a few roll angles.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bopsurg.errors import InputError
from bopsurg.generators.kinematics import (
    L_PITCH2YAW,
    L_RCC,
    L_TOOL,
    PSM_JOINT_LIMITS,
    PSM_JOINT_NAMES,
    psm_link_frames,
)

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Length (m) that weighs like one radian in the residual.
POSITION_SCALE = 0.01
#: Default convergence tolerances: position (mm) and orientation (degrees).
TOL_MM = 1e-4
TOL_DEG = 1e-4

_LO = PSM_JOINT_LIMITS[:, 0]
_HI = PSM_JOINT_LIMITS[:, 1]
_REVOLUTE = np.array([True, True, False, True, True, True])


class IKError(InputError):
    """A tool-tip pose the PSM cannot reach within its joint limits."""


@dataclass(frozen=True)
class IKResult:
    """Outcome of one solve.

    Attributes:
        q: (6,) joints, always within the limits (the best found when not converged).
        converged: Whether both tolerances were met.
        pos_err_mm: Remaining position error, mm.
        rot_err_deg: Remaining orientation error, degrees.
        iterations: Iterations used, over all starts.
    """

    q: F64
    converged: bool
    pos_err_mm: float
    rot_err_deg: float
    iterations: int


def _log_rotation(R: F64) -> F64:
    """Rotation vector (rad) of a rotation matrix, robust near 0 and π."""
    cos = np.clip(0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0), -1.0, 1.0)
    angle = float(np.arccos(cos))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-6:
        return 0.5 * axis  # first order: sin(a) ≈ a
    if np.pi - angle > 1e-4:
        scaled: F64 = axis * (angle / (2.0 * np.sin(angle)))
        return scaled
    # Near π the antisymmetric part vanishes: read the axis from the symmetric part.
    sym = 0.5 * (R + np.eye(3))
    k = int(np.argmax(np.diag(sym)))
    u = sym[:, k] / np.sqrt(max(sym[k, k], 1e-300))
    if axis @ u < 0.0:
        u = -u
    out: F64 = angle * u / np.linalg.norm(u)
    return out


def _residual(T: F64, T_target: F64) -> tuple[F64, float, float]:
    """Scaled residual (6,), position error (m) and orientation error (rad)."""
    dp = T_target[:3, 3] - T[:3, 3]
    dr = _log_rotation(T_target[:3, :3] @ T[:3, :3].T)
    e = np.concatenate([dp / POSITION_SCALE, dr])
    return e, float(np.linalg.norm(dp)), float(np.linalg.norm(dr))


def _jacobian(frames: list[F64]) -> F64:
    """Geometric Jacobian (6, 6) of the tip in the base frame, position rows scaled."""
    p_tip = frames[-1][:3, 3]
    jac = np.empty((6, 6))
    for i in range(6):
        z = frames[i][:3, 2]  # modified DH: joint i acts along z of frame i
        if _REVOLUTE[i]:
            jac[:3, i] = np.cross(z, p_tip - frames[i][:3, 3])
            jac[3:, i] = z
        else:
            jac[:3, i] = z
            jac[3:, i] = 0.0
    jac[:3] /= POSITION_SCALE
    return jac


def cold_seed(T_base_tip: ArrayLike, roll: float = 0.0) -> F64:
    """A start for a solve without a previous solution.

    Outer yaw, pitch and insertion point the shaft at the approximate wrist centre
    (``L_PITCH2YAW`` behind the tip along the jaws); the wrist starts straight.

    Args:
        T_base_tip: (4, 4) target tip pose in the PSM base (RCM) frame, m.
        roll: Outer roll to start from, rad.

    Returns:
        (6,) joints within the limits.
    """
    T = np.asarray(T_base_tip, dtype=np.float64)
    wrist = T[:3, 3] - L_PITCH2YAW * T[:3, 2]
    dist = float(np.linalg.norm(wrist))
    d = wrist / max(dist, 1e-9)
    # At zero joints the shaft points along -Z; d = (sin q1 cos q2, -sin q2, -cos q1 cos q2).
    q2 = -np.arcsin(np.clip(d[1], -1.0, 1.0))
    q1 = np.arctan2(d[0], -d[2])
    q3 = dist + L_RCC - L_TOOL
    q: F64 = np.clip(np.array([q1, q2, q3, roll, 0.0, 0.0]), _LO, _HI)
    return q


def _solve_from(
    T_target: F64, q0: F64, tol_pos: float, tol_rot: float, max_iter: int
) -> tuple[F64, bool, float, float, int]:
    """Projected Levenberg–Marquardt from ``q0``."""
    q = np.clip(q0, _LO, _HI)
    frames = psm_link_frames(q)
    e, ep, er = _residual(frames[-1], T_target)
    lam = 1e-3
    it = 0
    while it < max_iter:
        if ep <= tol_pos and er <= tol_rot:
            return q, True, ep, er, it
        it += 1
        jac = _jacobian(frames)
        A = jac.T @ jac
        g = jac.T @ e
        dq = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-9), g)
        q_new = np.clip(q + dq, _LO, _HI)
        frames_new = psm_link_frames(q_new)
        e_new, ep_new, er_new = _residual(frames_new[-1], T_target)
        if e_new @ e_new < e @ e:
            q, frames, e, ep, er = q_new, frames_new, e_new, ep_new, er_new
            lam = max(lam * 0.1, 1e-9)
        else:
            lam *= 10.0
            if lam > 1e6:  # stuck against a limit or at a local minimum
                break
    return q, ep <= tol_pos and er <= tol_rot, ep, er, it


def psm_ik_solve(
    T_base_tip: ArrayLike,
    q_seed: ArrayLike | None = None,
    *,
    tol_mm: float = TOL_MM,
    tol_deg: float = TOL_DEG,
    max_iter: int = 60,
    restarts: bool = True,
) -> IKResult:
    """Solve the PSM IK and report how well it went (never raises for unreachable poses).

    Args:
        T_base_tip: (4, 4) tip pose in the base (RCM) frame, m.
        q_seed: (6,) start (the previous sample's solution); ``None`` for a cold start.
        tol_mm: Position tolerance, mm.
        tol_deg: Orientation tolerance, degrees.
        max_iter: Iterations per start.
        restarts: When the seed fails, also try cold starts with several roll angles.

    Returns:
        The best solution found and its residuals.
    """
    T = np.asarray(T_base_tip, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise IKError(f"target pose must be a finite (4, 4) matrix, got shape {T.shape}")
    tol_pos, tol_rot = tol_mm * 1e-3, np.deg2rad(tol_deg)
    seeds: list[F64] = []
    if q_seed is not None:
        seed = np.asarray(q_seed, dtype=np.float64)
        if seed.shape != (6,) or not np.all(np.isfinite(seed)):
            raise IKError(f"q_seed must be 6 finite joints, got shape {seed.shape}")
        seeds.append(seed)
    if restarts or not seeds:
        base_roll = float(seeds[0][3]) if seeds else 0.0
        for roll in (base_roll, 0.0, np.pi / 2, -np.pi / 2, 2.6, -2.6):
            seeds.append(cold_seed(T, roll))
    best: tuple[F64, bool, float, float] | None = None
    total = 0
    for seed in seeds:
        q, ok, ep, er, it = _solve_from(T, seed, tol_pos, tol_rot, max_iter)
        total += it
        if best is None or ep / POSITION_SCALE + er < best[2] / POSITION_SCALE + best[3]:
            best = (q, ok, ep, er)
        if ok:
            break
    assert best is not None
    q, ok, ep, er = best
    return IKResult(q, ok, ep * 1e3, float(np.rad2deg(er)), total)


def psm_ik(
    T_base_tip: ArrayLike,
    q_seed: ArrayLike | None = None,
    *,
    tol_mm: float = TOL_MM,
    tol_deg: float = TOL_DEG,
) -> F64:
    """Joints (6,) that put the PSM tool tip at ``T_base_tip``; within the joint limits.

    Args:
        T_base_tip: (4, 4) tip pose in the base (RCM) frame, m.
        q_seed: (6,) warm start (e.g. the previous sample's joints); ``None`` for a cold start.
        tol_mm: Position tolerance, mm.
        tol_deg: Orientation tolerance, degrees.

    Raises:
        IKError: The pose is unreachable within the joint limits (from every start tried).
    """
    res = psm_ik_solve(T_base_tip, q_seed, tol_mm=tol_mm, tol_deg=tol_deg)
    if not res.converged:
        raise IKError(_unreachable(res))
    return res.q


def _unreachable(res: IKResult) -> str:
    at_limit = [
        PSM_JOINT_NAMES[i] for i in range(6) if min(res.q[i] - _LO[i], _HI[i] - res.q[i]) < 1e-6
    ]
    limits = f" ({', '.join(at_limit)} at its limit)" if at_limit else ""
    return (
        f"PSM pose unreachable: best solution misses by {res.pos_err_mm:.3g} mm and "
        f"{res.rot_err_deg:.3g} deg{limits}"
    )


def psm_ik_trajectory(
    T_base_tips: ArrayLike,
    q_seed: ArrayLike | None = None,
    *,
    tol_mm: float = TOL_MM,
    tol_deg: float = TOL_DEG,
    strict: bool = True,
) -> tuple[F64, NDArray[np.bool_]]:
    """IK of a whole trajectory, each sample warm-started from the previous solution.

    Args:
        T_base_tips: (N, 4, 4) tip poses in the base frame, m.
        q_seed: (6,) start for the first sample; ``None`` for a cold start.
        tol_mm: Position tolerance, mm.
        tol_deg: Orientation tolerance, degrees.
        strict: Raise at the first unreachable sample; otherwise flag it and go on.

    Returns:
        Joints (N, 6) and a (N,) mask of converged samples.

    Raises:
        IKError: With ``strict``, naming the first unreachable sample.
    """
    T_all = np.asarray(T_base_tips, dtype=np.float64)
    if T_all.ndim != 3 or T_all.shape[1:] != (4, 4):
        raise IKError(f"poses must be (N, 4, 4), got {T_all.shape}")
    q = np.empty((len(T_all), 6))
    ok = np.zeros(len(T_all), dtype=bool)
    prev = None if q_seed is None else np.asarray(q_seed, dtype=np.float64)
    for i, T in enumerate(T_all):
        # Warm start only; restarts are the fallback when a sample jumps.
        res = psm_ik_solve(T, prev, tol_mm=tol_mm, tol_deg=tol_deg, restarts=False)
        if not res.converged:
            res = psm_ik_solve(T, prev, tol_mm=tol_mm, tol_deg=tol_deg)
        if not res.converged and strict:
            raise IKError(f"sample {i}: {_unreachable(res)}")
        q[i], ok[i] = res.q, res.converged
        prev = res.q
    return q, ok
