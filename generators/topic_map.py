"""Topic maps: which bag topic carries which stream of a recording, and how to read it.

A topic map (``topic_maps/crtk.toml``, ``topic_maps/ambf.toml``, or a path) lists *sources*:
for each stream (``psm_joints``, ``jaw``, ``psm_pose``, ``ecm_joints``, ``needle_pose``,
``meta``; per ``arm`` for the first three) the candidate topics in order of preference, each
with its message type, the ``field`` holding the value (dotted attribute path), an optional
``scale`` (number or per-element list, multiplied on read and divided on write; e.g. 0.1 turns
AMBF simulation units into metres) and ``indices`` (elements to take). ``required = true``
makes a stream mandatory.
A ``[types]`` table registers custom messages: ``"pkg/msg/Name" = "relative/path/Name.msg"``.

Top-level keys: ``robot`` says whose kinematics replay the map's recordings (``simulator``,
the default; ``dvrk``; or ``auto``: the simulator's when the bag carries a meta message, as
every bag bopsurg writes does, else the real dVRK's) and ``require_one_arm = true`` makes the joints
of at least one arm mandatory.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from bopsurg.errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: the backport (bopsurg[sim] installs it there), same API
    import tomli as tomllib

STREAMS = ("psm_joints", "jaw", "psm_pose", "ecm_joints", "needle_pose", "meta")
_PER_ARM = ("psm_joints", "jaw", "psm_pose")
#: Whose kinematics replay a map's recordings.
ROBOTS = ("auto", "simulator", "dvrk")
TOPIC_MAP_DIR = Path(__file__).parent / "topic_maps"


class BagError(InputError):
    """A bag or topic map that cannot be read or written, named with its file and topic."""


@dataclass(frozen=True)
class Source:
    """One candidate topic of a stream in a topic map.

    Attributes:
        stream: ``psm_joints``, ``jaw``, ``psm_pose``, ``ecm_joints``, ``needle_pose`` or
            ``meta``.
        arm: The arm (``psm_joints``, ``jaw`` and ``psm_pose`` only), else None.
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
        robot: ``auto``, ``simulator`` or ``dvrk`` (:data:`ROBOTS`); ``simulator`` unless
            the file says.
        require_one_arm: At least one arm's ``psm_joints`` must be in the bag.
    """

    name: str
    path: Path
    sources: tuple[Source, ...]
    types: Mapping[str, Path]
    robot: str = "simulator"
    require_one_arm: bool = False

    def robot_of(self, has_meta: bool) -> str:
        """``simulator`` or ``dvrk`` for a bag with or without a meta message (``auto``: a bag
        bopsurg wrote, with its meta, was made with the simulator's kinematics)."""
        if self.robot != "auto":
            return self.robot
        return "simulator" if has_meta else "dvrk"

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
    # A map written before real recordings were staged replays as it always did.
    robot = str(data.get("robot", "simulator"))
    if robot not in ROBOTS:
        raise BagError(f"must be one of {', '.join(ROBOTS)}", path=path, field="robot")
    return TopicMap(
        str(data.get("name", path.stem)),
        path,
        sources,
        types,
        robot=robot,
        require_one_arm=bool(data.get("require_one_arm", False)),
    )


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


def typestore(store: Stores, tmap: TopicMap) -> Any:
    """A typestore of ``store`` with the map's custom types registered."""
    ts = get_typestore(store)
    for name, msg in tmap.types.items():
        try:
            ts.register(get_types_from_msg(msg.read_text(encoding="utf-8"), name))
        except Exception as err:  # rosbags raises several types for bad definitions
            raise BagError(f"cannot register {name}: {err}", path=msg) from err
    return ts


__all__ = [
    "ROBOTS",
    "STREAMS",
    "TOPIC_MAP_DIR",
    "BagError",
    "Source",
    "TopicMap",
    "load_topic_map",
    "normalize_msgtype",
    "typestore",
]
