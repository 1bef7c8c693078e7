"""Recordings of a suturing episode, in memory and as rosbags (ROS1, ROS2 sqlite3, ROS2 MCAP).

A :class:`Recording` holds time-stamped streams (joints of each PSM, jaws, ECM joints, needle
pose) and answers :meth:`Recording.state_at` with the :class:`SceneState` a renderer replays.
:func:`write_bag` and :func:`read_bag` move recordings to and from bags with the `rosbags`
library; which topic carries which stream comes from a *topic map* (TOML), so recordings made
elsewhere (the AMBF surgical-robotics-challenge, a real dVRK) replay too.

Topics written (built-in map ``crtk``):

+-------------------------+---------------------------+--------------------+--------+---------+
| topic                   | type                      | content            | units  | frame   |
+=========================+===========================+====================+========+=========+
| /psm1/measured_js,      | sensor_msgs/JointState    | 6 PSM joints,      | rad;   | joints  |
| /psm2/measured_js       |                           | CRTK order [1]     | m [2]  | [3]     |
+-------------------------+---------------------------+--------------------+--------+---------+
| /psm1/jaw/measured_js,  | sensor_msgs/JointState    | one joint ``jaw``: | rad    | —       |
| /psm2/jaw/measured_js   |                           | opening [4]        |        |         |
+-------------------------+---------------------------+--------------------+--------+---------+
| /ecm/measured_js        | sensor_msgs/JointState    | yaw, pitch,        | rad;   | joints  |
|                         |                           | insertion, roll    | m [2]  | [5]     |
+-------------------------+---------------------------+--------------------+--------+---------+
| /needle/measured_cp     | geometry_msgs/PoseStamped | T_world_needle:    | m;     | world   |
|                         |                           | position, quat [6] | xyzw   | [7]     |
+-------------------------+---------------------------+--------------------+--------+---------+
| /bopsurg/meta           | std_msgs/String           | JSON, one message  | —      | —       |
|                         |                           | at t = 0 [8]       |        |         |
+-------------------------+---------------------------+--------------------+--------+---------+

[1] ``outer_yaw, outer_pitch, outer_insertion, outer_roll, outer_wrist_pitch,
    outer_wrist_yaw`` (the JointState ``name`` field carries them).
[2] Insertion in m, the other joints in rad.
[3] The arm's base frame is its remote centre of motion, ``SceneLayout.psm_base(i)``; the
    tool tip is ``psm_tip_pose(q)`` in it.
[4] A jaw at or below 0.2 rad holds the needle (``trajectory.GRASP_JAW_THRESHOLD``).
[5] Relative to ``SceneLayout.ecm_base()``; the camera pose is ``ecm_camera_pose(joints)``.
[6] The needle model frame (BOP's: arc in its XY plane around the origin, tail on +X; the
    model's vertices are in mm, this pose in m).
[7] ``header.frame_id = "world"``: the tissue surface is z = 0, +Z up.
[8] Seed, generator and version, layout, needle spec, rate, ``time_origin_ns``, task events
    and grasp windows.

Stamps: ``time_origin_ns`` + the sample time, in both the message header and the bag record;
``time_origin_ns`` defaults to :data:`DEFAULT_TIME_ORIGIN_NS`.

Topic maps (``topic_maps/crtk.toml``, ``topic_maps/ambf.toml``, or a path) list *sources*: for
each stream (``psm_joints``, ``jaw``, ``ecm_joints``, ``needle_pose``, ``meta``; per ``arm``
for the first two) the candidate topics in order of preference, each with its message type,
the ``field`` holding the value (dotted attribute path), an optional ``scale`` (number or
per-element list, multiplied on read and divided on write; e.g. 0.1 turns AMBF simulation units
into metres) and ``indices`` (elements to take). ``required = true`` makes a stream mandatory.
A ``[types]`` table registers custom messages: ``"pkg/msg/Name" = "relative/path/Name.msg"``.
Reading takes the first candidate topic the bag holds; writing the first one with a standard
type (JointState, Float64MultiArray, Float64, PoseStamped, String).

Streams missing from a recording come from documented defaults in :meth:`Recording.state_at`.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from bopsurg.errors import InputError
from bopsurg.generators.backend import SceneState
from bopsurg.generators.kinematics import (
    ECM_JOINT_LIMITS,
    ECM_JOINT_NAMES,
    JAW_LIMITS,
    PSM_JOINT_LIMITS,
    PSM_JOINT_NAMES,
)

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
Stream = tuple[F64, F64]  # (times (T,) s, values (T, ...))
BagFormat = Literal["ros1", "ros2", "mcap"]

#: Defaults :meth:`Recording.state_at` uses for streams a recording lacks.
#: A parked PSM: shaft straight along its base −Z, 5 cm inserted (the tip ~28 mm below the
#: RCM, far above the tissue); jaws closed.
PARKED_PSM_JOINTS = np.array([0.0, 0.0, 0.05, 0.0, 0.0, 0.0])
PARKED_JAW = 0.0
#: The endoscope at its base pose (looking at the workspace centre).
DEFAULT_ECM_JOINTS = np.zeros(4)
#: The needle lying flat on the tissue at the world origin (model +Z up; 0.36 mm = wire radius).
DEFAULT_NEEDLE_POSE = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.36e-3], [0.0, 0.0, 0.0, 1.0]]
)
#: Absolute time (ns since the epoch) of t = 0 when a recording does not say (2023-11-14).
DEFAULT_TIME_ORIGIN_NS = 1_700_000_000 * 10**9

STREAMS = ("psm_joints", "jaw", "ecm_joints", "needle_pose", "meta")
_PER_ARM = ("psm_joints", "jaw")
TOPIC_MAP_DIR = Path(__file__).parent / "topic_maps"


class BagError(InputError):
    """A bag or topic map that cannot be read or written, named with its file and topic."""


# --------------------------------------------------------------------------- recording


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
    """

    psm_joints: dict[str, Stream] = field(default_factory=dict)
    jaws: dict[str, Stream] = field(default_factory=dict)
    ecm_joints: Stream | None = None
    needle_pose: Stream | None = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

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
        slerp in rotation. Streams the recording lacks take the defaults: arms ``psm1`` and
        ``psm2`` parked (:data:`PARKED_PSM_JOINTS`, jaw :data:`PARKED_JAW`), the ECM at
        :data:`DEFAULT_ECM_JOINTS`, the needle at :data:`DEFAULT_NEEDLE_POSE`.
        """
        arms = sorted({"psm1", "psm2", *self.psm_joints, *self.jaws})
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
    return (1.0 - w) * values[i] + w * values[i + 1]


def _interp_pose(times: F64, poses: F64, t: float) -> F64:
    i, w = _bracket(times, t)
    if len(times) == 1 or w == 0.0:
        return poses[i].copy()
    T_a, T_b = poses[i], poses[i + 1]
    if w == 1.0:
        return T_b.copy()
    rv = Rotation.from_matrix(T_a[:3, :3].T @ T_b[:3, :3]).as_rotvec()
    T = np.eye(4)
    T[:3, :3] = T_a[:3, :3] @ Rotation.from_rotvec(w * rv).as_matrix()
    T[:3, 3] = (1.0 - w) * T_a[:3, 3] + w * T_b[:3, 3]
    return T


# --------------------------------------------------------------------------- topic maps


@dataclass(frozen=True)
class Source:
    """One candidate topic of a stream in a topic map.

    Attributes:
        stream: ``psm_joints``, ``jaw``, ``ecm_joints``, ``needle_pose`` or ``meta``.
        arm: The arm (``psm_joints`` and ``jaw`` only), else None.
        topic: Topic name.
        msgtype: Message type, normalised to ``pkg/msg/Name``.
        field: Dotted attribute path to the value inside the message.
        scale: Factor(s) applied on read (divided on write); for poses, to the translation.
        indices: Elements of an array field to take, or None for all.
        required: The stream must be in the bag (through any of its sources).
    """

    stream: str
    arm: str | None
    topic: str
    msgtype: str
    field: str
    scale: tuple[float, ...] = (1.0,)
    indices: tuple[int, ...] | None = None
    required: bool = False

    @property
    def key(self) -> tuple[str, str | None]:
        """(stream, arm): sources with the same key are alternatives."""
        return self.stream, self.arm


@dataclass(frozen=True)
class TopicMap:
    """A parsed topic map.

    Attributes:
        name: Its name.
        path: The TOML file.
        sources: Candidate topics, in order of preference within each stream.
        types: Custom message types: type name → ``.msg`` file.
    """

    name: str
    path: Path
    sources: tuple[Source, ...]
    types: Mapping[str, Path]

    def candidates(self, key: tuple[str, str | None]) -> list[Source]:
        """Sources of one stream, in order of preference."""
        return [s for s in self.sources if s.key == key]

    def stream_keys(self) -> list[tuple[str, str | None]]:
        """Distinct (stream, arm) keys, in file order."""
        return list(dict.fromkeys(s.key for s in self.sources))


def normalize_msgtype(name: str) -> str:
    """``pkg/Name`` or ``pkg/msg/Name`` → ``pkg/msg/Name``."""
    parts = name.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name.strip()


def load_topic_map(topic_map: str | Path) -> TopicMap:
    """Load a topic map: a built-in name (``"crtk"``, ``"ambf"``) or a path to a TOML file.

    Raises:
        BagError: Unknown name, unreadable TOML, or an invalid entry (named by its index).
    """
    path = Path(topic_map)
    if path.suffix != ".toml" and not path.exists():
        path = TOPIC_MAP_DIR / f"{topic_map}.toml"
        if not path.is_file():
            known = sorted(p.stem for p in TOPIC_MAP_DIR.glob("*.toml"))
            raise BagError(f"unknown topic map {topic_map!r}; built-in maps: {', '.join(known)}")
    if not path.is_file():
        raise BagError("topic map not found", path=path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise BagError(f"invalid TOML: {err}", path=path) from err
    types = {}
    for name, rel in dict(data.get("types", {})).items():
        msg = (path.parent / str(rel)).resolve()
        if not msg.is_file():
            raise BagError(f"message definition {rel!r} not found", path=path, field=name)
        types[normalize_msgtype(name)] = msg
    raw = data.get("source", [])
    if not isinstance(raw, list) or not raw:
        raise BagError("no [[source]] entries", path=path)
    sources = tuple(_parse_source(entry, i, path) for i, entry in enumerate(raw))
    return TopicMap(str(data.get("name", path.stem)), path, sources, types)


def _parse_source(entry: Mapping[str, Any], index: int, path: Path) -> Source:
    where = f"source[{index}]"
    try:
        stream = str(entry["stream"])
        topic = str(entry["topic"])
        msgtype = normalize_msgtype(str(entry["type"]))
        fld = str(entry["field"])
    except KeyError as err:
        raise BagError(f"missing key {err.args[0]!r}", path=path, field=where) from err
    if stream not in STREAMS:
        raise BagError(
            f"unknown stream {stream!r}; one of {', '.join(STREAMS)}", path=path, field=where
        )
    arm = entry.get("arm")
    if (stream in _PER_ARM) != (arm is not None):
        need = "needs" if stream in _PER_ARM else "takes no"
        raise BagError(f"stream {stream!r} {need} 'arm'", path=path, field=where)
    scale = entry.get("scale", 1.0)
    scale_t = tuple(float(x) for x in (scale if isinstance(scale, list) else [scale]))
    if not scale_t or not all(math.isfinite(x) and x != 0.0 for x in scale_t):
        raise BagError("scale must be finite and non-zero", path=path, field=where)
    indices = entry.get("indices")
    return Source(
        stream=stream,
        arm=None if arm is None else str(arm),
        topic=topic,
        msgtype=msgtype,
        field=fld,
        scale=scale_t,
        indices=None if indices is None else tuple(int(i) for i in indices),
        required=bool(entry.get("required", False)),
    )


def _typestore(store: Stores, tmap: TopicMap) -> Any:
    """A typestore of ``store`` with the map's custom types registered."""
    ts = get_typestore(store)
    for name, msg in tmap.types.items():
        try:
            ts.register(get_types_from_msg(msg.read_text(encoding="utf-8"), name))
        except Exception as err:  # rosbags raises several types for bad definitions
            raise BagError(f"cannot register {name}: {err}", path=msg) from err
    return ts


# --------------------------------------------------------------------------- writing

_WRITABLE = {
    "sensor_msgs/msg/JointState": "position",
    "std_msgs/msg/Float64MultiArray": "data",
    "std_msgs/msg/Float64": "data",
    "geometry_msgs/msg/PoseStamped": "pose",
    "std_msgs/msg/String": "data",
}


def _writable(src: Source) -> bool:
    return _WRITABLE.get(src.msgtype) == src.field and src.indices is None


def _joint_names(stream: str, n: int) -> list[str]:
    if stream == "psm_joints" and n == 6:
        return list(PSM_JOINT_NAMES)
    if stream == "ecm_joints" and n == 4:
        return list(ECM_JOINT_NAMES)
    if stream == "jaw":
        return ["jaw"]
    return [f"joint_{i}" for i in range(n)]


class _MessageFactory:
    """Builds standard messages for one typestore (ROS1 headers carry ``seq``)."""

    def __init__(self, ts: Any) -> None:
        self.ts = ts
        self.t = ts.types
        self.has_seq = "seq" in self.t["std_msgs/msg/Header"].__dataclass_fields__

    def header(self, seq: int, stamp_ns: int, frame_id: str) -> Any:
        stamp = self.t["builtin_interfaces/msg/Time"](
            sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9
        )
        header_type = self.t["std_msgs/msg/Header"]
        if self.has_seq:
            return header_type(seq=seq, stamp=stamp, frame_id=frame_id)
        return header_type(stamp=stamp, frame_id=frame_id)

    def build(self, src: Source, value: F64, seq: int, stamp_ns: int) -> Any:
        t = self.t
        if src.msgtype == "sensor_msgs/msg/JointState":
            n = value.size
            return t[src.msgtype](
                header=self.header(seq, stamp_ns, ""),
                name=_joint_names(src.stream, n),
                position=np.ascontiguousarray(value, dtype=np.float64).ravel(),
                velocity=np.zeros(0),
                effort=np.zeros(0),
            )
        if src.msgtype == "std_msgs/msg/Float64MultiArray":
            layout = t["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
            return t[src.msgtype](layout=layout, data=np.ascontiguousarray(value).ravel())
        if src.msgtype == "std_msgs/msg/Float64":
            return t[src.msgtype](data=float(value.ravel()[0]))
        if src.msgtype == "geometry_msgs/msg/PoseStamped":
            x, y, z = value[:3, 3]
            qx, qy, qz, qw = Rotation.from_matrix(value[:3, :3]).as_quat()
            pose = t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z)),
                orientation=t["geometry_msgs/msg/Quaternion"](
                    x=float(qx), y=float(qy), z=float(qz), w=float(qw)
                ),
            )
            return t[src.msgtype](header=self.header(seq, stamp_ns, "world"), pose=pose)
        raise AssertionError(src.msgtype)  # _writable() filtered the rest


def _check_stream(kind: str, arm: str | None, stream: Stream, shape: tuple[int, ...]) -> None:
    name = kind if arm is None else f"{kind}[{arm}]"
    times, values = (np.asarray(a, dtype=np.float64) for a in stream)
    if times.ndim != 1 or values.shape != (len(times), *shape):
        raise BagError(
            f"expected times (T,) and values (T, {', '.join(map(str, shape))}), got "
            f"{times.shape} and {values.shape}",
            field=name,
        )
    if len(times) == 0:
        raise BagError("stream is empty", field=name)
    if not (np.all(np.isfinite(times)) and np.all(np.isfinite(values))):
        raise BagError("non-finite time or value", field=name)
    bad = np.flatnonzero(np.diff(times) <= 0.0)
    if bad.size:
        raise BagError(f"times not strictly increasing at sample {bad[0] + 1}", field=name)


_SHAPES = {"psm_joints": (6,), "jaw": (), "ecm_joints": (4,), "needle_pose": (4, 4)}


def write_bag(
    path: str | Path,
    recording: Recording,
    *,
    format: BagFormat = "ros1",
    topic_map: str | Path = "crtk",
    overwrite: bool = False,
) -> dict[str, int]:
    """Write a recording as a rosbag, atomically.

    The bag is written beside the target under a temporary name and renamed when complete,
    so a reader never sees half a bag. ROS2 and MCAP bags are folders (``metadata.yaml`` plus
    one ``.db3`` / ``.mcap`` file); ROS1 bags are single files, which must end in ``.bag``
    (readers tell the formats apart by it).

    Args:
        path: Target file (ROS1) or folder (ROS2, MCAP).
        recording: What to write; times relative to ``meta["time_origin_ns"]``
            (default :data:`DEFAULT_TIME_ORIGIN_NS`).
        format: ``"ros1"``, ``"ros2"`` (sqlite3 storage) or ``"mcap"`` (ROS2 MCAP storage).
        topic_map: Built-in map name or TOML path; each stream goes to its map's first
            writable source.
        overwrite: Replace an existing target.

    Returns:
        Messages written per topic.

    Raises:
        BagError: Target exists (without ``overwrite``), bad format or suffix, a stream the
            map cannot write, or malformed recording arrays.
    """
    target = Path(path)
    if format not in ("ros1", "ros2", "mcap"):
        raise BagError(f"unknown bag format {format!r}; one of ros1, ros2, mcap", path=target)
    if format == "ros1" and target.suffix != ".bag":
        raise BagError("a ROS1 bag file name must end in .bag", path=target)
    if (target.exists() or target.is_symlink()) and not overwrite:
        raise BagError(
            "exists already; pass overwrite=True (--overwrite) to replace it", path=target
        )
    tmap = load_topic_map(topic_map)
    plan = _write_plan(recording, tmap)
    origin = int(recording.meta.get("time_origin_ns", DEFAULT_TIME_ORIGIN_NS))
    store = Stores.ROS1_NOETIC if format == "ros1" else Stores.ROS2_HUMBLE
    ts = _typestore(store, tmap)
    factory = _MessageFactory(ts)
    serialize = ts.serialize_ros1 if format == "ros1" else ts.serialize_cdr

    target.parent.mkdir(parents=True, exist_ok=True)
    tmp_dir = target.parent / f".{target.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp_dir, ignore_errors=True)
    tmp_dir.mkdir()
    tmp = tmp_dir / target.name  # the bag keeps its final name inside (ROS2 names files by it)
    counts: dict[str, int] = {}
    try:
        if format == "ros1":
            writer: Any = Writer1(tmp)
        else:
            plugin = StoragePlugin.MCAP if format == "mcap" else StoragePlugin.SQLITE3
            writer = Writer2(tmp, version=9, storage_plugin=plugin)
        with writer:
            messages = []  # (stamp_ns, order, connection, raw)
            for order, (src, times, values) in enumerate(plan):
                conn = writer.add_connection(src.topic, src.msgtype, typestore=ts)
                scale = np.asarray(src.scale)
                for i, (t, v) in enumerate(zip(times, values, strict=True)):
                    stamp = origin + round(float(t) * 1e9)
                    if src.stream == "meta":
                        msg = ts.types[src.msgtype](data=str(v))
                    elif src.stream == "needle_pose":
                        v = v.copy()
                        v[:3, 3] /= scale[0]
                        msg = factory.build(src, v, i, stamp)
                    else:
                        msg = factory.build(src, np.atleast_1d(v) / scale, i, stamp)
                    messages.append((stamp, order, conn, serialize(msg, src.msgtype)))
                counts[src.topic] = len(times)
            messages.sort(key=lambda m: (m[0], m[1]))  # bags are read in time order
            for stamp, _, conn, raw in messages:
                writer.write(conn, stamp, raw)
        _replace(tmp, target, overwrite)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)
    log.info("wrote %s (%s, %d topics)", target, format, len(counts))
    return counts


def _write_plan(recording: Recording, tmap: TopicMap) -> list[tuple[Source, Any, Any]]:
    """(source, times, values) of every stream to write, meta first."""
    plan: list[tuple[Source, Any, Any]] = []
    for kind, arm, stream in recording.streams():
        _check_stream(kind, arm, stream, _SHAPES[kind])
        cands = tmap.candidates((kind, arm))
        src = next((s for s in cands if _writable(s)), None)
        if src is None:
            name = kind if arm is None else f"{kind} of {arm}"
            raise BagError(
                f"topic map {tmap.name!r} has no writable topic for {name}", path=tmap.path
            )
        times, values = (np.asarray(a, dtype=np.float64) for a in stream)
        if src.stream in ("psm_joints", "ecm_joints", "jaw"):
            n = 1 if values.ndim == 1 else values.shape[1]
            if len(src.scale) not in (1, n):
                raise BagError(
                    f"scale has {len(src.scale)} elements for {n} values",
                    path=tmap.path,
                    field=src.topic,
                )
        plan.append((src, times, values))
    meta_src = next((s for s in tmap.candidates(("meta", None)) if _writable(s)), None)
    if meta_src is not None:
        meta = dict(recording.meta)
        meta.setdefault("time_origin_ns", DEFAULT_TIME_ORIGIN_NS)
        t0 = min((float(s[0][0]) for _, _, s in recording.streams()), default=0.0)
        plan.insert(0, (meta_src, [t0], [json.dumps(meta, sort_keys=True)]))
    return plan


def _replace(tmp: Path, target: Path, overwrite: bool) -> None:
    """Move the finished bag onto ``target``; an old target goes only once the new is in."""
    old = None
    if target.exists() or target.is_symlink():
        if not overwrite:  # appeared while writing
            raise BagError("exists already; pass overwrite=True to replace it", path=target)
        old = target.parent / f".{target.name}.old-{os.getpid()}"
        os.replace(target, old)
    os.replace(tmp, target)
    if old is not None:
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old)
        else:
            old.unlink()


# --------------------------------------------------------------------------- reading


def read_bag(
    path: str | Path,
    *,
    topic_map: str | Path = "crtk",
    check_limits: bool = True,
    limit_tol: float = 1e-6,
) -> Recording:
    """Read a bag (ROS1 file, ROS2 sqlite3 or MCAP folder) into a :class:`Recording`.

    Stamps are the message header stamps when present and non-zero, else the bag's receive
    times. Times become seconds relative to the ``time_origin_ns`` of the bag's meta message
    (bags written by :func:`write_bag`), else to the earliest stamp read.

    Args:
        path: The ``.bag`` file, the ROS2 bag folder (or a ``.db3`` / ``.mcap`` file in it).
        topic_map: Built-in map name (``"crtk"``, ``"ambf"``) or TOML path.
        check_limits: Reject joints and jaws outside the kinematics' limits.
        limit_tol: Slack on the limits (rad or m).

    Returns:
        The recording; ``source`` is the bag path.

    Raises:
        BagError: One line naming the bag and topic: missing or unreadable (truncated,
            corrupt) bag, required topic missing, message type not the map's or unknown,
            empty topic, non-finite values, non-increasing stamps, joints out of limits.
    """
    bag = Path(path)
    if not bag.exists():
        raise BagError("no such bag file or folder", path=bag)
    if (
        bag.is_file()
        and bag.suffix in (".db3", ".mcap")
        and (bag.parent / "metadata.yaml").exists()
    ):
        bag = bag.parent
    if bag.is_file() and bag.suffix != ".bag":
        raise BagError("a ROS1 bag file name must end in .bag (ROS2 bags are folders)", path=bag)
    tmap = load_topic_map(topic_map)
    default_ts = _typestore(Stores.ROS2_HUMBLE, tmap)
    raw: dict[tuple[str, str | None], tuple[Source, list[int], list[Any]]] = {}
    meta_json: str | None = None
    try:
        with AnyReader([bag], default_typestore=default_ts) as reader:
            chosen = _choose_sources(reader, tmap, bag)
            by_topic: dict[str, list[Source]] = {}
            for src in chosen:  # one topic may feed several streams (AMBF baselink State)
                by_topic.setdefault(src.topic, []).append(src)
                raw[src.key] = (src, [], [])
            conns = [c for c in reader.connections if c.topic in by_topic]
            for conn, t_bag, data in reader.messages(connections=conns):
                try:
                    msg = reader.deserialize(data, conn.msgtype)
                except Exception as err:
                    raise BagError(
                        f"cannot decode message type {conn.msgtype} ({_brief(err)}); register "
                        "its .msg under [types] in the topic map",
                        path=bag,
                        field=conn.topic,
                    ) from err
                for src in by_topic[conn.topic]:
                    if src.stream == "meta":
                        meta_json = str(_get_field(msg, src, bag))
                        continue
                    _, stamps, values = raw[src.key]
                    stamps.append(_stamp(msg, t_bag))
                    values.append(_extract(msg, src, bag, len(values)))
    except BagError:
        raise
    except Exception as err:  # rosbags raises many types for truncated or corrupt bags
        raise BagError(f"cannot read bag ({_brief(err)})", path=bag) from err
    meta: dict[str, Any] = {}
    if meta_json is not None:
        try:
            meta = dict(json.loads(meta_json))
        except (ValueError, TypeError) as err:
            raise BagError(f"meta message is not a JSON object ({err})", path=bag) from err
    return _assemble(bag, raw, meta, check_limits, limit_tol)


def _brief(err: BaseException) -> str:
    text = " ".join(str(err).split()) or type(err).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _choose_sources(reader: Any, tmap: TopicMap, bag: Path) -> list[Source]:
    """The first candidate present in the bag for each stream of the map; checks types."""
    present: dict[str, list[Any]] = {}
    for conn in reader.connections:
        present.setdefault(conn.topic, []).append(conn)
    chosen = []
    for key in tmap.stream_keys():
        cands = tmap.candidates(key)
        src = next((s for s in cands if s.topic in present), None)
        if src is None:
            if any(s.required for s in cands):
                topics = " or ".join(s.topic for s in cands)
                have = ", ".join(sorted(present)) or "none"
                raise BagError(
                    f"required topic missing (bag topics: {have})", path=bag, field=topics
                )
            continue
        conns = present[src.topic]
        for conn in conns:
            if normalize_msgtype(conn.msgtype) != src.msgtype:
                raise BagError(
                    f"message type {conn.msgtype} is not the topic map's {src.msgtype}",
                    path=bag,
                    field=src.topic,
                )
        if sum(int(getattr(c, "msgcount", 1)) for c in conns) == 0:
            raise BagError("topic has no messages", path=bag, field=src.topic)
        chosen.append(src)
    return chosen


def _stamp(msg: Any, t_bag: int) -> int:
    header = getattr(msg, "header", None)
    if header is not None:
        ns = int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec)
        if ns:
            return ns
    return int(t_bag)


def _get_field(msg: Any, src: Source, bag: Path) -> Any:
    obj = msg
    for part in src.field.split("."):
        if not hasattr(obj, part):
            raise BagError(
                f"message {src.msgtype} has no field {src.field!r}", path=bag, field=src.topic
            )
        obj = getattr(obj, part)
    return obj


def _extract(msg: Any, src: Source, bag: Path, index: int) -> F64:
    value = _get_field(msg, src, bag)
    if src.stream == "needle_pose":
        if hasattr(value, "position"):
            p, q = value.position, value.orientation
        elif hasattr(value, "translation"):
            p, q = value.translation, value.rotation
        else:
            raise BagError(f"field {src.field!r} is not a pose", path=bag, field=src.topic)
        quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
        T = np.full((4, 4), np.nan)
        norm = float(np.linalg.norm(quat))
        if np.all(np.isfinite(quat)) and norm > 1e-9:
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(quat / norm).as_matrix()
            T[:3, 3] = np.array([p.x, p.y, p.z], dtype=np.float64) * src.scale[0]
        return T
    arr = np.atleast_1d(np.asarray(value, dtype=np.float64)).ravel()
    if src.indices is not None:
        if arr.size <= max(src.indices):
            raise BagError(
                f"message {index} has {arr.size} values, the map takes indices {src.indices}",
                path=bag,
                field=src.topic,
            )
        arr = arr[list(src.indices)]
    if len(src.scale) not in (1, arr.size):
        raise BagError(
            f"scale has {len(src.scale)} elements for {arr.size} values", path=bag, field=src.topic
        )
    return arr * np.asarray(src.scale)


_EXPECTED = {"psm_joints": 6, "jaw": 1, "ecm_joints": 4}
_LIMITS = {
    "psm_joints": (PSM_JOINT_LIMITS, PSM_JOINT_NAMES),
    "jaw": (np.array([JAW_LIMITS]), ("jaw",)),
    "ecm_joints": (ECM_JOINT_LIMITS, ECM_JOINT_NAMES),
}


def _assemble(
    bag: Path,
    raw: Mapping[tuple[str, str | None], tuple[Source, list[int], list[Any]]],
    meta: dict[str, Any],
    check_limits: bool,
    limit_tol: float,
) -> Recording:
    """Validate the raw streams and convert them to relative-time arrays."""
    stamps_all = [s[0] for _, s, _ in raw.values() if s]
    if "time_origin_ns" in meta:
        origin = int(meta["time_origin_ns"])
    else:
        origin = min(stamps_all) if stamps_all else 0
        meta["time_origin_ns"] = origin
    rec = Recording(source=str(bag), meta=meta)
    for (stream, arm), (src, stamps, values) in raw.items():
        if stream == "meta":
            continue
        if not stamps:
            raise BagError("topic has no messages", path=bag, field=src.topic)
        times = (np.asarray(stamps, dtype=np.int64) - origin) / 1e9
        bad = np.flatnonzero(np.diff(times) <= 0.0)
        if bad.size:
            i = int(bad[0]) + 1
            raise BagError(
                f"stamps not increasing at message {i} ({times[i]:.9f} s after "
                f"{times[i - 1]:.9f} s)",
                path=bag,
                field=src.topic,
            )
        if stream == "needle_pose":
            vals = np.stack(values)
        else:
            n = _EXPECTED[stream]
            sizes = {v.size for v in values}
            if sizes != {n}:
                raise BagError(
                    f"expected {n} values per message, got {sorted(sizes)}",
                    path=bag,
                    field=src.topic,
                )
            vals = np.stack(values)
        finite = np.all(np.isfinite(vals.reshape(len(vals), -1)), axis=1)
        if not finite.all():
            i = int(np.flatnonzero(~finite)[0])
            raise BagError(
                f"NaN or infinite value in message {i} (t = {times[i]:.3f} s)",
                path=bag,
                field=src.topic,
            )
        if check_limits and stream in _LIMITS:
            _check_limits(bag, src, times, vals, *_LIMITS[stream], limit_tol)
        if stream == "psm_joints":
            rec.psm_joints[str(arm)] = (times, vals)
        elif stream == "jaw":
            rec.jaws[str(arm)] = (times, vals[:, 0])
        elif stream == "ecm_joints":
            rec.ecm_joints = (times, vals)
        else:
            rec.needle_pose = (times, vals)
    return rec


def _check_limits(
    bag: Path,
    src: Source,
    times: F64,
    vals: F64,
    limits: F64,
    names: Sequence[str],
    tol: float,
) -> None:
    out = (vals < limits[:, 0] - tol) | (vals > limits[:, 1] + tol)
    if out.any():
        i, j = (int(x) for x in np.argwhere(out)[0])
        lo, hi = limits[j]
        raise BagError(
            f"joint {names[j]} = {vals[i, j]:.6g} outside its limits [{lo:g}, {hi:g}] at "
            f"t = {times[i]:.3f} s (message {i})",
            path=bag,
            field=src.topic,
        )


__all__ = [
    "DEFAULT_ECM_JOINTS",
    "DEFAULT_NEEDLE_POSE",
    "DEFAULT_TIME_ORIGIN_NS",
    "PARKED_JAW",
    "PARKED_PSM_JOINTS",
    "BagError",
    "Recording",
    "Source",
    "TopicMap",
    "load_topic_map",
    "read_bag",
    "write_bag",
]
