"""dVRK PSM and ECM forward kinematics, and the scene layout they live in.

Units: metres and radians (ROS / CRTK SI), 4×4 homogeneous transforms ``T_a_b`` mapping
coordinates in frame ``b`` to frame ``a``. The world frame has +Z up; the tissue phantom's
top surface is the plane z = 0 around the origin.

PSM: modified Denavit–Hartenberg parameters of the Large Needle Driver (tool 400006) from
surgical_robotics_challenge ``kinematics/psmFK.py`` (see ``surgical_scene_facts.md`` §2.3).
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

# Lengths of the Large Needle Driver 400006, m.
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


def psm_link_frames(q: ArrayLike) -> list[F64]:
    """Frames of the PSM links in the base (RCM) frame for joints ``q`` (6,).

    Returns:
        Seven 4×4 transforms ``T_base_link``: outer yaw, outer pitch, insertion, roll (its
        origin is the shaft's distal end, at the wrist pitch axis), wrist pitch, wrist yaw
        (jaw pivot) and the tool tip (control point between the jaws).
    """
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


def psm_tip_pose(q: ArrayLike) -> F64:
    """Tool-tip frame ``T_base_tip`` (z along the jaws, pointing away from the wrist)."""
    return psm_link_frames(q)[-1]


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
    """Where the robots stand relative to the tissue (world frame, m).

    Attributes:
        psm_rcm: RCM position of each PSM.
        workspace_centre: The point the PSM shafts and the endoscope aim at (on the tissue).
        ecm_frame_origin: Origin of the ECM camera frame (the camera sits
            :data:`ECM_CAMERA_OFFSET` in front of it).
    """

    psm_rcm: tuple[tuple[float, float, float], ...] = ((0.075, -0.02, 0.10), (-0.075, -0.02, 0.10))
    workspace_centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ecm_frame_origin: tuple[float, float, float] = (0.0, -0.07, 0.085)

    def psm_base(self, index: int) -> F64:
        """``T_world_base`` of PSM ``index`` (0 = psm1): base −Z points at the workspace centre."""
        rcm = np.asarray(self.psm_rcm[index])
        down = np.asarray(self.workspace_centre) - rcm
        R = look_rotation(-down, up_hint=(0.0, -1.0, 0.0))
        return pose(R, rcm)

    def ecm_base(self) -> F64:
        """``T_world_ecmframe`` at zero ECM joints: looking at the workspace centre."""
        origin = np.asarray(self.ecm_frame_origin)
        forward = np.asarray(self.workspace_centre) - origin
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
