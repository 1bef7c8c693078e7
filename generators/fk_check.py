"""Checking a PSM's forward kinematics against the Cartesian poses its controller recorded.

A real dVRK records each arm's joints (``measured_js``) and its tool-tip pose
(``measured_cp``), the latter in a frame of the controller's choosing (often the ECM's). The
kinematics that replay the joints (:class:`~bopsurg.generators.kinematics.PsmKinematics`)
reproduce the controller only up to that unknown rigid transform, so :func:`fk_check`
registers the forward-kinematics tool tips to the recorded ones (Kabsch / Umeyama without
scale, samples paired by header stamp) and reports what is left: the residuals say whether
the kinematics (tool, lengths) are the robot's.

Units: positions m (reported in mm), rotations rad (reported in degrees).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from bopsurg.generators.kinematics import PsmKinematics

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
Stream = tuple[F64, F64]

#: Largest stamp difference between a joint sample and a pose sample that pair, s.
PAIR_TOLERANCE = 1e-3


@dataclass(frozen=True)
class FkCheck:
    """How well forward kinematics, rigidly registered, reproduces the recorded poses.

    Attributes:
        arm: The arm (``psm2``).
        pairs: Joint and pose samples paired by stamp.
        rms_mm, max_mm: Tool-tip position residuals after registration, mm.
        rot_rms_deg, rot_max_deg: Tool-tip rotation residuals after registration, degrees.
        T_frame_base: (4, 4) the registration: the arm's base (RCM) frame in the frame the
            poses were recorded in, m.
    """

    arm: str
    pairs: int
    rms_mm: float
    max_mm: float
    rot_rms_deg: float
    rot_max_deg: float
    T_frame_base: F64

    def line(self) -> str:
        """``fk-check PSM2: N pairs, rms X mm, max Y mm, rotation rms A deg, max B deg``."""
        return (
            f"fk-check {self.arm.upper()}: {self.pairs} pairs, rms {self.rms_mm:.4f} mm, "
            f"max {self.max_mm:.4f} mm, rotation rms {self.rot_rms_deg:.4f} deg, "
            f"max {self.rot_max_deg:.4f} deg"
        )


def pair_by_stamp(t_a: F64, t_b: F64, tolerance: float = PAIR_TOLERANCE) -> tuple[I64, I64]:
    """Indices (ia, ib) of the samples of two increasing time series that pair: each sample
    of ``t_a`` with the nearest of ``t_b`` when within ``tolerance`` (s)."""
    t_a, t_b = np.asarray(t_a, np.float64), np.asarray(t_b, np.float64)
    j: I64 = np.zeros(len(t_a), dtype=np.int64)
    if len(t_b) == 0:
        return j[:0], j[:0]
    if len(t_b) > 1:
        after = np.clip(np.searchsorted(t_b, t_a), 1, len(t_b) - 1).astype(np.int64)
        nearer_before = np.abs(t_b[after - 1] - t_a) <= np.abs(t_b[after] - t_a)
        j = np.where(nearer_before, after - 1, after)
    ok = np.abs(t_b[j] - t_a) <= tolerance
    ia: I64 = np.flatnonzero(ok).astype(np.int64)
    return ia, j[ok]


def register_rigid(src: F64, dst: F64) -> tuple[F64, F64]:
    """Rotation R (3, 3) and translation t (3,) minimising ``sum |R src + t - dst|²`` (no
    scale; Kabsch / Umeyama).

    Args:
        src, dst: (N, 3) corresponding points, N ≥ 3 not all on one line.
    """
    p0, q0 = src.mean(axis=0), dst.mean(axis=0)
    cov = (src - p0).T @ (dst - q0)
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    R: F64 = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return R, q0 - R @ p0


def fk_check(arm: str, joints: Stream, poses: Stream, kinematics: PsmKinematics) -> FkCheck | None:
    """Register the forward kinematics of ``joints`` to the recorded ``poses``.

    Args:
        arm: The arm's name.
        joints: (times (N,) s, joints (N, 6)).
        poses: (times (M,) s, tool-tip poses (M, 4, 4), m) in any fixed frame.
        kinematics: The PSM and tool.

    Returns:
        The residuals and the registration; None with fewer than 3 pairs or pairs that do not
        span a plane (nothing to register).
    """
    ia, ib = pair_by_stamp(joints[0], poses[0])
    if len(ia) < 3:
        return None
    fk = kinematics.tip_poses(joints[1][ia])
    rec = np.asarray(poses[1], np.float64)[ib]
    p_fk, p_rec = fk[:, :3, 3], rec[:, :3, 3]
    if np.linalg.matrix_rank(p_fk - p_fk.mean(axis=0), tol=1e-9) < 2:
        return None
    R, t = register_rigid(p_fk, p_rec)
    err = np.linalg.norm(p_fk @ R.T + t - p_rec, axis=1)
    R_res = np.swapaxes(R @ fk[:, :3, :3], 1, 2) @ rec[:, :3, :3]
    cos = np.clip((np.trace(R_res, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return FkCheck(
        arm=arm,
        pairs=len(ia),
        rms_mm=float(np.sqrt(np.mean(err**2)) * 1e3),
        max_mm=float(err.max() * 1e3),
        rot_rms_deg=float(np.sqrt(np.mean(ang**2))),
        rot_max_deg=float(ang.max()),
        T_frame_base=T,
    )


__all__ = ["PAIR_TOLERANCE", "FkCheck", "fk_check", "pair_by_stamp", "register_rigid"]
