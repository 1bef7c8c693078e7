"""Recordings and rosbags: round trips, topic maps, custom messages, bad bags, the CLI."""

from __future__ import annotations

import argparse
import contextlib
import os
import sqlite3
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")  # bopsurg[sim]: the bag writer these tests record with

from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from bopsurg.errors import InputError
from bopsurg.generators import cli_record
from bopsurg.generators.backend import DEFAULT_ECM_JOINTS, DEFAULT_NEEDLE_POSE, PARKED_PSM_JOINTS
from bopsurg.generators.bags import (
    DEFAULT_TIME_ORIGIN_NS,
    TOPIC_MAP_DIR,
    BagError,
    Recording,
    load_topic_map,
    read_bag,
    write_bag,
)
from bopsurg.generators.trajectory import synthesize_suturing

T0 = DEFAULT_TIME_ORIGIN_NS


@pytest.fixture(scope="module")
def rec() -> Recording:
    return synthesize_suturing(4, duration=3.0, rate_hz=20.0)


def _bag_name(fmt: str) -> str:
    return "episode.bag" if fmt == "ros1" else "episode"


def _assert_same(a: Recording, b: Recording) -> None:
    assert sorted(a.psm_joints) == sorted(b.psm_joints)
    for arm in a.psm_joints:
        np.testing.assert_array_equal(a.psm_joints[arm][0], b.psm_joints[arm][0])
        np.testing.assert_array_equal(a.psm_joints[arm][1], b.psm_joints[arm][1])
        np.testing.assert_array_equal(a.jaws[arm][0], b.jaws[arm][0])
        np.testing.assert_array_equal(a.jaws[arm][1], b.jaws[arm][1])
    np.testing.assert_array_equal(a.ecm_joints[0], b.ecm_joints[0])
    np.testing.assert_array_equal(a.ecm_joints[1], b.ecm_joints[1])
    np.testing.assert_array_equal(a.needle_pose[0], b.needle_pose[0])
    # via a quaternion: equal to rounding
    np.testing.assert_allclose(a.needle_pose[1], b.needle_pose[1], rtol=0, atol=1e-14)


def _one_line(err: pytest.ExceptionInfo, *parts: str) -> str:
    text = str(err.value)
    assert "\n" not in text
    for part in parts:
        assert part in text, text
    return text


# ----------------------------------------------------------------- raw bags for the tests


class _Raw:
    """Writes bags message by message, the way other recorders would."""

    def __init__(self, path: Path, *, ros2: bool = False, msg_types: dict | None = None) -> None:
        self.path, self.ros2 = path, ros2
        self.ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
        for name, text in (msg_types or {}).items():
            self.ts.register(get_types_from_msg(text, name))
        self.T = self.ts.types
        self.messages: list[tuple[str, str, int, object]] = []
        self.empty: list[tuple[str, str]] = []

    def header(self, stamp_ns: int, frame: str = "") -> object:
        stamp = self.T["builtin_interfaces/msg/Time"](
            sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9
        )
        if self.ros2:
            return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)
        return self.T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)

    def joint_state(self, topic: str, t_ns: int, position, stamp_ns: int | None = None) -> None:
        msg = self.T["sensor_msgs/msg/JointState"](
            header=self.header(t_ns if stamp_ns is None else stamp_ns),
            name=[f"j{i}" for i in range(len(position))],
            position=np.asarray(position, dtype=np.float64),
            velocity=np.zeros(0),
            effort=np.zeros(0),
        )
        self.add(topic, "sensor_msgs/msg/JointState", t_ns, msg)

    def float64_array(self, topic: str, t_ns: int, data) -> None:
        layout = self.T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
        msg = self.T["std_msgs/msg/Float64MultiArray"](layout=layout, data=np.asarray(data, float))
        self.add(topic, "std_msgs/msg/Float64MultiArray", t_ns, msg)

    def geometry_pose(self, T: np.ndarray) -> object:
        qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
        return self.T["geometry_msgs/msg/Pose"](
            position=self.T["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            orientation=self.T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )

    def pose_stamped(self, topic: str, t_ns: int, T: np.ndarray) -> None:
        msg = self.T["geometry_msgs/msg/PoseStamped"](
            header=self.header(t_ns, "world"), pose=self.geometry_pose(T)
        )
        self.add(topic, "geometry_msgs/msg/PoseStamped", t_ns, msg)

    def add(self, topic: str, msgtype: str, t_ns: int, msg: object) -> None:
        self.messages.append((topic, msgtype, t_ns, msg))

    def write(self, *, definitions: bool = True) -> Path:
        topics = dict.fromkeys([(m[0], m[1]) for m in self.messages] + self.empty)
        if self.ros2:
            writer = Writer2(self.path, version=9, storage_plugin=StoragePlugin.SQLITE3)
        else:
            writer = Writer1(self.path)
        with writer:
            conns = {t: writer.add_connection(t, m, typestore=self.ts) for t, m in topics}
            for topic, msgtype, t_ns, msg in sorted(self.messages, key=lambda m: m[2]):
                ser = self.ts.serialize_cdr if self.ros2 else self.ts.serialize_ros1
                writer.write(conns[topic], t_ns, ser(msg, msgtype))
        if not definitions:  # like bags recorded before ROS2 Iron: no message definitions
            assert self.ros2
            with contextlib.closing(sqlite3.connect(self.path / f"{self.path.name}.db3")) as db:
                db.execute("DELETE FROM message_definitions")
                db.commit()
        return self.path


def _joints(i: int) -> np.ndarray:
    return np.array([0.1, -0.2, 0.12, 0.3, 0.2, -0.1]) + 0.01 * i


def _needle(i: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.1 * i]).as_matrix()
    T[:3, 3] = [0.001 * i, 0.002, 0.003]
    return T


# ----------------------------------------------------------------- round trips


@pytest.mark.parametrize("fmt", ["ros1", "ros2", "mcap"])
def test_round_trip(rec, tmp_path, fmt):
    path = tmp_path / _bag_name(fmt)
    counts = write_bag(path, rec, format=fmt)
    n = len(rec.psm_joints["psm1"][0])
    assert counts == {
        "/bopsurg/meta": 1,
        "/psm1/measured_js": n,
        "/psm2/measured_js": n,
        "/psm1/jaw/measured_js": n,
        "/psm2/jaw/measured_js": n,
        "/ecm/measured_js": n,
        "/needle/measured_cp": n,
    }
    back = read_bag(path)
    _assert_same(rec, back)
    assert back.meta["seed"] == 4
    assert back.meta["time_origin_ns"] == T0
    assert back.meta["needle"] == rec.meta["needle"]
    assert back.source == str(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporaries left
    if fmt != "ros1":
        suffix = ".mcap" if fmt == "mcap" else ".db3"
        assert (path / f"episode{suffix}").is_file()
        assert read_bag(path / f"episode{suffix}").meta["seed"] == 4  # the file inside works


def test_write_refuses_to_overwrite_unless_asked(rec, tmp_path):
    path = tmp_path / "ep"
    write_bag(path, rec, format="ros2")
    with pytest.raises(BagError, match="overwrite") as err:
        write_bag(path, rec, format="ros2")
    _one_line(err, str(path))
    other = synthesize_suturing(9, duration=1.0, rate_hz=10.0)
    write_bag(path, other, format="mcap", overwrite=True)
    assert read_bag(path).meta["seed"] == 9
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ep"]


def test_ros1_bag_needs_the_bag_suffix(rec, tmp_path):
    with pytest.raises(BagError, match=r"\.bag"):
        write_bag(tmp_path / "episode.ros1", rec, format="ros1")
    with pytest.raises(BagError, match="unknown bag format"):
        write_bag(tmp_path / "x.bag", rec, format="ros3")  # type: ignore[arg-type]


def test_write_rejects_malformed_recordings(tmp_path):
    t = np.array([0.0, 0.2, 0.1])
    bad = Recording(psm_joints={"psm1": (t, np.zeros((3, 6)))})
    with pytest.raises(BagError, match=r"psm_joints\[psm1\].*increasing"):
        write_bag(tmp_path / "x.bag", bad)
    bad = Recording(jaws={"psm1": (np.arange(3.0), np.array([0.1, np.nan, 0.1]))})
    with pytest.raises(BagError, match="non-finite"):
        write_bag(tmp_path / "x.bag", bad)
    bad = Recording(ecm_joints=(np.arange(3.0), np.zeros((3, 3))))
    with pytest.raises(BagError, match="expected"):
        write_bag(tmp_path / "x.bag", bad)
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------- topic maps


def test_ambf_map_reads_the_paper_setpoint_topics(tmp_path):
    raw = _Raw(tmp_path / "teleop.bag")
    t0 = 1_600_000_000 * 10**9
    for i in range(5):
        t = t0 + i * 5_000_000  # 200 Hz, no headers: the bag time is the stamp
        raw.float64_array("/psm1/setpoint_js", t, _joints(i))
        raw.float64_array("/psm2/setpoint_js", t, -_joints(i) * [1, 1, -1, 1, 1, 1])
        raw.add(
            "/psm1/jaw/setpoint_js",
            "std_msgs/msg/Float64",
            t,
            raw.T["std_msgs/msg/Float64"](data=0.5 - 0.1 * i),
        )
        raw.float64_array("/ecm/setpoint_js", t, [0.0, 0.05, -0.01, 0.0])
        raw.pose_stamped("/CRTK/Needle/measured_cp", t, _needle(i))
    rec = read_bag(raw.write(), topic_map="ambf")
    times = np.arange(5) * 0.005
    np.testing.assert_allclose(rec.psm_joints["psm1"][0], times, atol=1e-12)
    np.testing.assert_allclose(rec.psm_joints["psm1"][1], np.stack([_joints(i) for i in range(5)]))
    np.testing.assert_allclose(rec.jaws["psm1"][1], 0.5 - 0.1 * np.arange(5))
    assert "psm2" not in rec.jaws
    np.testing.assert_allclose(rec.ecm_joints[1][0], [0.0, 0.05, -0.01, 0.0])
    np.testing.assert_allclose(rec.needle_pose[1][3], _needle(3), atol=1e-12)
    assert rec.meta["time_origin_ns"] == t0
    state = rec.state_at(0.01)
    np.testing.assert_allclose(state.psm_joints["psm1"], _joints(2))
    assert state.jaws["psm2"] == 0.0  # parked default


def test_ambf_map_scales_body_states_from_sim_units(tmp_path):
    msg = (TOPIC_MAP_DIR.parent / "msg" / "RigidBodyState.msg").read_text()
    raw = _Raw(tmp_path / "ambf.bag", msg_types={"ambf_msgs/msg/RigidBodyState": msg})
    T = raw.T
    for i in range(4):
        t = T0 + i * 10_000_000
        q = _joints(i)
        jp = np.array([*q[:2], q[2] * 10.0, *q[3:], -0.4, -0.4], dtype=np.float32)  # sim units
        zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        pose_sim = _needle(i)
        pose_sim[:3, 3] *= 10.0
        state = T["ambf_msgs/msg/RigidBodyState"](
            header=raw.header(t),
            sim_step=i,
            identifier=T["std_msgs/msg/String"](data="psm1"),
            name=T["std_msgs/msg/String"](data="baselink"),
            wall_time=0.0,
            sim_time=0.0,
            mass=1.0,
            pInertia=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
            pose=raw.geometry_pose(pose_sim),
            twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
            wrench=T["geometry_msgs/msg/Wrench"](force=zero, torque=zero),
            children_names=[],
            joint_names=[f"j{k}" for k in range(8)],
            joint_positions=jp,
            joint_velocities=np.zeros(8, dtype=np.float32),
            joint_efforts=np.zeros(8, dtype=np.float32),
        )
        raw.add("/ambf/env/psm1/baselink/State", "ambf_msgs/msg/RigidBodyState", t, state)
        raw.add("/ambf/env/Needle/State", "ambf_msgs/msg/RigidBodyState", t, state)
    rec = read_bag(raw.write(), topic_map="ambf")
    expected = np.stack([_joints(i) for i in range(4)])
    np.testing.assert_allclose(rec.psm_joints["psm1"][1], expected, atol=1e-6)  # float32
    np.testing.assert_allclose(rec.jaws["psm1"][1], 0.4, atol=1e-6)
    np.testing.assert_allclose(rec.needle_pose[1][2], _needle(2), atol=1e-7)


def test_write_and_read_with_the_ambf_map(rec, tmp_path):
    path = tmp_path / "ambf"
    counts = write_bag(path, rec, format="mcap", topic_map="ambf")
    assert "/CRTK/psm1/measured_js" in counts
    assert "/psm1/jaw/setpoint_js" in counts  # std_msgs/Float64
    assert "/CRTK/Needle/measured_cp" in counts
    back = read_bag(path, topic_map=TOPIC_MAP_DIR / "ambf.toml")
    _assert_same(rec, back)


def test_crtk_map_accepts_capitalised_topics(tmp_path):
    raw = _Raw(tmp_path / "dvrk.bag")
    for i in range(3):
        raw.joint_state("/PSM1/measured_js", T0 + i * 10**8, _joints(i))
        raw.joint_state("/PSM1/jaw/measured_js", T0 + i * 10**8, [0.3])
    rec = read_bag(raw.write())
    np.testing.assert_allclose(rec.psm_joints["psm1"][1][2], _joints(2))
    np.testing.assert_allclose(rec.psm_joints["psm1"][0], [0.0, 0.1, 0.2])
    assert rec.needle_pose is None
    np.testing.assert_array_equal(rec.state_at(0.0).needle_pose, DEFAULT_NEEDLE_POSE)


CUSTOM_MSG = "std_msgs/Header header\nstring tool\nfloat64[] q\nfloat64 jaw_angle\n"


def _custom_map(tmp_path: Path) -> Path:
    (tmp_path / "msgs").mkdir()
    (tmp_path / "msgs" / "ArmState.msg").write_text(CUSTOM_MSG)
    path = tmp_path / "mylab.toml"
    path.write_text(
        'name = "mylab"\n[types]\n"mylab_msgs/ArmState" = "msgs/ArmState.msg"\n'
        '[[source]]\nstream = "psm_joints"\narm = "psm1"\ntopic = "/arm1/state"\n'
        'type = "mylab_msgs/ArmState"\nfield = "q"\nrequired = true\n'
        '[[source]]\nstream = "jaw"\narm = "psm1"\ntopic = "/arm1/state"\n'
        'type = "mylab_msgs/msg/ArmState"\nfield = "jaw_angle"\n'
    )
    return path


@pytest.mark.parametrize("definitions", [True, False], ids=["embedded", "from-map"])
def test_custom_message_type_from_msg_file(tmp_path, definitions):
    tmap = _custom_map(tmp_path)
    raw = _Raw(tmp_path / "lab", ros2=True, msg_types={"mylab_msgs/msg/ArmState": CUSTOM_MSG})
    for i in range(4):
        msg = raw.T["mylab_msgs/msg/ArmState"](
            header=raw.header(T0 + i * 10**7), tool="LND", q=_joints(i), jaw_angle=0.1 * i
        )
        raw.add("/arm1/state", "mylab_msgs/msg/ArmState", T0 + i * 10**7, msg)
    rec = read_bag(raw.write(definitions=definitions), topic_map=tmap)
    np.testing.assert_allclose(rec.psm_joints["psm1"][1][3], _joints(3))
    np.testing.assert_allclose(rec.jaws["psm1"][1], 0.1 * np.arange(4))


def test_topic_map_errors(tmp_path):
    with pytest.raises(BagError, match="built-in maps: ambf, crtk"):
        load_topic_map("nope")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [\n")
    with pytest.raises(BagError, match="invalid TOML") as err:
        load_topic_map(bad)
    _one_line(err, str(bad))
    bad.write_text('[[source]]\nstream = "psm_joints"\ntopic = "/a"\ntype = "x/Y"\nfield = "q"\n')
    with pytest.raises(BagError, match=r"source\[0\].*needs 'arm'"):
        load_topic_map(bad)
    bad.write_text('[[source]]\nstream = "joints"\ntopic = "/a"\ntype = "x/Y"\nfield = "q"\n')
    with pytest.raises(BagError, match="unknown stream"):
        load_topic_map(bad)
    bad.write_text('[types]\n"a/B" = "missing.msg"\n[[source]]\nstream = "meta"\n')
    with pytest.raises(BagError, match="not found"):
        load_topic_map(bad)


# ----------------------------------------------------------------- bad bags


def test_missing_bag(tmp_path):
    with pytest.raises(BagError, match="no such bag") as err:
        read_bag(tmp_path / "nothing.bag")
    _one_line(err, "nothing.bag")


@pytest.mark.parametrize("fmt", ["ros1", "ros2", "mcap"])
def test_truncated_bag_is_one_line_error(rec, tmp_path, fmt):
    path = tmp_path / _bag_name(fmt)
    write_bag(path, rec, format=fmt)
    file = path if fmt == "ros1" else next(p for p in path.iterdir() if p.suffix != ".yaml")
    data = file.read_bytes()
    file.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="cannot read bag") as err:
        read_bag(path)
    _one_line(err, str(path))
    assert isinstance(err.value, InputError)


def test_garbage_file_is_one_line_error(tmp_path):
    path = tmp_path / "junk.bag"
    path.write_bytes(os.urandom(2000))
    with pytest.raises(BagError, match="cannot read bag") as err:
        read_bag(path)
    _one_line(err, "junk.bag")


def test_required_topic_missing(tmp_path):
    raw = _Raw(tmp_path / "ecm_only.bag")
    raw.joint_state("/ecm/measured_js", T0, [0.0, 0.0, 0.0, 0.0])
    with pytest.raises(BagError, match="required topic missing") as err:
        read_bag(raw.write())
    _one_line(err, "ecm_only.bag", "/psm1/measured_js or /PSM1/measured_js", "/ecm/measured_js")


def test_message_type_not_the_maps(tmp_path):
    raw = _Raw(tmp_path / "wrong.bag")
    raw.add("/psm1/measured_js", "std_msgs/msg/String", T0, raw.T["std_msgs/msg/String"](data="x"))
    with pytest.raises(BagError, match="message type std_msgs/msg/String") as err:
        read_bag(raw.write())
    _one_line(err, "wrong.bag", "/psm1/measured_js", "sensor_msgs/msg/JointState")


def test_unknown_message_type_without_definitions(tmp_path):
    raw = _Raw(tmp_path / "lab", ros2=True, msg_types={"mylab_msgs/msg/ArmState": CUSTOM_MSG})
    msg = raw.T["mylab_msgs/msg/ArmState"](
        header=raw.header(T0), tool="", q=_joints(0), jaw_angle=0
    )
    raw.add("/arm1/state", "mylab_msgs/msg/ArmState", T0, msg)
    raw.write(definitions=False)
    tmap = _custom_map(tmp_path)
    tmap.write_text(
        tmap.read_text().replace('[types]\n"mylab_msgs/ArmState" = "msgs/ArmState.msg"', "")
    )
    with pytest.raises(BagError, match="mylab_msgs/msg/ArmState") as err:
        read_bag(tmp_path / "lab", topic_map=tmap)
    _one_line(err, str(tmp_path / "lab"))


def test_non_monotonic_stamps(tmp_path):
    raw = _Raw(tmp_path / "stamps.bag")
    stamps = [0, 1, 2, 1, 4]  # header stamps step back at message 3
    for i, s in enumerate(stamps):
        raw.joint_state("/psm1/measured_js", T0 + i * 10**8, _joints(i), stamp_ns=T0 + s * 10**8)
    with pytest.raises(BagError, match="stamps not increasing at message 3") as err:
        read_bag(raw.write())
    _one_line(err, "stamps.bag", "/psm1/measured_js")


def test_joint_outside_limits(tmp_path):
    t = np.arange(4) * 0.25
    q = np.tile(_joints(0), (4, 1))
    q[2, 1] = 1.2  # outer pitch beyond 0.925 rad at t = 0.5 s
    path = tmp_path / "limits.bag"
    write_bag(path, Recording(psm_joints={"psm1": (t, q)}))
    with pytest.raises(BagError, match=r"outer_pitch = 1\.2 outside") as err:
        read_bag(path)
    _one_line(err, "limits.bag", "/psm1/measured_js", "t = 0.500 s")
    assert read_bag(path, check_limits=False).psm_joints["psm1"][1][2, 1] == 1.2


def test_nan_values(tmp_path):
    raw = _Raw(tmp_path / "nan.bag")
    for i in range(3):
        q = _joints(i)
        if i == 1:
            q[4] = np.nan
        raw.joint_state("/psm1/measured_js", T0 + i * 10**8, q)
    with pytest.raises(BagError, match="NaN or infinite value in message 1") as err:
        read_bag(raw.write())
    _one_line(err, "nan.bag", "/psm1/measured_js")


def test_empty_topic(tmp_path):
    raw = _Raw(tmp_path / "empty", ros2=True)
    raw.joint_state("/psm1/measured_js", T0, _joints(0))
    raw.empty.append(("/needle/measured_cp", "geometry_msgs/msg/PoseStamped"))
    with pytest.raises(BagError, match="no messages") as err:
        read_bag(raw.write())
    _one_line(err, "empty", "/needle/measured_cp")


def test_wrong_number_of_joints(tmp_path):
    raw = _Raw(tmp_path / "five.bag")
    raw.joint_state("/psm1/measured_js", T0, _joints(0)[:5])
    with pytest.raises(BagError, match="expected 6 values"):
        read_bag(raw.write())


# ----------------------------------------------------------------- state_at


def test_state_at_interpolates_and_clamps():
    t = np.array([0.0, 1.0, 3.0])
    q = np.stack([np.zeros(6), np.full(6, 0.1), np.full(6, 0.3)])
    q[:, 2] = [0.10, 0.12, 0.16]
    poses = np.stack([np.eye(4)] * 3)
    poses[1, :3, :3] = Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_matrix()
    poses[1, :3, 3] = [0.02, 0.0, 0.0]
    poses[2] = poses[1]
    rec = Recording(
        psm_joints={"psm1": (t, q)},
        jaws={"psm1": (t, np.array([0.8, 0.0, 0.4]))},
        needle_pose=(t, poses),
    )
    s = rec.state_at(2.0)
    np.testing.assert_allclose(s.psm_joints["psm1"], [0.2, 0.2, 0.14, 0.2, 0.2, 0.2])
    assert s.jaws["psm1"] == pytest.approx(0.2)
    s = rec.state_at(0.5)
    assert s.jaws["psm1"] == pytest.approx(0.4)
    expected = Rotation.from_rotvec([0.0, 0.0, np.pi / 4]).as_matrix()
    np.testing.assert_allclose(s.needle_pose[:3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(s.needle_pose[:3, 3], [0.01, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(rec.state_at(-5.0).psm_joints["psm1"], q[0])
    np.testing.assert_allclose(rec.state_at(9.0).psm_joints["psm1"], q[2])
    np.testing.assert_allclose(rec.state_at(9.0).needle_pose, poses[2])
    # streams the recording lacks: documented defaults
    s = rec.state_at(1.0)
    np.testing.assert_array_equal(s.psm_joints["psm2"], PARKED_PSM_JOINTS)
    assert s.jaws["psm2"] == 0.0
    np.testing.assert_array_equal(s.ecm_joints, DEFAULT_ECM_JOINTS)
    assert (rec.start, rec.end, rec.duration) == (0.0, 3.0, 3.0)
    single = Recording(ecm_joints=(np.array([2.0]), np.ones((1, 4))))
    np.testing.assert_array_equal(single.state_at(0.0).ecm_joints, np.ones(4))
    assert single.duration == 0.0
    assert Recording().duration == 0.0


# ----------------------------------------------------------------- the record command


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bopsurg")
    cli_record.register(parser.add_subparsers(dest="command", required=True))
    return parser


def test_record_command_writes_a_bag(tmp_path, capsys):
    out = tmp_path / "ep.bag"
    args = _parser().parse_args(
        ["record", "--out", str(out), "--seed", "3", "--duration", "2", "--rate", "20"]
    )
    assert args.func(args) == 0
    text = capsys.readouterr().out
    assert "/psm1/measured_js" in text
    assert "41" in text  # messages per topic: 2 s at 20 Hz, both ends
    back = read_bag(out)
    assert back.meta["seed"] == 3
    assert back.duration == pytest.approx(2.0)
    with pytest.raises(InputError, match="overwrite"):
        cli_record.run(args)
    args = _parser().parse_args(
        [
            "record",
            "--out",
            str(tmp_path / "ep2"),
            "--seed",
            "3",
            "--duration",
            "1",
            "--format",
            "mcap",
            "--overwrite",
        ]
    )
    assert cli_record.run(args) == 0
    assert (tmp_path / "ep2" / "metadata.yaml").is_file()


def test_record_help_teaches(capsys):
    with pytest.raises(SystemExit):
        _parser().parse_args(["record", "--help"])
    text = capsys.readouterr().out
    for word in ("/psm1/measured_js", "/needle/measured_cp", "/bopsurg/meta", "--seed", "tremor"):
        assert word in text


def test_record_rejects_bad_arguments(tmp_path):
    args = _parser().parse_args(
        ["record", "--out", str(tmp_path / "x.bag"), "--seed", "1", "--duration", "-3"]
    )
    with pytest.raises(InputError, match="duration"):
        cli_record.run(args)
