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

One module per concept: :mod:`~bopsurg.generators.recording` (streams and interpolation),
:mod:`~bopsurg.generators.topic_map`, :mod:`~bopsurg.generators.bag_writer` and
:mod:`~bopsurg.generators.bag_reader`; this module is their public entry point.
"""

from __future__ import annotations

from bopsurg.generators.bag_reader import read_bag
from bopsurg.generators.bag_writer import BagFormat, write_bag
from bopsurg.generators.recording import DEFAULT_TIME_ORIGIN_NS, Recording
from bopsurg.generators.topic_map import TOPIC_MAP_DIR, BagError, Source, TopicMap, load_topic_map

__all__ = [
    "DEFAULT_TIME_ORIGIN_NS",
    "TOPIC_MAP_DIR",
    "BagError",
    "BagFormat",
    "Recording",
    "Source",
    "TopicMap",
    "load_topic_map",
    "read_bag",
    "write_bag",
]
