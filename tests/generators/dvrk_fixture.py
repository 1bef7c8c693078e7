"""Bags laid out like a real dVRK's recordings, written with the rosbags writers.

A real dVRK (sawIntuitiveResearchKit 2.x, ROS1 or ROS2) records, per arm that moved:
``/PSM2/measured_js`` and ``/PSM2/setpoint_js`` (sensor_msgs/JointState, joint names
``outer_yaw ... outer_wrist_yaw``), ``/PSM2/measured_cp`` and ``/PSM2/setpoint_cp``
(geometry_msgs/PoseStamped, frame ``ECM``) and ``/PSM2/measured_cv`` (TwistStamped); no jaw,
no ECM, no needle, no bopsurg meta. The Cartesian poses here are the dVRK kinematics of the
given tool applied to known joints, seen through a known registration ``T_ecm_base``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from bopsurg.generators.dvrk_tools import dvrk_psm
from bopsurg.generators.kinematics import PSM_JOINT_NAMES

T0_NS = 1_650_000_000 * 10**9


def known_registration() -> np.ndarray:
    """``T_ecm_base`` (4, 4), m: PSM2's RCM beside and ahead of the endoscope's tip."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [0.9, -0.4, 2.6]).as_matrix()
    T[:3, 3] = [0.09, -0.05, 0.03]
    return T


def dvrk_joints(times: np.ndarray, seed: int = 0) -> np.ndarray:
    """(T, 6) joints of a pitch-excitation run: the outer pitch sweeps, the rest drift."""
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0.0, 2 * np.pi, 6)
    q0 = np.array([0.05, -0.1, 0.14, 0.2, 0.1, -0.1])
    amp = np.array([0.10, 0.20, 0.012, 0.5, 0.3, 0.3])
    freq = np.array([0.07, 0.23, 0.11, 0.05, 0.17, 0.13])
    return q0 + amp * np.sin(2 * np.pi * freq * times[:, None] + phase)


def write_dvrk_bag(
    path: Path,
    fmt: str = "ros1",
    *,
    arms: tuple[str, ...] = ("psm2",),
    duration: float = 2.0,
    rate_hz: float = 100.0,
    tool: str = "LARGE_NEEDLE_DRIVER_400006",
    T_ecm_base: np.ndarray | None = None,
    cp_noise_m: float = 0.0,
    jaw: bool = False,
    seed: int = 0,
    joints: np.ndarray | None = None,
    cartesian_only: tuple[str, ...] = (),
) -> dict[str, np.ndarray]:
    """Write the bag (``fmt``: ros1, ros2 or mcap); returns each arm's joints (T, 6).

    ``joints`` (T, 6) replaces the synthetic motion of every arm (and sets T); the arms of
    ``cartesian_only`` get their Cartesian topics only.
    """
    T_reg = known_registration() if T_ecm_base is None else T_ecm_base
    ros2 = fmt != "ros1"
    ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    n = round(duration * rate_hz) + 1 if joints is None else len(joints)
    times = np.arange(n) / rate_hz
    stamps = T0_NS + np.rint(times * 1e9).astype(np.int64)
    kin = dvrk_psm(tool)
    rng = np.random.default_rng(seed + 100)
    messages: list[tuple[str, str, int, object]] = []
    written = {}
    for k, arm in enumerate(arms):
        A = arm.upper()
        q = dvrk_joints(times, seed + k) if joints is None else np.asarray(joints, np.float64)
        written[arm] = q
        cp = T_reg @ kin.tip_poses(q)
        cp[:, :3, 3] += cp_noise_m * rng.standard_normal((n, 3))
        setpoint = np.concatenate([q[:1], q[:-1]])  # the controller's command, one tick ahead
        sp_cp = T_reg @ kin.tip_poses(setpoint)
        for i, t in enumerate(stamps):
            t = int(t)
            if arm not in cartesian_only:
                messages.append((f"/{A}/measured_js", _JS, t, _joint_state(ts, ros2, t, q[i])))
                js = _joint_state(ts, ros2, t, setpoint[i])
                messages.append((f"/{A}/setpoint_js", _JS, t, js))
            messages.append((f"/{A}/measured_cp", _PS, t, _pose(ts, ros2, t, cp[i])))
            messages.append((f"/{A}/setpoint_cp", _PS, t, _pose(ts, ros2, t, sp_cp[i])))
            messages.append((f"/{A}/measured_cv", _TW, t, _twist(ts, ros2, t)))
            if jaw:
                messages.append((f"/{A}/jaw/measured_js", _JS, t, _jaw(ts, ros2, t, 0.4)))
    _write(path, fmt, ts, messages)
    return written


_JS, _PS, _TW = (
    "sensor_msgs/msg/JointState",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/TwistStamped",
)


def _header(ts, ros2: bool, t_ns: int, frame: str):
    T = ts.types
    stamp = T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
    if ros2:
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)
    return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)


def _joint_state(ts, ros2: bool, t_ns: int, q: np.ndarray):
    return ts.types[_JS](
        header=_header(ts, ros2, t_ns, ""),
        name=list(PSM_JOINT_NAMES),
        position=np.asarray(q, dtype=np.float64),
        velocity=np.zeros(len(q)),
        effort=np.zeros(len(q)),
    )


def _jaw(ts, ros2: bool, t_ns: int, value: float):
    return ts.types[_JS](
        header=_header(ts, ros2, t_ns, ""),
        name=["jaw"],
        position=np.array([value]),
        velocity=np.zeros(1),
        effort=np.zeros(1),
    )


def _pose(ts, ros2: bool, t_ns: int, T: np.ndarray):
    types = ts.types
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )
    return types[_PS](header=_header(ts, ros2, t_ns, "ECM"), pose=pose)


def _twist(ts, ros2: bool, t_ns: int):
    types = ts.types
    v = types["geometry_msgs/msg/Vector3"]
    twist = types["geometry_msgs/msg/Twist"](
        linear=v(x=0.0, y=0.0, z=0.0), angular=v(x=0.0, y=0.0, z=0.0)
    )
    return types[_TW](header=_header(ts, ros2, t_ns, "ECM"), twist=twist)


def _write(path: Path, fmt: str, ts, messages: list[tuple[str, str, int, object]]) -> None:
    if fmt == "ros1":
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        topics = dict.fromkeys((m[0], m[1]) for m in messages)
        conns = {t: writer.add_connection(t, m, typestore=ts) for t, m in topics}
        ser = ts.serialize_ros1 if fmt == "ros1" else ts.serialize_cdr
        for topic, msgtype, t_ns, msg in sorted(messages, key=lambda m: m[2]):
            writer.write(conns[topic], t_ns, ser(msg, msgtype))
