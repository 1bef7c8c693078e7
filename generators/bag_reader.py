"""Reading a rosbag (ROS1, ROS2 sqlite3, ROS2 MCAP) into a :class:`Recording`, validated.

Which topic feeds which stream comes from a topic map (:mod:`~bopsurg.generators.topic_map`);
every problem is a :class:`~bopsurg.generators.topic_map.BagError` naming the bag and topic.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores
from scipy.spatial.transform import Rotation

from bopsurg.generators.kinematics import (
    ECM_JOINT_LIMITS,
    ECM_JOINT_NAMES,
    PSM_JOINT_NAMES,
    SIMULATOR_PSM,
    PsmKinematics,
)
from bopsurg.generators.recording import Recording
from bopsurg.generators.topic_map import (
    BagError,
    Source,
    TopicMap,
    load_topic_map,
    normalize_msgtype,
    typestore,
)

F64 = NDArray[np.float64]

#: Slack on the limits for a real robot's joints, rad or m: measured joints of a real arm
#: overshoot its software limits a little; far outside them means wrong units or order.
REAL_LIMIT_SLACK = 0.05


def read_bag(
    path: str | Path,
    *,
    topic_map: str | Path = "crtk",
    check_limits: bool = True,
    limit_tol: float = 1e-6,
    joint_source: str | None = None,
    kinematics: PsmKinematics | None = None,
) -> Recording:
    """Read a bag (ROS1 file, ROS2 sqlite3 or MCAP folder) into a :class:`Recording`.

    Stamps are the message header stamps when present and non-zero, else the bag's receive
    times. Times become seconds relative to the ``time_origin_ns`` of the bag's meta message
    (bags written by :func:`write_bag`), else to the earliest stamp read.

    Args:
        path: The ``.bag`` file, the ROS2 bag folder (or a ``.db3`` / ``.mcap`` file in it).
        topic_map: Built-in map name (``"crtk"``, ``"ambf"``) or TOML path.
        check_limits: Reject joints and jaws outside the kinematics' limits.
        limit_tol: Slack on the limits (rad or m); at least :data:`REAL_LIMIT_SLACK` for a
            real robot's recording.
        joint_source: ``measured`` or ``setpoint``: take the PSM joints, jaws and tool-tip
            poses only from topics of that kind (``.../setpoint_js`` vs the others); None:
            the first candidate present.
        kinematics: Whose joint and jaw limits to check; default: the simulator's for a
            simulator's recording, the dVRK's Large Needle Driver for a real robot's (the
            topic map's ``robot``).

    Returns:
        The recording; ``source`` is the bag path, ``robot`` whose kinematics replay it.

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
    raw, meta_json = _read_streams(bag, tmap, joint_source)
    meta: dict[str, Any] = {}
    if meta_json is not None:
        try:
            meta = dict(json.loads(meta_json))
        except (ValueError, TypeError) as err:
            raise BagError(f"meta message is not a JSON object ({err})", path=bag) from err
    robot = tmap.robot_of(meta_json is not None)
    if kinematics is None:
        from bopsurg.generators.dvrk_tools import dvrk_psm

        kinematics = SIMULATOR_PSM if robot == "simulator" else dvrk_psm()
    tol = limit_tol if robot == "simulator" else max(limit_tol, REAL_LIMIT_SLACK)
    rec = _assemble(bag, raw, meta, kinematics if check_limits else None, tol)
    rec.robot = robot
    return rec


RawStreams = dict[tuple[str, str | None], tuple[Source, list[int], list[Any]]]


def _read_streams(
    bag: Path, tmap: TopicMap, joint_source: str | None
) -> tuple[RawStreams, str | None]:
    """Every chosen stream's (source, stamps ns, values) and the meta message's text."""
    raw: RawStreams = {}
    meta_json: str | None = None
    try:
        with AnyReader([bag], default_typestore=typestore(Stores.ROS2_HUMBLE, tmap)) as reader:
            by_topic: dict[str, list[Source]] = {}
            for src in choose_sources(reader, tmap, bag, joint_source):
                by_topic.setdefault(src.topic, []).append(src)  # AMBF: one topic, 2 streams
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
    return raw, meta_json


def _brief(err: BaseException) -> str:
    text = " ".join(str(err).split()) or type(err).__name__
    return text if len(text) <= 200 else text[:197] + "..."


JOINT_SOURCES = ("measured", "setpoint")


def _of_kind(cands: list[Source], joint_source: str | None) -> list[Source]:
    """The candidates of a per-arm stream that are of the wanted kind (setpoint or not)."""
    if joint_source is None or cands[0].stream not in ("psm_joints", "jaw", "psm_pose"):
        return cands
    if joint_source not in JOINT_SOURCES:
        raise BagError(f"must be one of {', '.join(JOINT_SOURCES)}", field="joint_source")
    want_setpoint = joint_source == "setpoint"
    return [s for s in cands if ("setpoint" in s.topic) == want_setpoint]


def choose_sources(
    reader: Any, tmap: TopicMap, bag: Path, joint_source: str | None = None
) -> list[Source]:
    """For each stream of the map, the first candidate the bag holds with the map's type.

    A candidate topic present with another type is skipped when a later candidate fits, and
    is the error when none does.
    """
    present: dict[str, list[Any]] = {}
    for conn in reader.connections:
        present.setdefault(conn.topic, []).append(conn)
    chosen = []
    for key in tmap.stream_keys():
        cands = [s for s in _of_kind(tmap.candidates(key), joint_source) if s.topic in present]
        fits = [
            s
            for s in cands
            if all(normalize_msgtype(c.msgtype) == s.msgtype for c in present[s.topic])
        ]
        if not fits:
            if cands:
                src = cands[0]
                wrong = next(
                    c for c in present[src.topic] if normalize_msgtype(c.msgtype) != src.msgtype
                )
                raise BagError(
                    f"message type {wrong.msgtype} is not the topic map's {src.msgtype}",
                    path=bag,
                    field=src.topic,
                )
            if any(s.required for s in tmap.candidates(key)):
                _missing(tmap.candidates(key), present, bag)
            continue
        src = fits[0]
        if sum(int(getattr(c, "msgcount", 1)) for c in present[src.topic]) == 0:
            raise BagError("topic has no messages", path=bag, field=src.topic)
        chosen.append(src)
    if tmap.require_one_arm and not any(s.stream == "psm_joints" for s in chosen):
        arms = [s for s in tmap.sources if s.stream == "psm_joints"]
        _missing(_of_kind(arms, joint_source) or arms, present, bag)
    return chosen


def _missing(cands: Sequence[Source], present: Mapping[str, Any], bag: Path) -> None:
    """Raise the error of a required stream none of whose candidates the bag holds."""
    topics = " or ".join(s.topic for s in cands)
    have = ", ".join(sorted(present)) or "none"
    raise BagError(f"required topic missing (bag topics: {have})", path=bag, field=topics)


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
    if src.stream in ("needle_pose", "psm_pose"):
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
    scaled: F64 = arr * np.asarray(src.scale)
    return scaled


_EXPECTED = {"psm_joints": 6, "jaw": 1, "ecm_joints": 4}


def _limits(kinematics: PsmKinematics) -> dict[str, tuple[F64, Sequence[str]]]:
    return {
        "psm_joints": (kinematics.limits(), PSM_JOINT_NAMES),
        "jaw": (np.array([kinematics.jaw_limits]), ("jaw",)),
        "ecm_joints": (ECM_JOINT_LIMITS, ECM_JOINT_NAMES),
    }


def _assemble(
    bag: Path,
    raw: RawStreams,
    meta: dict[str, Any],
    kinematics: PsmKinematics | None,
    limit_tol: float,
) -> Recording:
    """Validate the raw streams and convert them to relative-time arrays (joints and jaws
    against the limits of ``kinematics`` unless None)."""
    limits = {} if kinematics is None else _limits(kinematics)
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
        if stream in ("needle_pose", "psm_pose"):
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
        if stream in limits:
            _check_limits(bag, src, times, vals, *limits[stream], limit_tol)
        if stream == "psm_joints":
            rec.psm_joints[str(arm)] = (times, vals)
        elif stream == "jaw":
            rec.jaws[str(arm)] = (times, vals[:, 0])
        elif stream == "psm_pose":
            rec.psm_poses[str(arm)] = (times, vals)
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


__all__ = ["JOINT_SOURCES", "choose_sources", "read_bag"]
