"""Staging a real robot's recording in bopsurg's scene: where its arms stand, the needle, the view.

A recording of a real dVRK carries the joints of the arms that moved (often one), sometimes
their jaws and the ECM, and never a needle pose. :func:`stage_recording` turns it into a
recording :func:`~bopsurg.generators.replay.run_replay` can render:

* the arms are the recorded ones (any of ``psm1``, ``psm2``, ``psm3``), posed with the dVRK's
  own kinematics of the chosen tool (:mod:`~bopsurg.generators.dvrk_tools`); arms absent
  from the recording are not in the scene;
* each arm's RCM takes its slot of :data:`RCM_SLOTS` (its shaft aiming at the workspace
  centre, as in the default layout), and the whole set of RCMs is then moved by one
  translation so that the recorded tool-tip workspace is centred over the phantom and its
  lowest point (tool tips and the held needle) is :data:`CLEARANCE` above the tissue;
* the needle is held in one arm's jaws with a fixed, plausible grasp (:data:`GRASP`; the
  holder's jaw is closed on it, :data:`GRASP_JAW`), or lies flat on the tissue under the
  workspace;
* the endoscope's base pose looks at the workspace's centre from the default layout's
  direction, far enough that the whole motion stays in view under the replays' drawn ECM
  offsets (the recorded ECM joints, like any bag's, are not used for the camera).

Units: m and rad, world frame of :mod:`~bopsurg.generators.kinematics` (tissue at z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from bopsurg.errors import InputError
from bopsurg.generators.backend import ALL_ARMS, DEFAULT_NEEDLE_POSE
from bopsurg.generators.kinematics import (
    DEFAULT_LAYOUT,
    ECM_CAMERA_OFFSET,
    PsmKinematics,
    SceneLayout,
)
from bopsurg.generators.recording import Recording
from bopsurg.generators.trajectory import needle_grasp
from bopsurg.needle import NeedleSpec

F64 = NDArray[np.float64]

#: RCM of each arm before the workspace is moved over the phantom, m: PSM1 and PSM2 where the
#: default layout has them, PSM3 across the tissue from the endoscope.
RCM_SLOTS: dict[str, tuple[float, float, float]] = {
    "psm1": DEFAULT_LAYOUT.psm_rcm[0],
    "psm2": DEFAULT_LAYOUT.psm_rcm[1],
    "psm3": (0.0, 0.09, 0.10),
}
#: Lowest point of the staged motion (tool tips, held needle) above the tissue, m.
CLEARANCE = 0.005
#: The held needle's grasp: arc angle from the tail (deg), tilt (deg), wire-to-pivot depth
#: (mm), as the middle of the synthetic episodes' first grasps (``trajectory._draw_throws``).
GRASP = (13.0, -15.0, 6.25)
#: Jaw angle closed on the needle's wire, rad (below ``trajectory.GRASP_JAW_THRESHOLD``).
GRASP_JAW = 0.05
#: Half-angle of the image the workspace is framed in, rad: within the vertical half field of
#: view (0.6 rad at the default 1.2), leaving room for most of the drawn ECM rotation (up to
#: ~0.35 rad) without moving the camera so far that the needle shrinks to a few pixels.
FRAMING_HALF_ANGLE = 0.45
#: Share of the motion's points the framing must hold (the rest: its rare excursions).
FRAMING_QUANTILE = 0.9
#: Largest drawn ECM insertion towards the workspace, m (base poses + offsets), and the
#: nearest the camera may then come to the workspace's centre, m.
MAX_ECM_INSERTION = 0.04
MIN_VIEW_DISTANCE = 0.03
#: Samples of a stream used to find the workspace (evenly spaced; the bounds do not need all).
MAX_SAMPLES = 2000


@dataclass(frozen=True)
class Staging:
    """How a recording was staged (for ``inspect`` and the logs).

    Attributes:
        arms: The recorded arms, in the scene.
        holder: The arm holding the needle, or None (on the tissue).
        kinematics: The PSM kinematics (tool) the arms are posed with.
        shift: (3,) translation applied to the arms' slots, m.
        view_target: (3,) the point the endoscope looks at, m.
        view_distance: Camera-to-target distance at zero ECM joints, m.
        extent: Distance from the target within which :data:`FRAMING_QUANTILE` of the staged
            motion's points lie, m.
    """

    arms: tuple[str, ...]
    holder: str | None
    kinematics: PsmKinematics
    shift: F64
    view_target: F64
    view_distance: float
    extent: float


def choose_holder(arms: tuple[str, ...], needle_holder: str) -> str | None:
    """The arm holding the needle: ``auto`` (the recorded arm, or the first of several),
    ``none``, or an arm's name (any case).

    Raises:
        InputError: The named arm is not in the recording.
    """
    key = needle_holder.strip().lower()
    if key == "none":
        return None
    if key == "auto":
        return arms[0]
    if key not in arms:
        raise InputError(
            f"{needle_holder!r} is not a recorded arm (recorded: {', '.join(arms)}; or none)",
            field="--needle-holder",
        )
    return key


def _samples(times: F64, values: F64) -> tuple[F64, F64]:
    step = max(1, int(np.ceil(len(times) / MAX_SAMPLES)))
    return times[::step], values[::step]


def _arc_points(needle: NeedleSpec, count: int = 9) -> F64:
    """(count, 4) homogeneous points on the needle's centre line, model frame, m."""
    arc = np.deg2rad(needle.body_deg + needle.tip_deg)
    s = np.linspace(0.0, arc, count)
    r = needle.arc_radius * 1e-3
    return np.stack([r * np.cos(s), r * np.sin(s), np.zeros(count), np.ones(count)], axis=1)


def stage_recording(
    rec: Recording,
    kinematics: PsmKinematics,
    *,
    needle: NeedleSpec | None = None,
    needle_holder: str = "auto",
) -> tuple[Recording, Staging]:
    """A real robot's recording placed in bopsurg's scene (see the module docstring).

    Args:
        rec: The recording as read (joints of at least one arm).
        kinematics: The PSM and tool to pose the arms with.
        needle: Needle geometry (mm); default :class:`~bopsurg.needle.NeedleSpec`.
        needle_holder: ``auto``, ``none`` or an arm (:func:`choose_holder`).

    Returns:
        The staged recording (its ``layout`` set, a needle pose stream, the holder's jaw
        closed) and how it was staged.

    Raises:
        InputError: No arm in the recording, or a holder that is not recorded.
    """
    needle = needle or NeedleSpec()
    arms = tuple(a for a in ALL_ARMS if a in rec.psm_joints)
    if not arms:
        raise InputError("the recording has no PSM joints", path=rec.source)
    holder = choose_holder(arms, needle_holder)
    slots = SceneLayout(psm_rcm=tuple(RCM_SLOTS[a] for a in arms), arms=arms, kinematics=kinematics)
    T_tn = needle_grasp(needle, GRASP[0], approach=-1, tilt_deg=GRASP[1], depth_mm=GRASP[2])
    points = []  # world points of the motion with the slots as they are
    for arm in arms:
        _, q = _samples(*rec.psm_joints[arm])
        tips = slots.arm_base(arm) @ kinematics.tip_poses(q)
        points.append(tips[:, :3, 3])
        if arm == holder:
            arc = (tips @ T_tn) @ _arc_points(needle).T  # (N, 4, count)
            points.append(arc[:, :3, :].transpose(0, 2, 1).reshape(-1, 3))
    cloud = np.concatenate(points)
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    shift = np.array([-0.5 * (lo[0] + hi[0]), -0.5 * (lo[1] + hi[1]), CLEARANCE - lo[2]])
    cloud = cloud + shift
    target = 0.5 * (cloud.min(axis=0) + cloud.max(axis=0))
    extent = float(np.quantile(np.linalg.norm(cloud - target, axis=1), FRAMING_QUANTILE))
    distance = max(extent / np.tan(FRAMING_HALF_ANGLE), MIN_VIEW_DISTANCE) + MAX_ECM_INSERTION
    direction = np.asarray(DEFAULT_LAYOUT.ecm_frame_origin) - np.asarray(
        DEFAULT_LAYOUT.workspace_centre
    )
    direction /= np.linalg.norm(direction)
    origin = target + (distance + ECM_CAMERA_OFFSET) * direction
    layout = SceneLayout(
        psm_rcm=tuple(_vec3(np.asarray(RCM_SLOTS[a]) + shift) for a in arms),
        workspace_centre=_vec3(np.asarray(DEFAULT_LAYOUT.workspace_centre) + shift),
        ecm_frame_origin=_vec3(origin),
        arms=arms,
        kinematics=kinematics,
        view_target=_vec3(target),
    )
    staged = Recording(
        psm_joints={a: rec.psm_joints[a] for a in arms},
        jaws={a: rec.jaws[a] for a in arms if a in rec.jaws and a != holder},
        needle_pose=_needle_stream(rec, layout, holder, T_tn, needle, target),
        source=rec.source,
        meta=rec.meta,
        psm_poses=rec.psm_poses,
        layout=layout,
        robot=rec.robot,
    )
    if holder is not None:
        times = rec.psm_joints[holder][0]
        staged.jaws[holder] = (times, np.full(len(times), GRASP_JAW))
    info = Staging(arms, holder, kinematics, shift, target, distance, extent)
    return staged, info


def _vec3(v: F64) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def _needle_stream(
    rec: Recording,
    layout: SceneLayout,
    holder: str | None,
    T_tn: F64,
    needle: NeedleSpec,
    target: F64,
) -> tuple[F64, F64]:
    """``T_world_needle`` over time: in the holder's jaws, or flat on the tissue below the
    workspace's centre (one sample)."""
    if holder is None:
        T = DEFAULT_NEEDLE_POSE.copy()
        T[:2, 3] = target[:2]
        T[2, 3] = 0.5e-3 * needle.wire_diameter
        return np.array([rec.start]), T[None]
    times, q = rec.psm_joints[holder]
    T_world_tip = layout.arm_base(holder) @ layout.kinematics.tip_poses(q)
    return times, T_world_tip @ T_tn


__all__ = [
    "CLEARANCE",
    "GRASP",
    "GRASP_JAW",
    "RCM_SLOTS",
    "Staging",
    "choose_holder",
    "stage_recording",
]
