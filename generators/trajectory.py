"""Synthetic suturing episodes: two dVRK PSMs pass a curved needle through tissue.

:func:`synthesize_suturing` plays an operator through one or two *throws* of a running
suture and returns a :class:`~bopsurg.generators.recording.Recording` (joints of both PSMs, jaws,
ECM joints and the needle pose at a fixed rate), ready for
:func:`~bopsurg.generators.bags.write_bag`. Everything random comes from
``numpy.random.default_rng(seed)``: the same seed gives the same arrays.

The episode, in world coordinates (m; tissue surface z = 0, +Z up):

1. The needle rests flat on the tissue. PSM1 approaches with open jaws, closes them on the
   wire near the tail; from the moment its jaw closes to :data:`GRASP_JAW_THRESHOLD` the needle
   is rigidly attached: ``T_world_needle = T_world_tip @ T_tip_needle`` (the grasp offset).
2. PSM1 lifts the needle, turns its plane upright across the wound and puts the tip on the
   entry point, then *drives* it: the needle turns about its own arc centre axis, so the tip
   follows the circle down through the tissue and up at the exit point a chord away
   (in two or three pushes with short pauses).
3. PSM2 grasps the emerged tip side (hand-off: both hold, then PSM1 opens and retracts),
   pulls the needle through along its arc until the tail is out and lifts the thread.
4. With enough time (about 35 s or more), a second throw a few mm along the wound: PSM2
   presents the needle, PSM1 regrasps it near the tail, PSM2 lets go, and steps 2–3 repeat.

Operator realism: minimum-jerk segments (zero velocity and acceleration at both ends), a
speed factor per segment, random pauses, physiological tremor (8–12 Hz, 0.05–0.1 mm RMS) on
each moving tool tip, and small occasional endoscope (ECM) adjustments around its base pose.
Joints come from :func:`~bopsurg.generators.ik.psm_ik` (warm-started), so they always lie
within the PSM limits.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from bopsurg._version import __version__
from bopsurg.errors import InputError
from bopsurg.generators.backend import ARMS, DEFAULT_ECM_JOINTS
from bopsurg.generators.ik import psm_ik_solve
from bopsurg.generators.kinematics import (
    DEFAULT_LAYOUT,
    L_PITCH2YAW,
    L_RCC,
    L_TOOL,
    PSM_JOINT_LIMITS,
    SceneLayout,
    pose,
    psm_tip_pose,
    rot_z,
)
from bopsurg.generators.pybullet_scene import pad_height
from bopsurg.generators.recording import Recording
from bopsurg.needle import NeedleSpec, needle_centerline, needle_radius_profile

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: A jaw at or below this opening (rad) holds the needle (the AMBF simulator's rule).
GRASP_JAW_THRESHOLD = 0.2
#: Physiological tremor band (Hz) and RMS amplitude range (m).
TREMOR_HZ = (8.0, 12.0)
TREMOR_RMS = (0.05e-3, 0.1e-3)

#: Average speeds (at tempo 1) the operator does not exceed in one segment: translation (m/s)
#: and rotation (rad/s) of the moved tool or needle; longer moves take longer.
AVG_SPEED, AVG_SPIN = 0.025, 0.65
#: Range of the operator's tempo (duration factor) when fitting the plan into an episode.
MIN_TEMPO, MAX_TEMPO = 0.7, 1.3

_MM = 1e-3


def min_jerk(tau: F64) -> F64:
    """Minimum-jerk progress ``10τ³ − 15τ⁴ + 6τ⁵`` of ``tau`` clipped to [0, 1]."""
    s = np.clip(tau, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def _rotations(rotvecs: F64) -> F64:
    out: F64 = Rotation.from_rotvec(rotvecs).as_matrix().reshape(-1, 3, 3)
    return out


def _line(T_a: F64, T_b: F64) -> Callable[[F64], F64]:
    """Pose path from T_a to T_b: straight translation, slerp rotation."""
    rv = Rotation.from_matrix(T_a[:3, :3].T @ T_b[:3, :3]).as_rotvec()

    def path(s: F64) -> F64:
        out = np.zeros((len(s), 4, 4))
        out[:, :3, :3] = T_a[:3, :3] @ _rotations(s[:, None] * rv)
        out[:, :3, 3] = (1.0 - s)[:, None] * T_a[:3, 3] + s[:, None] * T_b[:3, 3]
        out[:, 3, 3] = 1.0
        return out

    return path


def _arc(T_a: F64, centre: F64, axis: F64, angle: float) -> Callable[[F64], F64]:
    """Pose path turning T_a by ``angle`` (rad) about ``axis`` through ``centre`` (world)."""

    def path(s: F64) -> F64:
        R = _rotations((s * angle)[:, None] * axis)
        out = np.zeros((len(s), 4, 4))
        out[:, :3, :3] = R @ T_a[:3, :3]
        out[:, :3, 3] = centre + (R @ (T_a[:3, 3] - centre)[:, None])[:, :, 0]
        out[:, 3, 3] = 1.0
        return out

    return path


def _lerp(a: F64, b: F64) -> Callable[[F64], F64]:
    return lambda s: a + s.reshape(-1, *([1] * a.ndim)) * (b - a)


@dataclass
class _Track:
    """A quantity over time: min-jerk segments, holding its value in between."""

    value: F64
    segments: list[tuple[float, float, Callable[[F64], F64]]] = field(default_factory=list)
    end_time: float = 0.0

    def __post_init__(self) -> None:
        self.initial = self.value.copy()

    def add(self, t0: float, t1: float, path: Callable[[F64], F64]) -> float:
        assert t0 >= self.end_time - 1e-9, "segments must not overlap"
        self.segments.append((t0, t1, path))
        self.value = path(np.ones(1))[0]
        self.end_time = t1
        return t1

    def evaluate(self, times: F64) -> F64:
        out = np.broadcast_to(self.initial, (len(times), *self.initial.shape)).copy()
        for t0, t1, path in self.segments:
            mask = times >= t0
            if not mask.any():
                continue
            tau = (times[mask] - t0) / (t1 - t0) if t1 > t0 else np.ones(mask.sum())
            out[mask] = path(min_jerk(tau))
        return out


@dataclass
class _Hold:
    """An arm holding the needle with grasp offset ``T_tn`` (= T_tip_needle) over a window."""

    arm: str
    T_tn: F64
    t_from: float  # the jaw starts closing
    t_to: float = math.inf  # the jaw has opened


def needle_grasp(
    needle: NeedleSpec,
    s_deg: float,
    *,
    approach: int,
    tilt_deg: float,
    depth_mm: float,
    flip: bool = False,
) -> F64:
    """Grasp offset ``T_tip_needle`` (m) of jaws closed on the wire at arc angle ``s_deg``.

    The jaws clamp the wire across them: the tip frame's x axis (the jaw hinge direction) runs
    along the wire, its z axis (along the jaws) crosses the needle plane. The tip frame's origin
    (the jaw pivot) sits ``depth_mm`` behind the wire along −z.

    Args:
        needle: Needle geometry (mm).
        s_deg: Arc angle of the grasp point from the tail, degrees.
        approach: −1: the jaws point along the needle's −Z (the arm is on its +Z side);
            +1: along +Z.
        tilt_deg: Tilt of the jaws towards the arc centre (negative: away from it), degrees.
        depth_mm: Wire to jaw pivot distance, mm.
        flip: Spin the jaws 180° about their axis (x runs against the arc's direction).

    Returns:
        (4, 4) pose of the needle model frame in the tip frame, m.
    """
    s, tilt = np.deg2rad(s_deg), np.deg2rad(tilt_deg)
    r = needle.arc_radius * _MM
    radial = np.array([np.cos(s), np.sin(s), 0.0])
    tangent = np.array([-np.sin(s), np.cos(s), 0.0])
    z = np.cos(tilt) * approach * np.array([0.0, 0.0, 1.0]) - np.sin(tilt) * radial
    x = -tangent if flip else tangent
    y = np.cross(z, x)
    T_needle_tip = pose(np.stack([x, y, z], axis=1), r * radial - depth_mm * _MM * z)
    return np.linalg.inv(T_needle_tip)


@dataclass(frozen=True)
class _Stitch:
    """One throw's geometry: the needle circle stands upright across the wound.

    Stitch frame: origin on the tissue midway between entry and exit, x̂ along the wound
    (towards PSM1), ŷ from entry to exit. Needle model axes at rotation φ: model x → ŷ turned
    by φ in the upright plane, model z → x̂; a model point at arc angle s sits at
    ψ = φ + s on the circle ``C + r (cos ψ ŷ + sin ψ ẑ)``.
    """

    origin: F64
    yaw: float
    radius: float
    bite: float  # arc below the tissue, rad

    @property
    def x(self) -> F64:
        axis: F64 = rot_z(self.yaw)[:, 0]
        return axis

    @property
    def y(self) -> F64:
        axis: F64 = rot_z(self.yaw)[:, 1]
        return axis

    @property
    def centre(self) -> F64:
        c: F64 = self.origin + np.array([0.0, 0.0, self.radius * np.cos(self.bite / 2)])
        return c

    @property
    def psi_entry(self) -> float:
        return 1.5 * np.pi - self.bite / 2

    @property
    def psi_exit(self) -> float:
        return 1.5 * np.pi + self.bite / 2

    def needle_pose(self, phi: float) -> F64:
        R_0 = np.stack([self.y, np.array([0.0, 0.0, 1.0]), self.x], axis=1)
        T: F64 = pose(R_0 @ rot_z(phi), self.centre)
        return T


def _translated(T: F64, d: ArrayLike) -> F64:
    out = T.copy()
    out[:3, 3] += np.asarray(d, dtype=np.float64)
    return out


class _Planner:
    """Writes the operator's plan as tracks, advancing a clock ``t`` (s)."""

    def __init__(
        self,
        rng: np.random.Generator,
        tempo: float,
        needle_rest: F64,
        tips: dict[str, F64],
        jaws: dict[str, float],
    ) -> None:
        self.rng = rng
        self.tempo = tempo
        self.t = 0.0
        self.needle = _Track(needle_rest)
        self.tips = {arm: _Track(T) for arm, T in tips.items()}
        self.jaws = {arm: _Track(np.array(v)) for arm, v in jaws.items()}
        self.idle = {arm: T.copy() for arm, T in tips.items()}
        self.idle_jaw = dict(jaws)
        self.holds: list[_Hold] = []
        self.events: list[dict[str, object]] = []

    def dur(self, nominal: float) -> float:
        """Duration of a segment: nominal × tempo × a speed factor of the moment."""
        return nominal * self.tempo * self.rng.uniform(0.8, 1.25)

    def pause(self, lo: float, hi: float, p: float = 1.0) -> None:
        if self.rng.random() < p:
            self.t += self.tempo * self.rng.uniform(lo, hi)

    def event(self, what: str, t0: float) -> None:
        self.events.append({"t0": round(float(t0), 4), "t1": round(float(self.t), 4), "what": what})

    def move_dur(self, nominal: float, T_a: F64, T_b: F64, angle: float | None = None) -> float:
        """Duration of a move between two poses: the nominal, longer for long moves."""
        if angle is None:
            rv = Rotation.from_matrix(T_a[:3, :3].T @ T_b[:3, :3]).as_rotvec()
            angle = float(np.linalg.norm(rv))
        dist = float(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3]))
        return self.dur(max(nominal, dist / AVG_SPEED, abs(angle) / AVG_SPIN))

    def tip_to(self, arm: str, T: F64, nominal: float, at: float | None = None) -> float:
        track = self.tips[arm]
        t0 = max(self.t if at is None else at, track.end_time)
        return track.add(t0, t0 + self.move_dur(nominal, track.value, T), _line(track.value, T))

    def jaw_to(self, arm: str, value: float, nominal: float, at: float | None = None) -> float:
        track = self.jaws[arm]
        t0 = max(self.t if at is None else at, track.end_time)
        return track.add(t0, t0 + self.dur(nominal), _lerp(track.value, np.array(value)))

    def needle_line(self, T: F64, nominal: float) -> None:
        T_a = self.needle.value
        self.t = self.needle.add(self.t, self.t + self.move_dur(nominal, T_a, T), _line(T_a, T))

    def needle_arc(self, centre: F64, axis: F64, angle: float, nominal: float) -> None:
        T_a = self.needle.value
        path = _arc(T_a, centre, axis, angle)
        duration = self.move_dur(nominal, T_a, path(np.ones(1))[0], angle)
        self.t = self.needle.add(self.t, self.t + duration, path)

    def grasp(self, arm: str, T_tn: F64, nominal: float = 0.4) -> None:
        """Close the jaw on the needle (the tip must already be at the grasp pose)."""
        self.holds.append(_Hold(arm, T_tn, self.t))
        self.t = self.jaw_to(arm, self.rng.uniform(0.02, 0.08), nominal)

    def release(self, arm: str, nominal: float = 0.4) -> None:
        """Open the jaw; the arm's own track takes over from where the needle had it."""
        hold = next(h for h in self.holds if h.arm == arm and h.t_to == math.inf)
        assert self.needle.end_time <= self.t + 1e-9
        T_release = self.needle.value @ np.linalg.inv(hold.T_tn)
        self.tips[arm].add(self.t, self.t, _line(T_release, T_release))
        self.t = self.jaw_to(arm, self.rng.uniform(0.6, 0.9), nominal)
        hold.t_to = self.t

    def retract(self, arm: str, back: float) -> None:
        """Back the open jaws off along their axis and up, then drift home (not waited for)."""
        T = self.tips[arm].value
        self.t = self.tip_to(arm, _translated(T, -back * T[:3, 2] + [0, 0, 0.4 * back]), 0.8)
        self.tip_to(arm, self.idle[arm], 1.6, at=self.t)
        self.jaw_to(arm, self.idle_jaw[arm], 0.6, at=self.t + 0.3)


def _start_joints(layout: SceneLayout, index: int, hover: F64, rng: np.random.Generator) -> F64:
    """Joints putting the (straight) wrist over ``hover`` (world, m), roll and wrist jittered."""
    p = (np.linalg.inv(layout.psm_base(index)) @ np.append(hover, 1.0))[:3]
    dist = float(np.linalg.norm(p))
    d = p / dist
    q = np.array(
        [
            np.arctan2(d[0], -d[2]),
            -np.arcsin(d[1]),
            dist + L_RCC - L_TOOL - L_PITCH2YAW,
            rng.uniform(-0.4, 0.4),
            rng.uniform(-0.3, 0.3),
            rng.uniform(-0.3, 0.3),
        ]
    )
    clipped: F64 = np.clip(q, PSM_JOINT_LIMITS[:, 0], PSM_JOINT_LIMITS[:, 1])
    return clipped


@dataclass
class _Throw:
    """The geometry of one throw, drawn before any timing (so flips can be checked)."""

    stitch: _Stitch
    phi_pre: float  # needle rotation with the tip just above the entry point, rad
    phi_end: float  # end of the drive: the tip side has emerged
    phi_pull: float  # end of the pull: the tail is out
    grasp1: tuple[float, float, float]  # PSM1 grasp: arc angle (deg), tilt (deg), depth (mm)
    grasp2: tuple[float, float, float]  # PSM2 grasp
    high: float  # height of the transport (throw 1) or presentation (throw 2) pose, m
    lift: F64  # thread-pulling lift after the pull, m
    backs: tuple[float, float, float, float]  # approach and retract distances, m
    jaw_open: tuple[float, float]  # jaw openings of PSM1 and PSM2 when approaching, rad

    @property
    def T_pre(self) -> F64:
        return self.stitch.needle_pose(self.phi_pre)

    @property
    def T_high(self) -> F64:
        return _translated(self.T_pre, [0.0, 0.0, self.high])


def _draw_throws(
    rng: np.random.Generator, centre: F64, needle: NeedleSpec, count: int
) -> list[_Throw]:
    r = needle.arc_radius * _MM
    arc = np.deg2rad(needle.total_deg)
    throws: list[_Throw] = []
    for k in range(count):
        if k == 0:
            origin = centre + np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), 0.0]) * _MM
            yaw = np.deg2rad(rng.uniform(-15.0, 15.0))
        else:  # the next stitch a few mm along the wound
            prev = throws[-1].stitch
            origin = prev.origin + rng.uniform(4.0, 6.0) * rng.choice([-1.0, 1.0]) * _MM * prev.x
            yaw = prev.yaw + np.deg2rad(rng.uniform(-5.0, 5.0))
        grasp1 = (rng.uniform(10.0, 16.0), -rng.uniform(5.0, 25.0), rng.uniform(5.5, 7.0))
        bite_max = arc - np.deg2rad(grasp1[0]) - np.deg2rad(25.0)
        if bite_max < np.deg2rad(40.0):
            raise InputError(
                f"needle arc {needle.total_deg:.0f} deg is too short to suture (needs >= 80 deg)",
                field="needle",
            )
        bite = min(np.deg2rad(rng.uniform(65.0, 80.0)), bite_max)
        stitch = _Stitch(origin, yaw, r, bite)
        # Arc still above the tissue behind the PSM1 jaws when the drive ends: half of it
        # emerges at the exit for PSM2, the rest keeps PSM1's jaws off the tissue.
        emerge = 0.5 * (arc - np.deg2rad(grasp1[0]) - bite)
        phi_end = stitch.psi_exit - arc + emerge
        grasp2 = (np.rad2deg(arc - 0.5 * emerge), -rng.uniform(15.0, 30.0), rng.uniform(5.5, 7.0))
        throws.append(
            _Throw(
                stitch=stitch,
                phi_pre=stitch.psi_entry - arc - np.deg2rad(rng.uniform(3.0, 6.0)),
                phi_end=phi_end,
                phi_pull=stitch.psi_exit + np.deg2rad(rng.uniform(15.0, 25.0)),
                grasp1=grasp1,
                grasp2=grasp2,
                high=rng.uniform(6.0, 12.0) * _MM,
                lift=(np.array([0.0, 0.0, rng.uniform(15, 25)]) - rng.uniform(5, 12) * stitch.x)
                * _MM,
                backs=tuple(rng.uniform(8.0, 12.0, 4) * _MM),
                jaw_open=(rng.uniform(0.6, 0.95), rng.uniform(0.6, 0.95)),
            )
        )
    return throws


def _densify(poses: list[F64], step_m: float = 0.004, step_rad: float = 0.15) -> list[F64]:
    """Poses with straight/slerp in-betweens, at most ``step_m`` and ``step_rad`` apart."""
    out = [poses[0]]
    for T_a, T_b in itertools.pairwise(poses):
        angle = np.linalg.norm(Rotation.from_matrix(T_a[:3, :3].T @ T_b[:3, :3]).as_rotvec())
        n = int(max(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3]) / step_m, angle / step_rad)) + 1
        out.extend(_line(T_a, T_b)(np.arange(1, n + 1) / n))
    return out


def _reach_score(base_inv: F64, q_home: F64, tip_poses: list[F64]) -> float:
    """How close to its limits an arm comes following ``tip_poses`` from ``q_home`` and back.

    Returns:
        The largest |joint| / limit of roll and wrist along the way, or ``inf`` when a pose
        is unreachable or a route that ends at home does not bring the joints back to
        ``q_home`` (the roll wound up).
    """
    q, worst = q_home, 0.0
    for T in _densify(tip_poses):
        res = psm_ik_solve(base_inv @ T, q, restarts=False)
        if not res.converged:
            return math.inf
        q = res.q
        worst = max(worst, float(np.max(np.abs(q[3:]) / PSM_JOINT_LIMITS[3:, 1])))
    if np.allclose(tip_poses[-1], tip_poses[0]) and not np.allclose(q, q_home, atol=1e-3):
        return math.inf
    return worst


def _pick_grasp(
    needle: NeedleSpec,
    params: tuple[float, float, float],
    approach: int,
    layout: SceneLayout,
    index: int,
    q_home: F64,
    route: Callable[[F64], list[F64]],
) -> F64:
    """The grasp offset whose whole route keeps the roll and wrist farthest from their limits.

    Tries the drawn grasp spun 0 and 180° about the jaw axis (the jaws are symmetric); when
    neither keeps the route reachable, other jaw tilts and grasp points nearby, the way an
    operator would regrip. ``route(T_tn)`` lists the tip poses of the arm from home, through the
    hold, and back home when it lets go.
    """
    base_inv = np.linalg.inv(layout.psm_base(index))
    best, best_score = None, math.inf
    s_deg, tilt, depth = params
    # Regrip away from the tail swage (PSM1) or towards the exit (PSM2), never off the body.
    shift = 6.0 if approach < 0 else -3.0
    for d_tilt, d_s in ((0, 0), (15, 0), (-15, 0), (0, 1), (30, 0), (-30, 0), (15, 1)):
        for flip in (False, True):
            T_tn = needle_grasp(
                needle,
                s_deg + d_s * shift,
                approach=approach,
                tilt_deg=tilt + d_tilt,
                depth_mm=depth,
                flip=flip,
            )
            score = _reach_score(base_inv, q_home, route(T_tn))
            if best is None or score < best_score:
                best, best_score = T_tn, score
        if math.isfinite(best_score):
            break
    else:
        log.warning("psm%d: no grasp keeps the whole route reachable", index + 1)
    assert best is not None
    return best


@dataclass
class _Episode:
    planner: _Planner
    start_q: dict[str, F64]
    throws: int


@dataclass
class _Setup:
    """The drawn geometry of an episode, before any timing.

    Attributes:
        start_q: Each arm's joints at the start (wrist hovering beside the wound).
        home: Each arm's tip pose at the start, where it returns to, world, m.
        idle_jaw: Each arm's jaw opening at rest, rad.
        throws: The throws, in order.
        T_rest: The needle lying flat on the tissue beside the wound.
        T_lifted: The needle just picked up, above ``T_rest``.
    """

    start_q: dict[str, F64]
    home: dict[str, F64]
    idle_jaw: dict[str, float]
    throws: list[_Throw]
    T_rest: F64
    T_lifted: F64


def _rest_height(R: F64, at: F64, needle: NeedleSpec) -> float:
    """Height (m) at which the needle, turned by ``R`` and placed at ``at`` (x, y), lies on the
    pad: lowered until its wire touches the surface (ridges, undulation; it bridges the
    incisions) and nowhere below it. At z = 0 a needle beside the wound sank up to 0.8 mm
    into a ridge over half its arc, and frames of it at rest were a tail with a speck of tip."""
    s = np.deg2rad(np.linspace(0.0, needle.total_deg, 64))
    pts, _ = needle_centerline(needle, s)
    world = (pts * _MM) @ R.T  # centre line relative to its origin, m
    x_mm, y_mm = 1e3 * (at[0] + world[:, 0]), 1e3 * (at[1] + world[:, 1])
    wire = needle_radius_profile(needle, np.rad2deg(s)) * _MM
    surface = pad_height(x_mm, y_mm) * _MM
    return float(np.max(surface + wire - world[:, 2]))


def _draw_setup(
    rng: np.random.Generator, layout: SceneLayout, needle: NeedleSpec, n_throws: int
) -> _Setup:
    """Everything geometric, drawn first and in a fixed order (timing draws come after)."""
    centre = np.asarray(layout.workspace_centre, dtype=np.float64)
    start_q, home = {}, {}
    for i, (arm, side) in enumerate(zip(ARMS, (1.0, -1.0), strict=True)):
        hover = centre + np.array([0.022 * side, -0.006, 0.028]) + rng.normal(0.0, 0.003, 3)
        start_q[arm] = _start_joints(layout, i, hover, rng)
        home[arm] = layout.psm_base(i) @ psm_tip_pose(start_q[arm])
    idle_jaw = {arm: float(rng.uniform(0.3, 0.5)) for arm in ARMS}
    throws = _draw_throws(rng, centre, needle, 2)[:n_throws]
    first = throws[0]
    # The needle at rest: flat on the tissue beside the wound (model +Z up).
    lay_flat = Rotation.from_rotvec(-np.pi / 2 * first.stitch.y).as_matrix()
    spin = rot_z(np.deg2rad(rng.uniform(-35.0, 35.0)))
    s = first.stitch
    rest_at = s.origin + (rng.uniform(4, 10) * s.x - rng.uniform(4, 10) * s.y) * _MM
    R_rest = spin @ lay_flat @ first.T_pre[:3, :3]
    rest_at[2] = _rest_height(R_rest, rest_at, needle)
    T_rest = pose(R_rest, rest_at)
    T_lifted = _translated(T_rest, [0.0, 0.0, rng.uniform(10, 15) * _MM])
    return _Setup(start_q, home, idle_jaw, throws, T_rest, T_lifted)


def _arc_poses(th: _Throw, a: float, b: float) -> list[F64]:
    return [th.stitch.needle_pose(phi) for phi in np.linspace(a, b, 12)]


def _lifted(th: _Throw) -> F64:
    """The needle after the pull, lifted to tighten the thread."""
    return _translated(th.stitch.needle_pose(th.phi_pull), th.lift)


def _tip(T_needle: F64, T_tn: F64) -> F64:
    """The tool tip holding the needle at ``T_needle`` with grasp offset ``T_tn``."""
    return T_needle @ np.linalg.inv(T_tn)


def _approach_route(T_tn: F64, T_needle: F64, back: float) -> list[F64]:
    T = _tip(T_needle, T_tn)
    return [_translated(T, -back * T[:3, 2]), T]


def _away_route(home: F64, T_tn: F64, T_needle: F64, back: float) -> list[F64]:
    T = _tip(T_needle, T_tn)
    return [T, _translated(T, -back * T[:3, 2] + [0, 0, 0.4 * back]), home]


def _hold_route(home: F64, T_tn: F64, needle_path: list[F64], back_in: float) -> list[F64]:
    """Tip poses from home, along a needle path held with ``T_tn`` (not the way back)."""
    poses = [home, *_approach_route(T_tn, needle_path[0], back_in)]
    return poses + [_tip(T, T_tn) for T in needle_path[1:]]


def _psm1_path(setup: _Setup, k: int) -> list[F64]:
    """The needle poses while PSM1 holds it in throw ``k`` (from pick-up or hand-back)."""
    th = setup.throws[k]
    start = [setup.T_rest, setup.T_lifted] if k == 0 else []
    return [*start, th.T_high, *_arc_poses(th, th.phi_pre, th.phi_end)]


def _psm2_path(setup: _Setup, k: int) -> list[F64]:
    """The needle poses while PSM2 holds it in throw ``k`` (pull, lift, next presentation)."""
    th = setup.throws[k]
    path = [*_arc_poses(th, th.phi_end, th.phi_pull), _lifted(th)]
    if k + 1 < len(setup.throws):
        path.append(setup.throws[k + 1].T_high)
    return path


def _grasp_offsets(
    setup: _Setup, layout: SceneLayout, needle: NeedleSpec, check_reach: bool
) -> tuple[list[F64], list[F64]]:
    """PSM1's and PSM2's grasp offsets per throw, spun so each hold's route stays reachable."""
    T_tn1: list[F64] = []
    T_tn2: list[F64] = []
    home1, home2 = setup.home["psm1"], setup.home["psm2"]
    for k, th in enumerate(setup.throws):
        if not check_reach:
            for T_tn, (s_deg, tilt, depth), approach in (
                (T_tn1, th.grasp1, -1),
                (T_tn2, th.grasp2, 1),
            ):
                T_tn.append(
                    needle_grasp(needle, s_deg, approach=approach, tilt_deg=tilt, depth_mm=depth)
                )
            continue
        path1, path2 = _psm1_path(setup, k), _psm2_path(setup, k)
        nxt = setup.throws[k + 1] if k + 1 < len(setup.throws) else None

        def route1(T_tn: F64, th: _Throw = th, path: list[F64] = path1) -> list[F64]:
            return [
                *_hold_route(home1, T_tn, path, th.backs[0]),
                *_away_route(home1, T_tn, path[-1], th.backs[1]),
            ]

        def route2(
            T_tn: F64, th: _Throw = th, path: list[F64] = path2, nxt: _Throw | None = nxt
        ) -> list[F64]:
            poses = _hold_route(home2, T_tn, path, th.backs[2])
            if nxt is not None:
                poses += _away_route(home2, T_tn, path[-1], nxt.backs[3])
            return poses

        T_tn1.append(_pick_grasp(needle, th.grasp1, -1, layout, 0, setup.start_q["psm1"], route1))
        T_tn2.append(_pick_grasp(needle, th.grasp2, 1, layout, 1, setup.start_q["psm2"], route2))
    return T_tn1, T_tn2


def _pick_up(P: _Planner, setup: _Setup, T_tn: F64) -> None:
    """PSM1 picks the needle up and brings it above the first entry point."""
    first = setup.throws[0]
    t0 = P.t
    T_grasp = _tip(setup.T_rest, T_tn)
    T_above = _translated(T_grasp, -first.backs[0] * T_grasp[:3, 2])
    t_end = P.tip_to("psm1", T_above, 2.0)
    P.jaw_to("psm1", first.jaw_open[0], 0.6, at=P.t + 0.3 * (t_end - P.t))
    P.t = t_end
    P.pause(0.2, 0.8, p=0.5)
    P.t = P.tip_to("psm1", T_grasp, 0.9)
    P.pause(0.1, 0.3)
    P.grasp("psm1", T_tn)
    P.event("psm1 grasps the needle", t0)
    P.pause(0.15, 0.4)
    t0 = P.t
    P.needle_line(setup.T_lifted, 0.8)
    P.needle_line(first.T_high, 2.0)
    P.event("psm1 brings the needle to the entry point", t0)


def _hand_back(P: _Planner, th: _Throw, T_tn: F64) -> None:
    """PSM2 presents the needle above the next entry point, PSM1 takes it, PSM2 retracts."""
    t0 = P.t
    T_grasp = _tip(th.T_high, T_tn)
    T_above = _translated(T_grasp, -th.backs[0] * T_grasp[:3, 2])
    t_end = P.tip_to("psm1", T_above, 1.5, at=t0 + 0.3 * P.tempo)  # meanwhile
    P.needle_line(th.T_high, 2.0)
    P.jaw_to("psm1", th.jaw_open[0], 0.5, at=t_end - 0.6 * P.tempo)
    P.t = max(P.t, t_end)
    P.t = P.tip_to("psm1", T_grasp, 0.7)
    P.grasp("psm1", T_tn)
    P.pause(0.2, 0.5)
    P.release("psm2")
    P.event("hand-back: psm2 gives the needle to psm1", t0)
    P.retract("psm2", th.backs[3])


def _drive(P: _Planner, th: _Throw, k: int) -> float:
    """PSM1 turns the needle about its arc centre axis, in a few pushes; returns the last
    push's start time."""
    t0 = P.t
    P.pause(0.1, 0.6, p=0.6)
    P.needle_line(th.T_pre, 0.8)
    P.pause(0.2, 0.6)
    total = th.phi_end - th.phi_pre
    pushes = P.rng.dirichlet([3.0] * int(P.rng.integers(2, 4))) * total
    t_last = P.t
    for j, angle in enumerate(pushes):
        t_last = P.t
        P.needle_arc(th.stitch.centre, th.stitch.x, angle, 3.2 * angle / total)
        if j < len(pushes) - 1:
            P.pause(0.1, 0.4)
    P.event(f"throw {k + 1}: psm1 drives the needle through the tissue", t0)
    return t_last


def _hand_off(P: _Planner, th: _Throw, T_tn: F64, t_last: float, k: int) -> None:
    """PSM2 grasps the emerged tip side (moving in during the last push), PSM1 lets go."""
    t0 = P.t
    T_grasp = _tip(th.stitch.needle_pose(th.phi_end), T_tn)
    T_near = _translated(T_grasp, -th.backs[2] * T_grasp[:3, 2])
    t_end = P.tip_to("psm2", T_near, 2.0, at=max(t_last, P.t - 2.0 * P.tempo))
    P.jaw_to("psm2", th.jaw_open[1], 0.5, at=t_end - 0.6 * P.tempo)
    P.t = max(P.t, t_end)
    P.pause(0.1, 0.5, p=0.5)
    P.t = P.tip_to("psm2", T_grasp, 0.7)
    P.grasp("psm2", T_tn)
    P.pause(0.2, 0.5)
    P.release("psm1")
    P.event(f"throw {k + 1}: hand-off from psm1 to psm2", t0)
    P.retract("psm1", th.backs[1])


def _pull_through(P: _Planner, th: _Throw, k: int) -> None:
    """PSM2 pulls along the arc until the tail is out, then lifts the thread."""
    t0 = P.t
    P.pause(0.1, 0.3)
    P.needle_arc(th.stitch.centre, th.stitch.x, th.phi_pull - th.phi_end, 2.5)
    P.needle_line(_lifted(th), 1.5)
    P.event(f"throw {k + 1}: psm2 pulls the needle through", t0)
    P.pause(0.2, 0.8)


def _plan_episode(
    seed: int,
    n_throws: int,
    tempo: float,
    layout: SceneLayout,
    needle: NeedleSpec,
    *,
    check_reach: bool = True,
) -> _Episode:
    """The operator's plan. The random draws do not depend on ``tempo`` or ``n_throws``."""
    rng = np.random.default_rng(seed).spawn(3)[0]
    setup = _draw_setup(rng, layout, needle, n_throws)
    T_tn1, T_tn2 = _grasp_offsets(setup, layout, needle, check_reach)
    # Timing: segment durations and pauses are drawn from here on.
    P = _Planner(rng, tempo, setup.T_rest, setup.home, setup.idle_jaw)
    P.pause(0.5, 1.5)
    _pick_up(P, setup, T_tn1[0])
    for k, th in enumerate(setup.throws):
        if k > 0:
            _hand_back(P, th, T_tn1[k])
        t_last = _drive(P, th, k)
        _hand_off(P, th, T_tn2[k], t_last, k)
        _pull_through(P, th, k)
    return _Episode(P, setup.start_q, n_throws)


def _tremor(rng: np.random.Generator, times: F64) -> F64:
    """Physiological tremor (N, 3), m: a few 8–12 Hz sines per axis, slowly modulated."""
    rms = rng.uniform(*TREMOR_RMS)
    out = np.zeros((len(times), 3))
    for axis in range(3):
        f = rng.uniform(*TREMOR_HZ, size=3)
        w = rng.uniform(0.5, 1.0, size=3)
        ph = rng.uniform(0.0, 2 * np.pi, size=3)
        w *= (rms / np.sqrt(3.0)) / np.sqrt(0.5 * np.sum(w**2))
        out[:, axis] = np.sin(2 * np.pi * f[None, :] * times[:, None] + ph) @ w
    envelope = 1.0 + 0.3 * np.sin(2 * np.pi * rng.uniform(0.1, 0.3) * times + rng.uniform(0, 6.3))
    return out * envelope[:, None]


def _ecm_track(rng: np.random.Generator, duration: float) -> _Track:
    """ECM joints: the base pose, adjusted by the operator now and then (0–2 times)."""
    base = DEFAULT_ECM_JOINTS + rng.uniform(-1, 1, 4) * np.array([0.02, 0.02, 0.002, 0.03])
    track = _Track(base)
    n = int(rng.integers(0, 3))
    starts = np.sort(rng.uniform(0.1, 0.85, n)) * duration
    for t0 in starts:
        target = base + rng.uniform(-1, 1, 4) * np.array([0.04, 0.04, 0.003, 0.05])
        t0 = max(float(t0), track.end_time)
        track.add(t0, t0 + rng.uniform(1.0, 1.5), _lerp(track.value, target))
    return track


def synthesize_suturing(
    seed: int,
    duration: float = 30.0,
    rate_hz: float = 50.0,
    layout: SceneLayout = DEFAULT_LAYOUT,
    needle: NeedleSpec | None = None,
) -> Recording:
    """A seeded, realistic suturing episode of two PSMs and a needle (see the module doc).

    Two throws are planned when they fit in ``duration`` at a plausible speed, else one; the
    operator's tempo is scaled (0.7–1.3×, down to 0.3× for very short episodes) so the plan
    ends before ``duration``, and the remaining time is spent holding (with tremor).

    Args:
        seed: Seed of every random choice.
        duration: Episode length, s.
        rate_hz: Sample rate, Hz; samples at ``i / rate_hz`` for ``i = 0 .. duration·rate``.
        layout: Where the robots and the tissue are.
        needle: Needle geometry (default: the paper's needle, :class:`NeedleSpec`).

    Returns:
        The recording; ``meta`` holds the seed, generator, version, layout, needle spec,
        rate, number of throws, task events and grasp windows.

    Raises:
        InputError: Non-positive duration or rate, or a needle too short to suture.
    """
    needle = needle or NeedleSpec()
    if not (math.isfinite(duration) and duration > 0.0):
        raise InputError(f"duration must be positive, got {duration}", field="duration")
    if not (math.isfinite(rate_hz) and rate_hz > 0.0):
        raise InputError(f"rate must be positive, got {rate_hz}", field="rate_hz")
    n = math.floor(duration * rate_hz + 1e-9) + 1
    times = np.arange(n) / rate_hz
    room = max(duration - 0.5, 0.5 * duration)

    # Nominal lengths first (no reach checks: they do not change the timing draws).
    full = _plan_episode(seed, 2, 1.0, layout, needle, check_reach=False).planner.t
    if full * MIN_TEMPO <= room:
        throws, tempo = 2, min(room / full, MAX_TEMPO)
    else:
        one = _plan_episode(seed, 1, 1.0, layout, needle, check_reach=False).planner.t
        throws, tempo = 1, float(np.clip(room / one, 0.3, MAX_TEMPO))
    episode = _plan_episode(seed, throws, tempo, layout, needle)
    rec = _realise(episode, times, seed, layout)
    rec.meta.update(
        {
            "seed": int(seed),
            "generator": "bopsurg.generators.trajectory.synthesize_suturing",
            "version": __version__,
            "duration": float(duration),
            "rate_hz": float(rate_hz),
            "throws": throws,
            "tempo": round(float(tempo), 4),
            "layout": asdict(layout),
            "needle": asdict(needle),
            "events": episode.planner.events,
        }
    )
    rec.source = f"synthesize_suturing(seed={seed})"
    return rec


def _realise(episode: _Episode, times: F64, seed: int, layout: SceneLayout) -> Recording:
    """Sample the plan: tremor, IK for each arm, the needle attached to its holder."""
    P = episode.planner
    _, tremor_rng, ecm_rng = np.random.default_rng(seed).spawn(3)
    tremor = {arm: _tremor(tremor_rng, times) for arm in ARMS}
    ecm = _ecm_track(ecm_rng, float(times[-1]))
    needle_plan = P.needle.evaluate(times)
    tip_plan = {arm: P.tips[arm].evaluate(times) for arm in ARMS}
    jaw = {arm: P.jaws[arm].evaluate(times) for arm in ARMS}
    base = {arm: layout.psm_base(i) for i, arm in enumerate(ARMS)}
    base_inv = {arm: np.linalg.inv(T) for arm, T in base.items()}

    # Which hold (if any) is active at each sample: inside its window, jaw closed enough.
    holding: dict[str, list[_Hold | None]] = {arm: [None] * len(times) for arm in ARMS}
    for h in P.holds:
        win = (times >= h.t_from) & (times <= h.t_to) & (jaw[h.arm] <= GRASP_JAW_THRESHOLD)
        for j in np.flatnonzero(win):
            holding[h.arm][int(j)] = h

    q = {arm: np.empty((len(times), 6)) for arm in ARMS}
    needle = np.empty((len(times), 4, 4))
    prev = dict(episode.start_q)
    failures = 0

    def solve(arm: str, i: int, T_world_tip: F64) -> F64:
        nonlocal failures
        T = base_inv[arm] @ T_world_tip
        res = psm_ik_solve(T, prev[arm], restarts=False)
        if not res.converged:
            res = psm_ik_solve(T, prev[arm])
        if not res.converged:
            failures += 1
            log.warning("IK: %s at t=%.3f s misses by %.3g mm", arm, times[i], res.pos_err_mm)
        prev[arm] = q[arm][i] = res.q
        tip: F64 = base[arm] @ psm_tip_pose(res.q)
        return tip

    for i in range(len(times)):
        active = [h for h in (holding[arm][i] for arm in ARMS) if h is not None]
        leader = min(active, key=lambda h: h.t_from) if active else None
        if leader is not None:
            target = needle_plan[i] @ np.linalg.inv(leader.T_tn)
            target[:3, 3] += tremor[leader.arm][i]
            needle[i] = solve(leader.arm, i, target) @ leader.T_tn
        else:
            needle[i] = needle_plan[i]
        for arm in ARMS:
            if leader is not None and arm == leader.arm:
                continue
            hold = holding[arm][i]
            if hold is not None:  # a second holder follows the needle exactly
                solve(arm, i, needle[i] @ np.linalg.inv(hold.T_tn))
            else:
                target = tip_plan[arm][i].copy()
                target[:3, 3] += tremor[arm][i]
                solve(arm, i, target)

    grasps = [
        {
            "arm": h.arm,
            "t_from": round(float(h.t_from), 4),
            "t_to": round(float(min(h.t_to, 1e9)), 4),
        }
        for h in P.holds
    ]
    return Recording(
        psm_joints={arm: (times, q[arm]) for arm in ARMS},
        jaws={arm: (times, jaw[arm]) for arm in ARMS},
        ecm_joints=(times, ecm.evaluate(times)),
        needle_pose=(times, needle),
        meta={"grasps": grasps, "ik_failures": failures},
    )
