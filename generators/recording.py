"""A suturing episode in memory: time-stamped streams and the scene state at any instant.

A :class:`Recording` holds the streams (joints of each PSM, jaws, ECM joints, needle pose) that
synthesis (:mod:`~bopsurg.generators.trajectory`) produces and bags carry
(:mod:`~bopsurg.generators.bags`), and answers :meth:`Recording.state_at` with the
:class:`~bopsurg.generators.backend.SceneState` a render backend replays. Streams a recording
lacks take the default scene state of :mod:`~bopsurg.generators.backend`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from bopsurg.generators.backend import (
    ARMS,
    DEFAULT_ECM_JOINTS,
    DEFAULT_NEEDLE_POSE,
    PARKED_JAW,
    PARKED_PSM_JOINTS,
    SceneState,
)
from bopsurg.generators.kinematics import SceneLayout

F64 = NDArray[np.float64]
Stream = tuple[F64, F64]  # (times (T,) s, values (T, ...))

#: Absolute time (ns since the epoch) of t = 0 when a recording does not say (2023-11-14).
DEFAULT_TIME_ORIGIN_NS = 1_700_000_000 * 10**9


@dataclass
class Recording:
    """A suturing episode as time-stamped streams, the form shared by synthesis and bags.

    Times are float64 seconds relative to the recording's time origin
    (``meta["time_origin_ns"]``, ns since the epoch), strictly increasing per stream.

    Attributes:
        psm_joints: Per arm (``"psm1"``, ``"psm2"``): (times (T,), joints (T, 6)), rad and m.
        jaws: Per arm: (times (T,), jaw opening (T,)), rad.
        ecm_joints: (times, (T, 4)) yaw, pitch (rad), insertion (m), roll (rad), or None.
        needle_pose: (times, (T, 4, 4)) ``T_world_needle``, m, or None.
        source: Where it came from (a bag path, or the generator and seed).
        meta: JSON-serialisable facts: seed, generator, layout, needle spec, events, ...
        psm_poses: Per arm: (times, (T, 4, 4)) the tool tip's recorded Cartesian pose
            (``measured_cp``), m, in the frame the robot reported it in (not the world's);
            for checks, never replayed.
        layout: Where the recording's arms stand in bopsurg's world and with which
            kinematics (a real robot's recording placed by
            :func:`~bopsurg.generators.staging.stage_recording`); None: the default layout.
        robot: Whose kinematics replay it: ``simulator`` (bopsurg's, AMBF) or ``dvrk`` (a
            real robot's recording; see the topic map's ``robot``).
    """

    psm_joints: dict[str, Stream] = field(default_factory=dict)
    jaws: dict[str, Stream] = field(default_factory=dict)
    ecm_joints: Stream | None = None
    needle_pose: Stream | None = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)
    psm_poses: dict[str, Stream] = field(default_factory=dict)
    layout: SceneLayout | None = None
    robot: str = "simulator"

    def streams(self) -> list[tuple[str, str | None, Stream]]:
        """Every stream as (kind, arm or None, (times, values))."""
        out: list[tuple[str, str | None, Stream]] = []
        out += [("psm_joints", arm, s) for arm, s in sorted(self.psm_joints.items())]
        out += [("jaw", arm, s) for arm, s in sorted(self.jaws.items())]
        if self.ecm_joints is not None:
            out.append(("ecm_joints", None, self.ecm_joints))
        if self.needle_pose is not None:
            out.append(("needle_pose", None, self.needle_pose))
        return out

    @property
    def start(self) -> float:
        """Earliest sample time over all streams, s (0.0 for an empty recording)."""
        firsts = [s[0][0] for _, _, s in self.streams() if len(s[0])]
        return float(min(firsts)) if firsts else 0.0

    @property
    def end(self) -> float:
        """Latest sample time over all streams, s."""
        lasts = [s[0][-1] for _, _, s in self.streams() if len(s[0])]
        return float(max(lasts)) if lasts else 0.0

    @property
    def duration(self) -> float:
        """``end - start``, s."""
        return self.end - self.start

    def state_at(self, t: float) -> SceneState:
        """The scene at time ``t`` (s): interpolated, clamped to each stream's ends.

        Joints and jaws interpolate linearly; the needle pose linearly in translation and by
        slerp in rotation. Streams the recording lacks take the default scene state of
        :func:`~bopsurg.generators.backend.default_state`: arms ``psm1`` and ``psm2`` parked,
        the ECM at its base pose, the needle on the tissue. With a ``layout``, the state holds
        exactly its arms.
        """
        if self.layout is not None:
            arms = list(self.layout.arms)
        else:
            arms = sorted({*ARMS, *self.psm_joints, *self.jaws})
        joints = {
            arm: _interp(*self.psm_joints[arm], t)
            if arm in self.psm_joints
            else PARKED_PSM_JOINTS.copy()
            for arm in arms
        }
        jaws = {
            arm: float(_interp(*self.jaws[arm], t)) if arm in self.jaws else PARKED_JAW
            for arm in arms
        }
        ecm = (
            _interp(*self.ecm_joints, t)
            if self.ecm_joints is not None
            else DEFAULT_ECM_JOINTS.copy()
        )
        needle = (
            _interp_pose(*self.needle_pose, t)
            if self.needle_pose is not None
            else DEFAULT_NEEDLE_POSE.copy()
        )
        return SceneState(psm_joints=joints, jaws=jaws, ecm_joints=ecm, needle_pose=needle)


def _bracket(times: F64, t: float) -> tuple[int, float]:
    """Index i and weight w with t ≈ (1 - w) times[i] + w times[i + 1], clamped."""
    n = len(times)
    if n == 1 or t <= times[0]:
        return 0, 0.0
    if t >= times[-1]:
        return n - 2, 1.0
    i = int(np.searchsorted(times, t, side="right")) - 1
    return i, float((t - times[i]) / (times[i + 1] - times[i]))


def _interp(times: F64, values: F64, t: float) -> F64:
    i, w = _bracket(times, t)
    if len(times) == 1:
        return np.array(values[0], dtype=np.float64)
    out: F64 = (1.0 - w) * values[i] + w * values[i + 1]
    return out


def _interp_pose(times: F64, poses: F64, t: float) -> F64:
    i, w = _bracket(times, t)
    if len(times) == 1 or w == 0.0:
        return np.array(poses[i], dtype=np.float64)
    T_a, T_b = poses[i], poses[i + 1]
    if w == 1.0:
        return np.array(T_b, dtype=np.float64)
    rv = Rotation.from_matrix(T_a[:3, :3].T @ T_b[:3, :3]).as_rotvec()
    T = np.eye(4)
    T[:3, :3] = T_a[:3, :3] @ Rotation.from_rotvec(w * rv).as_matrix()
    T[:3, 3] = (1.0 - w) * T_a[:3, 3] + w * T_b[:3, 3]
    return T


__all__ = ["DEFAULT_TIME_ORIGIN_NS", "Recording", "Stream"]
