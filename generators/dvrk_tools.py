"""The dVRK's own PSM kinematics: the arm's three outer joints and each tool's wrist.

Every number here is copied from jhu-dvrk/sawIntuitiveResearchKit at commit
9e535e68eb7ff276d0516142bde82474fe9dc4bf (2026-04-17; the files last changed in
0fcfe532c080c1356fd43360bb3b42b0d742a614):

* the arm, ``share/kinematic/PSM.json`` (the classic PSM): outer yaw (alpha 1.5708, offset
  1.5708, limits ±1.588), outer pitch (alpha −1.5708, offset −1.5708, limits ±0.925025),
  insertion (prismatic, alpha 1.5708, offset −0.4318, limits [0, 0.24] m);
* each tool, ``share/tool/<NAME>.json``: roll (D = the shaft length), wrist pitch (alpha
  −1.5708, offset −1.5708), wrist yaw (alpha −1.5708, A = pitch-to-yaw length, offset
  −1.5708), their limits, the jaw limits, and ``tooltip_offset`` (the same rotation for
  every tool here, zero translation).

The files write π/2 as 1.5708; it is kept as written, so the forward kinematics is the
controller's (``measured_cp``) to the bit of its own arithmetic, not the ideal chain's.
Only tools with the one-pitch, one-yaw wrist of the needle drivers are listed (the 5 mm
snake-wrist tools have more joints).
"""

from __future__ import annotations

from bopsurg.errors import InputError
from bopsurg.generators.kinematics import DhJoint, PsmKinematics

_REPO = "jhu-dvrk/sawIntuitiveResearchKit@9e535e68eb7ff276d0516142bde82474fe9dc4bf"

#: share/kinematic/PSM.json: outer yaw, outer pitch, insertion, and their limits.
_ARM_JOINTS = (
    DhJoint(1.5708, 0.0, 0.0, 0.0, 1.5708),
    DhJoint(-1.5708, 0.0, 0.0, 0.0, -1.5708),
    DhJoint(1.5708, 0.0, 0.0, 0.0, -0.4318, prismatic=True),
)
_ARM_LIMITS = ((-1.588, 1.588), (-0.925025, 0.925025), (0.0, 0.24))

#: share/tool/*.json "tooltip_offset" (identical for every tool below).
_TOOLTIP_OFFSET = (
    (0.0, -1.0, 0.0, 0.0),
    (0.0, 0.0, 1.0, 0.0),
    (-1.0, 0.0, 0.0, 0.0),
    (0.0, 0.0, 0.0, 1.0),
)

# name: (roll D m, wrist yaw A m, roll limit, wrist pitch limit, wrist yaw limit,
#        jaw (qmin, qmax)), from share/tool/<name>.json.
_TOOLS: dict[str, tuple[float, float, float, float, float, tuple[float, float]]] = {
    "LARGE_NEEDLE_DRIVER_400006": (0.4162, 0.0091, 4.53786, 1.39626, 1.39626, (-0.698132, 1.39626)),
    "LARGE_NEEDLE_DRIVER_420006": (0.4670, 0.0091, 4.53786, 1.39626, 1.39626, (-0.349066, 1.39626)),
    "MEGA_NEEDLE_DRIVER_400194": (0.4162, 0.0112, 4.4506, 1.2217, 1.39626, (-0.349066, 1.39626)),
    "PROGRASP_FORCEPS_400093": (0.4162, 0.0107, 4.53786, 1.39626, 1.39626, (-0.349066, 1.39626)),
    "DEBAKEY_FORCEPS_400036": (0.4162, 0.0091, 4.53786, 1.39626, 1.39626, (-0.349066, 1.39626)),
    "CADIERE_FORCEPS_400049": (0.4162, 0.0091, 4.53786, 1.39626, 1.39626, (-0.349066, 1.39626)),
}

#: The tool a real recording is replayed with unless ``generate --psm-tool`` says otherwise.
DEFAULT_TOOL = "LARGE_NEEDLE_DRIVER_400006"

#: The tools known by name.
TOOL_NAMES = tuple(_TOOLS)


def dvrk_psm(tool: str = DEFAULT_TOOL) -> PsmKinematics:
    """The classic dVRK PSM carrying ``tool`` (a name of :data:`TOOL_NAMES`, any case).

    Raises:
        InputError: An unknown tool (one line listing the known ones).
    """
    key = tool.strip().upper()
    if key not in _TOOLS:
        raise InputError(
            f"unknown dVRK tool {tool!r}; known: {', '.join(TOOL_NAMES)}", field="--psm-tool"
        )
    shaft, pitch2yaw, roll, pitch, yaw, jaw = _TOOLS[key]
    joints = (
        *_ARM_JOINTS,
        DhJoint(0.0, 0.0, 0.0, shaft),
        DhJoint(-1.5708, 0.0, 0.0, 0.0, -1.5708),
        DhJoint(-1.5708, pitch2yaw, 0.0, 0.0, -1.5708),
    )
    return PsmKinematics(
        name=key,
        joints=joints,
        tip_offset=_TOOLTIP_OFFSET,
        joint_limits=(*_ARM_LIMITS, (-roll, roll), (-pitch, pitch), (-yaw, yaw)),
        jaw_limits=jaw,
        source=f"{_REPO} share/kinematic/PSM.json + share/tool/{key}.json",
    )


__all__ = ["DEFAULT_TOOL", "TOOL_NAMES", "dvrk_psm"]
