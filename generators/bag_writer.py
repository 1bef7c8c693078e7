"""Writing a :class:`~bopsurg.generators.recording.Recording` as a rosbag, atomically.

Each stream goes to the first *writable* source of its topic map (a standard message type:
JointState, Float64MultiArray, Float64, PoseStamped, String); the bag is written beside the
target under a temporary name and renamed when complete. The topics and their units are listed
in :mod:`bopsurg.generators.bags`.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores
from scipy.spatial.transform import Rotation

from bopsurg.generators.kinematics import ECM_JOINT_NAMES, PSM_JOINT_NAMES
from bopsurg.generators.recording import DEFAULT_TIME_ORIGIN_NS, Recording, Stream
from bopsurg.generators.topic_map import BagError, Source, TopicMap, load_topic_map, typestore

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
BagFormat = Literal["ros1", "ros2", "mcap"]

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

    def encode(self, src: Source, value: Any, seq: int, stamp_ns: int) -> Any:
        """The message of one sample (recording units, divided by the source's scale)."""
        if src.stream == "meta":
            return self.t[src.msgtype](data=str(value))
        scale = np.asarray(src.scale)
        if src.stream == "needle_pose":
            T = value.copy()
            T[:3, 3] /= scale[0]
            return self.build(src, T, seq, stamp_ns)
        return self.build(src, np.atleast_1d(value) / scale, seq, stamp_ns)

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
    ts = typestore(store, tmap)
    factory = _MessageFactory(ts)
    serialize = ts.serialize_ros1 if format == "ros1" else ts.serialize_cdr

    target.parent.mkdir(parents=True, exist_ok=True)
    tmp_dir = target.parent / f".{target.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp_dir, ignore_errors=True)
    tmp_dir.mkdir()
    tmp = tmp_dir / target.name  # the bag keeps its final name inside (ROS2 names files by it)
    counts: dict[str, int] = {}
    try:
        with _open_writer(tmp, format) as writer:
            messages = []  # (stamp_ns, order, connection, raw)
            for order, (src, times, values) in enumerate(plan):
                conn = writer.add_connection(src.topic, src.msgtype, typestore=ts)
                for i, (t, v) in enumerate(zip(times, values, strict=True)):
                    stamp = origin + round(float(t) * 1e9)
                    msg = factory.encode(src, v, i, stamp)
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


def _open_writer(path: Path, format: BagFormat) -> Any:
    """A rosbags writer of the format (not yet opened)."""
    if format == "ros1":
        return Writer1(path)
    plugin = StoragePlugin.MCAP if format == "mcap" else StoragePlugin.SQLITE3
    return Writer2(path, version=9, storage_plugin=plugin)


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


__all__ = ["BagFormat", "write_bag"]
