"""Randomised endoscope viewpoints and lighting, one draw per replay.

The paper replays every recording from 20 ECM poses (``scripts/generate_dataset.py`` of
jabarragann/6d_pose_collection_scripts), each perturbed by a uniform offset. The base list is
theirs; bopsurg also varies the lighting, which the original's released code does not.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.generators.backend import LightSpec

F64 = NDArray[np.float64]

#: ECM base poses (yaw rad, pitch rad, insertion m, roll rad) of the paper's 20 replays.
ECM_BASE_POSES: tuple[tuple[float, float, float, float], ...] = (
    (0.0, 0.0, 0.0, 0.0),
    (0.0, 0.05, -0.01, 0.0),
    (0.0, 0.05, -0.01, 0.4),
    (0.0, 0.05, -0.01, -0.4),
    (0.2, 0.05, -0.01, 0.0),
    (-0.2, 0.05, -0.01, 0.0),
    (0.0, 0.15, -0.01, 0.0),
    (0.0, -0.05, -0.01, 0.0),
    (0.0, 0.05, -0.05, 0.0),
    (0.0, 0.05, 0.03, 0.0),
    (0.1, 0.05, -0.01, 0.2),
    (-0.1, 0.05, -0.01, -0.2),
    (0.1, 0.10, -0.01, 0.0),
    (-0.1, 0.0, -0.01, 0.0),
    (0.0, 0.10, -0.01, 0.3),
    (0.0, 0.0, -0.01, 0.3),
    (0.1, 0.10, -0.01, 0.1),
    (-0.1, 0.0, -0.01, -0.1),
    (0.1, 0.10, -0.04, -0.1),
    (-0.1, 0.0, 0.02, 0.1),
)


@dataclass(frozen=True)
class ViewpointRanges:
    """Half-widths of the uniform offsets added to a base pose, and the lighting ranges."""

    yaw: float = 0.15
    pitch: float = 0.15
    insertion: float = 0.010
    roll: float = 0.15
    light_cone_deg: float = 35.0
    ambient: tuple[float, float] = (0.35, 0.75)
    diffuse: tuple[float, float] = (0.3, 0.8)
    specular: tuple[float, float] = (0.05, 0.6)
    color_temperature: tuple[float, float] = (0.85, 1.0)


@dataclass(frozen=True)
class ReplayDraw:
    """The random choices of one replay, recorded in the dataset.

    Attributes:
        base_index: Index into :data:`ECM_BASE_POSES`.
        ecm_joints: (4,) the drawn ECM joints.
        light: The drawn lighting (directions in the camera frame, see :func:`light_in_world`).
    """

    base_index: int
    ecm_joints: tuple[float, float, float, float]
    light_direction_cam: tuple[float, float, float]
    light_color: tuple[float, float, float]
    ambient: float
    diffuse: float
    specular: float

    def to_json(self) -> dict[str, Any]:
        """JSON-ready form."""
        return asdict(self)


def draw_replay(
    rng: np.random.Generator, replay_index: int, ranges: ViewpointRanges | None = None
) -> ReplayDraw:
    """Draw the viewpoint and lighting of replay ``replay_index`` (base pose cycles)."""
    r = ranges or ViewpointRanges()
    base_index = replay_index % len(ECM_BASE_POSES)
    base = np.asarray(ECM_BASE_POSES[base_index])
    offset = rng.uniform(-1.0, 1.0, 4) * np.array([r.yaw, r.pitch, r.insertion, r.roll])
    joints = base + offset
    # A light near the endoscope's axis, as a head light: a direction inside a cone around
    # the camera's -z (towards the camera), given in camera axes.
    cone = np.deg2rad(r.light_cone_deg)
    polar = np.arccos(rng.uniform(np.cos(cone), 1.0))
    azimuth = rng.uniform(0.0, 2 * np.pi)
    d = np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), -np.cos(polar)])
    warm = rng.uniform(*r.color_temperature)
    color = np.array([1.0, 0.5 * (1.0 + warm), warm])  # from warm (halogen) to neutral white
    return ReplayDraw(
        base_index=base_index,
        ecm_joints=(float(joints[0]), float(joints[1]), float(joints[2]), float(joints[3])),
        light_direction_cam=(float(d[0]), float(d[1]), float(d[2])),
        light_color=(float(color[0]), float(color[1]), float(color[2])),
        ambient=float(rng.uniform(*r.ambient)),
        diffuse=float(rng.uniform(*r.diffuse)),
        specular=float(rng.uniform(*r.specular)),
    )


def light_in_world(draw: ReplayDraw, T_world_cam: F64) -> LightSpec:
    """The drawn lighting with its direction turned from camera into world axes."""
    d = T_world_cam[:3, :3] @ np.asarray(draw.light_direction_cam)
    return LightSpec(
        direction=d,
        color=np.asarray(draw.light_color),
        ambient=draw.ambient,
        diffuse=draw.diffuse,
        specular=draw.specular,
    )
