"""dVRK PSM and ECM forward kinematics, and the scene layout they live in.

Units: metres and radians (ROS / CRTK SI), 4×4 homogeneous transforms ``T_a_b`` mapping
coordinates in frame ``b`` to frame ``a``. The world frame has +Z up; the tissue phantom's
top surface is the plane z = 0 around the origin.

PSM: modified Denavit–Hartenberg chains (:class:`PsmKinematics`, the dVRK's convention:
``Rx(alpha) Tx(a) Rz(theta) Tz(d)`` per link, then a fixed tool-tip offset). Two sources:
the simulator's Large Needle Driver (:data:`SIMULATOR_PSM`, surgical_robotics_challenge
``kinematics/psmFK.py``, see ``surgical_scene_facts.md`` §2.3), which replays bopsurg's own and
the AMBF recordings, and the dVRK's own tool definitions
(:mod:`~bopsurg.generators.dvrk_tools`), which replay recordings of real robots.
The base frame's origin is the remote centre of motion (RCM); at zero outer joints the shaft
points along −Z of the base frame. Joints ``q = (outer_yaw, outer_pitch, insertion [m],
outer_roll, wrist_pitch, wrist_yaw)``; the jaw angle is separate.

ECM: as the simulator does it, a camera frame rotated about its own origin by yaw (j0) and
pitch (j1), moved along its viewing axis by the insertion (j2, m; negative = retract) and
rolled (j3); the left camera sits 50 mm in front of that origin. Camera frames here use
OpenCV axes (x right, y down, z forward), as BOP does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

# Lengths of the simulator's Large Needle Driver 400006, m (psmFK.py, paper era).
L_RCC = 0.4389
L_TOOL = 0.416
L_PITCH2YAW = 0.009
L_YAW2CTRLPNT = 0.0

#: PSM joint names (CRTK order) and software limits (lower, upper): rad, insertion in m.
PSM_JOINT_NAMES = (
    "outer_yaw",
    "outer_pitch",
    "outer_insertion",
    "outer_roll",
    "outer_wrist_pitch",
    "outer_wrist_yaw",
)
PSM_JOINT_LIMITS = np.array(
    [
        [-1.605, 1.599],
        [-0.925, 0.925],
        [0.0, 0.240],
        [-3.054, 3.054],
        [-1.396, 1.396],
        [-1.396, 1.396],
    ]
)
#: Jaw opening limits, rad.
JAW_LIMITS = (-0.698, 1.396)

#: ECM joint names and limits: yaw, pitch (rad), insertion (m), roll (rad).
ECM_JOINT_NAMES = ("yaw", "pitch", "insertion", "roll")
ECM_JOINT_LIMITS = np.array([[-1.5, 1.5], [-1.5, 1.5], [-0.1, 0.1], [-1.57, 1.57]])
#: The left camera's offset in front of the ECM camera-frame origin, m.
ECM_CAMERA_OFFSET = 0.05
#: Stereo baseline, m (the right camera is +x of the left one).
STEREO_BASELINE = 0.004


def mdh(alpha: float, a: float, theta: float, d: float) -> F64:
    """Modified (Craig) DH transform of one link: Rx(alpha) Tx(a) Rz(theta) Tz(d)."""
    ca, sa, ct, st = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta)
    return np.array(
        [
            [ct, -st, 0.0, a],
            [st * ca, ct * ca, -sa, -sa * d],
            [st * sa, ct * sa, ca, ca * d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


@dataclass(frozen=True)
class DhJoint:
    """One link of a modified-DH chain, as the dVRK's kinematics files write it.

    The link transform is ``Rx(alpha) Tx(a) Rz(theta) Tz(d)``; the joint value ``q`` plus
    ``offset`` adds to ``theta`` (revolute) or to ``d`` (prismatic). Units: rad and m.
    """

    alpha: float
    a: float
    theta: float
    d: float
    offset: float = 0.0
    prismatic: bool = False


@dataclass(frozen=True)
class PsmKinematics:
    """A PSM with one tool: six DH joints, the fixed tool-tip offset, limits and provenance.

    Attributes:
        name: Tool name (``LARGE_NEEDLE_DRIVER_400006``, ``simulator``, ...).
        joints: The six joints in CRTK order (outer yaw, outer pitch, insertion, roll,
            wrist pitch, wrist yaw).
        tip_offset: (4, 4) fixed transform from the last joint's frame to the tool tip.
        joint_limits: (6, 2) lower and upper limits, rad and m.
        jaw_limits: Jaw opening limits, rad.
        source: Where the numbers come from (repository, path, commit).
    """

    name: str
    joints: tuple[DhJoint, ...]
    tip_offset: tuple[tuple[float, ...], ...]
    joint_limits: tuple[tuple[float, float], ...]
    jaw_limits: tuple[float, float]
    source: str

    def limits(self) -> F64:
        """(6, 2) joint limits as an array."""
        return np.asarray(self.joint_limits, dtype=np.float64)

    def link_frames(self, q: ArrayLike) -> list[F64]:
        """Seven 4×4 ``T_base_link`` for joints ``q`` (6,): six links and the tool tip."""
        q = np.asarray(q, dtype=np.float64)
        frames = []
        T = np.eye(4)
        for j, qj in zip(self.joints, q, strict=True):
            theta = j.theta if j.prismatic else j.theta + qj + j.offset
            d = j.d + qj + j.offset if j.prismatic else j.d
            T = T @ mdh(j.alpha, j.a, theta, d)
            frames.append(T)
        frames.append(T @ np.asarray(self.tip_offset, dtype=np.float64))
        return frames

    def tip_poses(self, q: ArrayLike) -> F64:
        """Tool-tip frames ``T_base_tip`` (N, 4, 4) for joints ``q`` (N, 6), vectorised."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        T = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
        for k, j in enumerate(self.joints):
            zeros = np.zeros(len(q))
            theta = j.theta + zeros if j.prismatic else j.theta + q[:, k] + j.offset
            d = j.d + q[:, k] + j.offset if j.prismatic else j.d + zeros
            T = T @ mdh_batch(j.alpha, j.a, theta, d)
        out: F64 = T @ np.asarray(self.tip_offset, dtype=np.float64)
        return out


#: The simulator's Large Needle Driver (surgical_robotics_challenge ``kinematics/psmFK.py``,
#: see the module docstring): what bopsurg's own and AMBF recordings are replayed with.
SIMULATOR_PSM = PsmKinematics(
    name="simulator",
    joints=(
        DhJoint(np.pi / 2, 0.0, 0.0, 0.0, np.pi / 2),
        DhJoint(-np.pi / 2, 0.0, 0.0, 0.0, -np.pi / 2),
        DhJoint(np.pi / 2, 0.0, 0.0, 0.0, -L_RCC, prismatic=True),
        DhJoint(0.0, 0.0, 0.0, L_TOOL),
        DhJoint(-np.pi / 2, 0.0, 0.0, 0.0, -np.pi / 2),
        DhJoint(-np.pi / 2, L_PITCH2YAW, 0.0, 0.0, -np.pi / 2),
    ),
    tip_offset=tuple(
        tuple(float(x) for x in row) for row in mdh(-np.pi / 2, 0.0, np.pi / 2, L_YAW2CTRLPNT)
    ),
    joint_limits=(
        (-1.605, 1.599),
        (-0.925, 0.925),
        (0.0, 0.240),
        (-3.054, 3.054),
        (-1.396, 1.396),
        (-1.396, 1.396),
    ),
    jaw_limits=(-0.698, 1.396),
    source="surgical-robotics-ai/surgical_robotics_challenge kinematics/psmFK.py (paper era)",
)


def mdh_batch(alpha: float, a: float, theta: F64, d: F64) -> F64:
    """:func:`mdh` for arrays ``theta`` and ``d`` (N,): (N, 4, 4)."""
    ca, sa = np.cos(alpha), np.sin(alpha)
    ct, st = np.cos(theta), np.sin(theta)
    T = np.zeros((len(theta), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 3] = ct, -st, a
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2], T[:, 1, 3] = st * ca, ct * ca, -sa, -sa * d
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2], T[:, 2, 3] = st * sa, ct * sa, ca, ca * d
    T[:, 3, 3] = 1.0
    return T


def psm_link_frames(q: ArrayLike, kinematics: PsmKinematics | None = None) -> list[F64]:
    """Frames of the PSM links in the base (RCM) frame for joints ``q`` (6,).

    Args:
        q: (6,) joints, rad and m.
        kinematics: The PSM and tool (default: the simulator's, :data:`SIMULATOR_PSM`).

    Returns:
        Seven 4×4 transforms ``T_base_link``: outer yaw, outer pitch, insertion, roll (its
        origin is the shaft's distal end, at the wrist pitch axis), wrist pitch, wrist yaw
        (jaw pivot) and the tool tip (control point between the jaws).
    """
    if kinematics is not None and kinematics is not SIMULATOR_PSM:
        return kinematics.link_frames(q)
    q = np.asarray(q, dtype=np.float64)
    rows = (
        (np.pi / 2, 0.0, q[0] + np.pi / 2, 0.0),
        (-np.pi / 2, 0.0, q[1] - np.pi / 2, 0.0),
        (np.pi / 2, 0.0, 0.0, q[2] - L_RCC),
        (0.0, 0.0, q[3], L_TOOL),
        (-np.pi / 2, 0.0, q[4] - np.pi / 2, 0.0),
        (-np.pi / 2, L_PITCH2YAW, q[5] - np.pi / 2, 0.0),
        (-np.pi / 2, 0.0, np.pi / 2, L_YAW2CTRLPNT),
    )
    frames = []
    T = np.eye(4)
    for row in rows:
        T = T @ mdh(*row)
        frames.append(T)
    return frames


def psm_tip_pose(q: ArrayLike, kinematics: PsmKinematics | None = None) -> F64:
    """Tool-tip frame ``T_base_tip`` (z along the jaws, pointing away from the wrist)."""
    return psm_link_frames(q, kinematics)[-1]


def look_rotation(forward: ArrayLike, up_hint: ArrayLike = (0.0, 0.0, 1.0)) -> F64:
    """Rotation whose z axis is ``forward`` and whose −y axis leans towards ``up_hint``."""
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z)
    up = np.asarray(up_hint, dtype=np.float64)
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-9:  # forward parallel to up: any perpendicular x
        x = np.cross([1.0, 0.0, 0.0], z) if abs(z[0]) < 0.9 else np.cross([0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def pose(R: ArrayLike, t: ArrayLike) -> F64:
    """4×4 transform from a rotation (3, 3) and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def rot_x(a: float) -> F64:
    """Rotation about x by ``a`` rad."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> F64:
    """Rotation about y by ``a`` rad."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> F64:
    """Rotation about z by ``a`` rad."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class SceneLayout:
    """Where the robots stand relative to the tissue (world frame, m), and which robots.

    Attributes:
        psm_rcm: RCM position of each PSM, in ``arms`` order.
        workspace_centre: The point the PSM shafts aim at (on the tissue); the endoscope's
            too unless ``view_target`` is set.
        ecm_frame_origin: Origin of the ECM camera frame (the camera sits
            :data:`ECM_CAMERA_OFFSET` in front of it).
        arms: The PSMs in the scene (``psm1``, ``psm2``, ``psm3``); others are not rendered.
        kinematics: The PSMs' kinematics and tool (:data:`SIMULATOR_PSM`, or a dVRK tool of
            :mod:`~bopsurg.generators.dvrk_tools`).
        view_target: The point the endoscope looks at when it is not ``workspace_centre``
            (a real recording's tool-tip workspace), or None.
    """

    psm_rcm: tuple[tuple[float, float, float], ...] = ((0.075, -0.02, 0.10), (-0.075, -0.02, 0.10))
    workspace_centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ecm_frame_origin: tuple[float, float, float] = (0.0, -0.07, 0.085)
    arms: tuple[str, ...] = ("psm1", "psm2")
    kinematics: PsmKinematics = SIMULATOR_PSM
    view_target: tuple[float, float, float] | None = None

    def psm_base(self, index: int) -> F64:
        """``T_world_base`` of PSM ``index`` (into ``arms``): base −Z points at the workspace
        centre."""
        rcm = np.asarray(self.psm_rcm[index])
        down = np.asarray(self.workspace_centre) - rcm
        R = look_rotation(-down, up_hint=(0.0, -1.0, 0.0))
        return pose(R, rcm)

    def arm_base(self, arm: str) -> F64:
        """``T_world_base`` of the arm named ``arm``.

        Raises:
            ValueError: The arm is not in the layout.
        """
        if arm not in self.arms:
            raise ValueError(f"unknown arm {arm!r}; expected one of {self.arms}")
        return self.psm_base(self.arms.index(arm))

    def ecm_base(self) -> F64:
        """``T_world_ecmframe`` at zero ECM joints: looking at the view target (default: the
        workspace centre)."""
        origin = np.asarray(self.ecm_frame_origin)
        target = self.workspace_centre if self.view_target is None else self.view_target
        forward = np.asarray(target) - origin
        return pose(look_rotation(forward), origin)


DEFAULT_LAYOUT = SceneLayout()


def ecm_camera_pose(
    joints: ArrayLike, layout: SceneLayout = DEFAULT_LAYOUT, *, right: bool = False
) -> F64:
    """``T_world_cam`` of the endoscope's left (or right) camera, OpenCV axes.

    Args:
        joints: (4,) yaw, pitch (rad), insertion (m), roll (rad).
        layout: Scene layout.
        right: The right camera of the stereo pair (baseline :data:`STEREO_BASELINE`).
    """
    j = np.asarray(joints, dtype=np.float64)
    # yaw about the camera's up axis (−y), pitch about x, insertion along z, roll about z
    motion = pose(rot_y(-j[0]) @ rot_x(-j[1]), [0.0, 0.0, 0.0])
    motion = motion @ pose(rot_z(j[3]), [0.0, 0.0, j[2]])
    cam = pose(np.eye(3), [STEREO_BASELINE if right else 0.0, 0.0, ECM_CAMERA_OFFSET])
    return layout.ecm_base() @ motion @ cam


def in_limits(q: ArrayLike, limits: NDArray[np.float64], tol: float = 1e-9) -> NDArray[np.bool_]:
    """Per-joint check of ``q`` (..., J) against ``limits`` (J, 2)."""
    a = np.asarray(q, dtype=np.float64)
    return (a >= limits[:, 0] - tol) & (a <= limits[:, 1] + tol)
