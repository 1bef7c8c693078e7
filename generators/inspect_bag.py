"""What a bag holds and what ``bopsurg generate`` will make of it (``bopsurg inspect``).

:func:`inspect_bag` lists the bag's topics (message type, count, rate), which streams the
topic map finds in it (each arm's joints, Cartesian pose and jaw, the ECM, the needle, the
meta), whose kinematics replay it and how ``generate`` stages it (arms, needle holder,
camera), and, for every arm recorded with both joints and Cartesian poses, the forward
kinematics check of :mod:`~bopsurg.generators.fk_check`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores

from bopsurg.generators.backend import ALL_ARMS
from bopsurg.generators.bag_reader import choose_sources, read_bag
from bopsurg.generators.dvrk_tools import dvrk_psm
from bopsurg.generators.fk_check import FkCheck, fk_check
from bopsurg.generators.kinematics import SIMULATOR_PSM, PsmKinematics
from bopsurg.generators.recording import Recording
from bopsurg.generators.replay import frame_times
from bopsurg.generators.staging import Staging, stage_recording
from bopsurg.generators.topic_map import BagError, Source, load_topic_map, typestore


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag: type, message count, rate (Hz, 0 for fewer than two messages)."""

    topic: str
    msgtype: str
    count: int
    rate_hz: float
    frame_id: str = ""


@dataclass
class BagReport:
    """Everything ``bopsurg inspect`` prints about one bag."""

    path: Path
    duration: float
    topics: list[TopicInfo]
    sources: list[Source]
    recording: Recording
    kinematics: PsmKinematics
    staging: Staging | None
    checks: list[FkCheck] = field(default_factory=list)
    frames: int = 0
    period: float = 0.5

    def lines(self) -> list[str]:
        """The report, one line each."""
        out = [f"{self.path}: {self.duration:.2f} s, {len(self.topics)} topics"]
        for t in self.topics:
            frame = f"  frame {t.frame_id}" if t.frame_id else ""
            out.append(f"  {t.topic}  {t.msgtype}  {t.count} msgs  {t.rate_hz:.1f} Hz{frame}")
        out += self._stream_lines()
        out += self._plan_lines()
        out += [c.line() for c in self.checks]
        return out

    def _stream_lines(self) -> list[str]:
        found = {(s.stream, s.arm): s.topic for s in self.sources}
        out = ["streams:"]
        for arm in ALL_ARMS:
            topics = [found.get((stream, arm)) for stream in ("psm_joints", "psm_pose", "jaw")]
            if topics == [None, None, None]:
                continue
            js, cp, jaw = (t or "none" for t in topics)
            note = "" if topics[0] else " (not rendered: generate poses arms from joints)"
            out.append(f"  {arm}: joints {js}, Cartesian {cp}, jaw {jaw}{note}")
        for stream, name in (("ecm_joints", "ECM"), ("needle_pose", "needle"), ("meta", "meta")):
            out.append(f"  {name}: {found.get((stream, None), 'none')}")
        return out

    def _plan_lines(self) -> list[str]:
        rec, st = self.recording, self.staging
        out = ["generate will:"]
        if st is None:
            out.append(
                "  replay a simulator's recording (bopsurg's or AMBF's) with the simulator's "
                "kinematics, the recorded needle pose and the default layout"
            )
        else:
            out.append(
                f"  render the recorded arms {', '.join(st.arms)} with the dVRK's "
                f"{st.kinematics.name} kinematics ({st.kinematics.source})"
            )
            holder = (
                f"held in {st.holder}'s jaws (closed on it)"
                if st.holder
                else "lying on the tissue under the workspace"
            )
            out.append(f"  place the needle {holder} (no needle topic is used)")
            out.append(
                "  draw endoscope viewpoints framed on the tool-tip workspace (extent "
                f"{st.extent * 1e3:.0f} mm, camera {st.view_distance * 1e3:.0f} mm from its "
                "centre at zero ECM joints; the recorded ECM joints are not used)"
            )
        out.append(f"  render {self.frames} frames per replay at --period {self.period:g} s")
        if rec.psm_poses and not self.checks:
            out.append("  (fk-check: no joint and pose samples pair by stamp)")
        return out


def topic_infos(reader: Any) -> list[TopicInfo]:
    """Per topic: type, count, rate from the bag's own times (messages not decoded)."""
    times: dict[str, list[int]] = {c.topic: [] for c in reader.connections}
    for conn, t, _ in reader.messages():
        times[conn.topic].append(t)
    out = []
    for conn in sorted(reader.connections, key=lambda c: c.topic):
        ts = np.asarray(times[conn.topic], dtype=np.float64)
        span = (ts[-1] - ts[0]) / 1e9 if len(ts) > 1 else 0.0
        rate = (len(ts) - 1) / span if span > 0 else 0.0
        out.append(TopicInfo(conn.topic, conn.msgtype, len(ts), rate, _frame_id(reader, conn)))
    return out


def _frame_id(reader: Any, conn: Any) -> str:
    """The header frame of a topic's first message ('' without a header or a decoder)."""
    for _, _, data in reader.messages(connections=[conn]):
        try:
            msg = reader.deserialize(data, conn.msgtype)
        except Exception:  # a type the typestore does not know: no frame to show
            return ""
        header = getattr(msg, "header", None)
        return str(getattr(header, "frame_id", "")) if header is not None else ""
    return ""


def inspect_bag(
    path: str | Path,
    *,
    topic_map: str = "crtk",
    joint_source: str | None = None,
    psm_tool: str | None = None,
    needle_holder: str = "auto",
    period: float = 0.5,
) -> BagReport:
    """Read a bag and say what it holds and what ``generate`` will do with it.

    Raises:
        BagError: The bag cannot be read (one line naming it and the topic).
        InputError: An unknown tool or needle holder.
    """
    bag = Path(path)
    kin = None if psm_tool is None else dvrk_psm(psm_tool)
    rec = read_bag(bag, topic_map=topic_map, joint_source=joint_source, kinematics=kin)
    tmap = load_topic_map(topic_map)
    folder = Path(rec.source)
    try:
        with AnyReader([folder], default_typestore=typestore(Stores.ROS2_HUMBLE, tmap)) as r:
            topics = topic_infos(r)
            sources = choose_sources(r, tmap, folder, joint_source)
            duration = (r.end_time - r.start_time) / 1e9
    except BagError:
        raise
    except Exception as err:  # read_bag read it: only an unexpected rosbags failure
        raise BagError(f"cannot read bag ({err})", path=bag) from err
    kinematics = kin or (SIMULATOR_PSM if rec.robot == "simulator" else dvrk_psm())
    staging = None
    played = rec
    if rec.robot != "simulator":
        played, staging = stage_recording(rec, kinematics, needle_holder=needle_holder)
    checks = [
        c
        for arm in ALL_ARMS
        if arm in rec.psm_joints and arm in rec.psm_poses
        if (c := fk_check(arm, rec.psm_joints[arm], rec.psm_poses[arm], kinematics)) is not None
    ]
    frames = len(frame_times(played.start, played.end, period))
    return BagReport(
        bag, duration, topics, sources, rec, kinematics, staging, checks, frames, period
    )


__all__ = ["BagReport", "TopicInfo", "inspect_bag", "topic_infos"]
