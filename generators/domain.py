"""Domain randomisation profiles of ``bopsurg generate --domain``: what a replay may look like.

A *profile* names how far each replay's random draw reaches. ``paper`` (the default) is the
draw of :func:`~bopsurg.generators.viewpoints.draw_replay` alone, byte for byte what
``generate`` always wrote. ``wide`` continues the **same** seeded stream of the replay
(``SeedSequence([seed, bag, replay])``) and also draws, per replay:

- a camera-to-needle distance, 20–120 mm: the endoscope keeps its drawn orientation and is
  moved (:func:`dolly_offset`) so that the needle's median position over the replay sits at
  that depth on the same pixel; or, on half the replays, the endoscope is placed around the
  needle instead (:class:`OrbitDraw`, :func:`orbit_offset`): any direction 10–70° above the
  tissue, any roll about its axis, the needle a little off the image centre, at the drawn
  depth. The ECM's 20 base poses see the upright needle of the episodes nearly edge-on and
  from one side; the orbit shows its faces, tilted either way, at every image orientation;
- a light set-up (:data:`LIGHT_SETUPS`: headlight, oblique, bright, dim), i.e. the ranges the
  usual light draw uses;
- the look (:class:`Appearance`): phantom surface (procedural tissue of one of several seeds,
  or flat plastic) and colour, background, a specular steel needle, grey/black instruments;
  on half the replays suture targets painted beside the incisions (:class:`MarksDraw`:
  squares, diamonds or dots of one colour, as training pads and the AMBF phantom have); on
  half the pad's shape (``Appearance.phantom_shape``): a groove its whole length between two
  lips, as the AMBF phantom has, instead of three incisions;
- instruments shaped closer to the Large Needle Driver (:func:`profile_scene`; per dataset,
  not drawn, since with ``--annotate-instruments`` they are BOP objects);
- a suture thread (:class:`ThreadDraw`) hanging from the needle's tail: a thin dark tube,
  simulated per frame (:class:`SutureThread`, position-based dynamics) so that it trails the
  tail with lag, drapes on the tissue and sways; it is scene geometry, so it occludes the
  needle, and it is no annotated object, so the needle's masks treat it as an occluder.

Everything drawn is written into the scene's ``bopsurg_scene.json`` (``domain``); the profile
name into the split's ``bopsurg_generate.json`` (``settings.domain``, absent for ``paper``).

A backend takes part through :class:`DomainBackend` (``set_appearance``, ``set_thread``),
which the PyBullet backend implements; ``--domain paper`` needs neither.

Units: scene positions in metres (world frame, +Z up, tissue top at z = 0), sizes of the
thread and distances in mm where the name says so.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from bopsurg.bop.meshes import ObjectModel
from bopsurg.errors import InputError
from bopsurg.generators.backend import NEEDLE, RenderBackend, SceneSpec
from bopsurg.generators.kinematics import look_rotation, pose, rot_z
from bopsurg.generators.pybullet_scene import MARK_SHAPES, PAD_SIZE, PAD_THICKNESS, pad_height
from bopsurg.generators.viewpoints import ReplayDraw, ViewpointRanges, draw_replay
from bopsurg.needle import fit_needle

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Profile names (``bopsurg generate --domain``); the first is the default.
DOMAINS = ("paper", "wide")
DEFAULT_DOMAIN = "paper"
#: Revision of each non-default profile's draw, recorded with the settings
#: (``settings.domain_revision``): a split drawn by an older revision is not resumed by a
#: newer one (its finished replays would look different from the rest).
DOMAIN_REVISIONS = {"wide": 4}  # 2: suture targets; 3: the orbiting endoscope; 4: the groove

#: Camera-to-needle distance range of ``wide``, mm (the needle's median depth per replay).
WIDE_DISTANCE_MM = (20.0, 120.0)

#: Light set-ups of ``wide``: the ranges of the light draw of
#: :func:`~bopsurg.generators.viewpoints.draw_replay` (the ECM offsets stay the paper's).
LIGHT_SETUPS: dict[str, ViewpointRanges] = {
    # the endoscope's own light, close to the optical axis
    "headlight": ViewpointRanges(
        light_cone_deg=15.0, ambient=(0.3, 0.6), diffuse=(0.5, 0.9), specular=(0.3, 0.9)
    ),
    # a light well off the axis: strong shading across the tissue's relief
    "oblique": ViewpointRanges(
        light_cone_deg=70.0, ambient=(0.2, 0.5), diffuse=(0.5, 1.0), specular=(0.2, 0.8)
    ),
    # flat, bright theatre light
    "bright": ViewpointRanges(
        light_cone_deg=35.0, ambient=(0.6, 0.9), diffuse=(0.3, 0.6), specular=(0.1, 0.5)
    ),
    # dim scene, strong highlights
    "dim": ViewpointRanges(
        light_cone_deg=35.0,
        ambient=(0.12, 0.3),
        diffuse=(0.4, 0.8),
        specular=(0.6, 1.0),
        color_temperature=(0.7, 1.0),
    ),
}

#: Phantom colours: RGB multipliers (≤ 1: TinyRenderer wraps brighter values around) of the
#: surface texture: the tissue pink of the default, the AMBF simulator's magenta phantom, red,
#: beige silicone, pale yellow.
PHANTOM_TINTS: dict[str, tuple[float, float, float]] = {
    "pink": (1.0, 1.0, 1.0),
    "magenta": (0.9, 0.45, 0.85),
    "red": (1.0, 0.62, 0.6),
    "beige": (1.0, 0.92, 0.8),
    "yellow": (1.0, 0.95, 0.62),
}
#: Phantom surfaces: procedural tissue (vessels, incisions) or flat plastic.
PHANTOM_SURFACES = ("tissue", "flat")
#: Backgrounds: RGB multipliers (≤ 1) of the drape texture: black (the AMBF scene's), the
#: blue-green drape of the default, dark grey, dark blue.
BACKGROUNDS: dict[str, tuple[float, float, float]] = {
    "black": (0.12, 0.12, 0.12),
    "drape": (1.0, 1.0, 1.0),
    "grey": (1.0, 0.43, 0.38),
    "blue": (0.5, 0.5, 1.0),
}
#: Suture colours (RGB): black silk, violet polyglactin, blue polypropylene, dark green.
THREAD_COLOURS: dict[str, tuple[float, float, float]] = {
    "black": (0.03, 0.03, 0.035),
    "violet": (0.22, 0.08, 0.3),
    "blue": (0.06, 0.09, 0.3),
    "green": (0.05, 0.16, 0.08),
}
#: Suture target colours (RGB): red (the AMBF phantom's), dark red, black, blue, green.
MARK_COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (0.85, 0.07, 0.08),
    "dark_red": (0.5, 0.04, 0.06),
    "black": (0.05, 0.05, 0.06),
    "blue": (0.08, 0.15, 0.6),
    "green": (0.1, 0.45, 0.15),
}
#: Share of ``wide`` replays whose phantom carries suture targets.
MARKS_SHARE = 0.5
#: Share of ``wide`` replays whose endoscope orbits the needle (:class:`OrbitDraw`).
ORBIT_SHARE = 0.5
#: Share of ``wide`` replays whose pad is the ``groove`` pad (one crease the pad's length
#: between two lips, as the AMBF simulator's phantom has) instead of the incised one.
GROOVE_SHARE = 0.5
#: Elevation of an orbiting endoscope above the tissue plane, seen from the needle, degrees.
ORBIT_ELEVATION_DEG = (10.0, 70.0)
#: Largest angle of the needle from the optical axis, across and down the image, degrees.
ORBIT_OFF_AXIS_DEG = 15.0


@dataclass(frozen=True)
class MarksDraw:
    """Suture targets painted on the phantom (see
    :func:`~bopsurg.generators.pybullet_scene.paint_marks`); sizes in mm.

    Attributes:
        shape: One of :data:`~bopsurg.generators.pybullet_scene.MARK_SHAPES`.
        colour: Key of :data:`MARK_COLOURS`.
        size_mm: Side or diameter, mm.
        spacing_mm: Distance between neighbouring targets along an incision, mm.
        offset_mm: Distance of a target from the incision's centre line, mm.
    """

    shape: str
    colour: str
    size_mm: float
    spacing_mm: float
    offset_mm: float


@dataclass(frozen=True)
class OrbitDraw:
    """An endoscope placed around the needle instead of at its ECM pose (see
    :func:`orbit_offset`); angles in degrees.

    Attributes:
        elevation_deg: Angle above the tissue plane (world XY) of the line from the needle's
            median position to the camera.
        azimuth_deg: That line's direction about world +Z (0: world +X).
        roll_deg: The image's rotation about the optical axis (0: world +Z is image up).
        off_x_deg, off_y_deg: The needle's direction from the optical axis before the roll,
            along image x and y.
    """

    elevation_deg: float
    azimuth_deg: float
    roll_deg: float
    off_x_deg: float
    off_y_deg: float


@dataclass(frozen=True)
class Appearance:
    """Materials of one replay (RGBA in [0, 1]).

    Attributes:
        phantom_surface: ``tissue`` (procedural texture of seed ``phantom_texture_seed``) or
            ``flat`` (plain plastic).
        phantom_texture_seed: Seed of the tissue texture.
        phantom_rgba: Multiplier of the phantom's texture.
        background_rgba: Multiplier of the drape's texture.
        needle_rgba, needle_specular: The needle's colour and specular colour.
        shaft_rgba, metal_rgba, jaw_rgba: Instrument shaft, wrist/hub and jaw colours.
        phantom_marks: Suture targets painted on the phantom, or None.
        phantom_shape: The pad's geometry (:data:`~.pybullet_scene.PAD_SHAPES`).
    """

    phantom_surface: str = "tissue"
    phantom_texture_seed: int = 0
    phantom_rgba: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    background_rgba: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    needle_rgba: tuple[float, float, float, float] = (0.78, 0.78, 0.80, 1.0)
    needle_specular: tuple[float, float, float] = (0.9, 0.9, 0.9)
    shaft_rgba: tuple[float, float, float, float] = (0.09, 0.09, 0.10, 1.0)
    metal_rgba: tuple[float, float, float, float] = (0.64, 0.65, 0.67, 1.0)
    jaw_rgba: tuple[float, float, float, float] = (0.55, 0.56, 0.58, 1.0)
    phantom_marks: MarksDraw | None = None
    phantom_shape: str = "incisions"


@dataclass(frozen=True)
class ThreadDraw:
    """The suture of one replay.

    Attributes:
        length_mm: Length of the simulated thread from the needle's tail, mm.
        radius_mm: Tube radius, mm (0.15–0.25: a 0.3–0.5 mm suture).
        segments: Rigid segments of the chain.
        rgba: Colour.
        heading: Initial direction of the thread on the tissue, rad (world x = 0).
        curl: Standard deviation of the turn between segments of the initial lay, rad.
        sway_mm_s2: Amplitude of the sideways sway acceleration, mm/s².
        sway_hz: Sway frequency, Hz.
        sway_phase: Sway phase, rad.
        lay_seed: Seed of the turns of the initial lay (drawn from the replay's stream).
        fall_m_s2: Downward acceleration, m/s²: air drag makes a light suture fall much
            slower than 9.81; low values keep loops in the air longer (a stiffer suture).
    """

    length_mm: float
    radius_mm: float
    segments: int
    rgba: tuple[float, float, float, float]
    heading: float
    curl: float
    sway_mm_s2: float
    sway_hz: float
    sway_phase: float
    lay_seed: int
    fall_m_s2: float


@dataclass(frozen=True)
class DomainDraw:
    """What a non-default profile drew for one replay (recorded as ``domain``).

    Attributes:
        profile: Profile name.
        light_setup: Key of :data:`LIGHT_SETUPS`.
        distance_mm: Camera-to-needle depth (the needle's median position over the replay).
        phantom_tint, background: Keys of :data:`PHANTOM_TINTS`, :data:`BACKGROUNDS`.
        appearance: The materials.
        thread: The suture, or None.
        orbit: Where the endoscope orbits the needle, or None (moved along its line of
            sight, :func:`dolly_offset`).
    """

    profile: str
    light_setup: str
    distance_mm: float
    phantom_tint: str
    background: str
    appearance: Appearance
    thread: ThreadDraw | None = None
    orbit: OrbitDraw | None = None

    def to_json(self) -> dict[str, Any]:
        """JSON-ready form."""
        return asdict(self)


@runtime_checkable
class DomainBackend(Protocol):
    """What a render backend adds to support a non-default ``--domain``."""

    def set_appearance(self, appearance: Appearance) -> None:
        """Change the materials of the loaded scene (phantom, background, needle, tools)."""
        ...

    def set_thread(
        self, points: F64, radius_mm: float, rgba: tuple[float, float, float, float]
    ) -> None:
        """Show a tube through ``points`` (N, 3), world, m, of radius ``radius_mm``.

        Not an annotated object: it appears in rgb and depth, never in the instance map.
        The number of points and the radius stay the same for the backend's lifetime.
        """
        ...


def _pick(rng: np.random.Generator, keys: tuple[str, ...] | list[str]) -> str:
    return keys[int(rng.integers(len(keys)))]


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def draw_domain(
    rng: np.random.Generator, replay_index: int, profile: str = DEFAULT_DOMAIN
) -> tuple[ReplayDraw, DomainDraw | None]:
    """The viewpoint, light and (for ``wide``) domain draw of one replay.

    ``paper`` is exactly :func:`~bopsurg.generators.viewpoints.draw_replay`; ``wide`` draws
    the light set-up first, then the same viewpoint draw with that set-up's light ranges,
    then the rest, all from ``rng``.

    Args:
        rng: The replay's seeded generator.
        replay_index: Replay index (selects the ECM base pose).
        profile: One of :data:`DOMAINS`.

    Raises:
        ValueError: An unknown profile.
    """
    if profile == "paper":
        return draw_replay(rng, replay_index), None
    if profile != "wide":
        raise ValueError(f"unknown domain profile {profile!r}; expected one of {DOMAINS}")
    setup = _pick(rng, list(LIGHT_SETUPS))
    draw = draw_replay(rng, replay_index, LIGHT_SETUPS[setup])
    distance = _u(rng, *WIDE_DISTANCE_MM)
    tint, background, appearance = _draw_appearance(rng)
    thread = _draw_thread(rng)
    # Drawn last (revision 2), so every draw above is what revision 1 drew.
    appearance = replace(appearance, phantom_marks=_draw_marks(rng))
    orbit = _draw_orbit(rng)  # revision 3, after everything above
    # Revision 4, drawn last: the groove pad.
    if _u(rng, 0.0, 1.0) < GROOVE_SHARE:
        appearance = replace(appearance, phantom_shape="groove")
    return draw, DomainDraw(
        profile=profile,
        light_setup=setup,
        distance_mm=distance,
        phantom_tint=tint,
        background=background,
        appearance=appearance,
        thread=thread,
        orbit=orbit,
    )


def _draw_appearance(rng: np.random.Generator) -> tuple[str, str, Appearance]:
    """The phantom's tint and the background (their names) and the materials of ``wide``."""
    tint = _pick(rng, list(PHANTOM_TINTS))
    background = _pick(rng, list(BACKGROUNDS))
    surface = _pick(rng, PHANTOM_SURFACES)
    steel = _u(rng, 0.45, 0.8)  # darker steel makes the highlights stand out
    shaft = _u(rng, 0.04, 0.2)
    metal = _u(rng, 0.35, 0.7)
    appearance = Appearance(
        phantom_surface=surface,
        phantom_texture_seed=int(rng.integers(0, 4)),
        phantom_rgba=(*PHANTOM_TINTS[tint], 1.0),
        background_rgba=(*BACKGROUNDS[background], 1.0),
        needle_rgba=(steel, steel, steel * _u(rng, 1.0, 1.06), 1.0),
        needle_specular=(1.0, 1.0, 1.0),
        shaft_rgba=(shaft, shaft, shaft * 1.05, 1.0),
        metal_rgba=(metal, metal, metal * 1.03, 1.0),
        jaw_rgba=(0.85 * metal, 0.85 * metal, 0.88 * metal, 1.0),
    )
    return tint, background, appearance


def _draw_thread(rng: np.random.Generator) -> ThreadDraw:
    """The suture thread of ``wide``."""
    colour = THREAD_COLOURS[_pick(rng, list(THREAD_COLOURS))]
    return ThreadDraw(
        length_mm=_u(rng, 40.0, 90.0),
        radius_mm=_u(rng, 0.15, 0.25),
        segments=24,
        rgba=(*colour, 1.0),
        heading=_u(rng, 0.0, 2 * np.pi),
        curl=_u(rng, 0.05, 0.35),
        sway_mm_s2=_u(rng, 0.0, 400.0),
        sway_hz=_u(rng, 0.2, 1.0),
        sway_phase=_u(rng, 0.0, 2 * np.pi),
        lay_seed=int(rng.integers(0, 2**31)),
        fall_m_s2=_u(rng, 0.05, 0.6),
    )


def _draw_marks(rng: np.random.Generator) -> MarksDraw | None:
    """Suture targets on :data:`MARKS_SHARE` of the replays; all six numbers are drawn
    whether or not targets are shown, so the stream's length is fixed."""
    marked = _u(rng, 0.0, 1.0) < MARKS_SHARE
    marks = MarksDraw(
        shape=_pick(rng, MARK_SHAPES),
        colour=_pick(rng, list(MARK_COLOURS)),
        size_mm=_u(rng, 2.0, 5.0),
        spacing_mm=_u(rng, 6.0, 12.0),
        offset_mm=_u(rng, 2.5, 6.0),
    )
    return marks if marked else None


def _draw_orbit(rng: np.random.Generator) -> OrbitDraw | None:
    """The orbit on :data:`ORBIT_SHARE` of the replays; every number is drawn whether or not
    it orbits."""
    orbiting = _u(rng, 0.0, 1.0) < ORBIT_SHARE
    orbit = OrbitDraw(
        elevation_deg=_u(rng, *ORBIT_ELEVATION_DEG),
        azimuth_deg=_u(rng, 0.0, 360.0),
        roll_deg=_u(rng, -180.0, 180.0),
        off_x_deg=_u(rng, -ORBIT_OFF_AXIS_DEG, ORBIT_OFF_AXIS_DEG),
        off_y_deg=_u(rng, -ORBIT_OFF_AXIS_DEG, ORBIT_OFF_AXIS_DEG),
    )
    return orbit if orbiting else None


def profile_scene(profile: str, scene: SceneSpec) -> SceneSpec:
    """The scene of a profile: ``wide`` shows Large Needle Driver instruments (``lnd``).

    Chosen per dataset, not per replay: with ``--annotate-instruments`` the instrument parts
    are BOP objects whose models are written once.
    """
    return scene if profile == DEFAULT_DOMAIN else replace(scene, instruments="lnd")


def dolly_offset(T_world_cam: F64, point_world: F64, distance_mm: float) -> F64:
    """The camera-frame translation that puts ``point_world`` at depth ``distance_mm``.

    The camera keeps its orientation and moves along the line of sight to the point, so the
    point stays on the same pixel; behind or beside the camera (z ≤ 1 mm), the point is
    brought onto the optical axis instead.

    Args:
        T_world_cam: (4, 4) camera pose, m, OpenCV axes.
        point_world: (3,) the point, world, m.
        distance_mm: Wanted depth (camera z) of the point, mm.

    Returns:
        (4, 4) ``T_cam_newcam`` (a translation, m): the new pose is ``T_world_cam @ it``.
    """
    p = np.linalg.solve(T_world_cam, np.append(np.asarray(point_world, np.float64), 1.0))[:3]
    d = 1e-3 * float(distance_mm)
    target = p * (d / p[2]) if p[2] > 1e-3 else np.array([0.0, 0.0, d])
    T = np.eye(4)
    T[:3, 3] = p - target
    return T


def orbit_offset(T_world_cam: F64, point_world: F64, distance_mm: float, orbit: OrbitDraw) -> F64:
    """The camera move that views ``point_world`` as ``orbit`` says, at depth ``distance_mm``.

    The new camera lies on the line from the point at the orbit's elevation and azimuth,
    turned so that the point is seen ``off_x_deg``, ``off_y_deg`` off its optical axis (world
    +Z up in the image), then rolled by ``roll_deg`` about that axis; its distance puts the
    point at depth (camera z) ``distance_mm``.

    Args:
        T_world_cam: (4, 4) the drawn (ECM) camera pose, m, OpenCV axes.
        point_world: (3,) the point, world, m.
        distance_mm: Wanted depth of the point, mm.
        orbit: The draw.

    Returns:
        (4, 4) ``T_cam_newcam`` (m): the new pose is ``T_world_cam @ it``.
    """
    e, a = np.deg2rad(orbit.elevation_deg), np.deg2rad(orbit.azimuth_deg)
    to_camera = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    R_look = look_rotation(-to_camera, up_hint=(0.0, 0.0, 1.0))  # the point on the axis
    # the point seen along v in the turned camera: turn maps v onto the optical axis
    v = np.array([np.tan(np.deg2rad(orbit.off_x_deg)), np.tan(np.deg2rad(orbit.off_y_deg)), 1.0])
    v /= np.linalg.norm(v)
    turn = Rotation.align_vectors([[0.0, 0.0, 1.0]], [v])[0].as_matrix()
    R = R_look @ turn @ rot_z(np.deg2rad(orbit.roll_deg))
    depth_per_m = v[2]  # a camera D m away sees the point at depth D · v_z
    centre = np.asarray(point_world, np.float64) + 1e-3 * distance_mm / depth_per_m * to_camera
    return np.linalg.solve(T_world_cam, pose(R, centre))


# --------------------------------------------------------------------------- the thread


def floor_height(xy: F64, pad_shape: str = "incisions") -> F64:
    """Height (m) of what a thread lies on at world (x, y) (N, 2) m: the pad of
    ``pad_shape`` (its incisions or groove bridged), else the drape (and the backdrop that
    continues it, in the same plane)."""
    x_mm, y_mm = 1e3 * xy[:, 0], 1e3 * xy[:, 1]
    on_pad = (np.abs(x_mm) <= 0.5 * PAD_SIZE[0]) & (np.abs(y_mm) <= 0.5 * PAD_SIZE[1])
    # A thread spans the 1.2 mm incisions (and the 2.4 mm groove) rather than dipping into
    # them: the highest of the pad's heights 1.5 mm either side across them (they run along y).
    n = len(x_mm)
    around = pad_height(np.concatenate([x_mm, x_mm - 1.5, x_mm + 1.5]), np.tile(y_mm, 3), pad_shape)
    top = around.reshape(3, n).max(axis=0)
    h = np.where(on_pad, top, -PAD_THICKNESS)
    out: F64 = 1e-3 * h
    return out


class SutureThread:
    """A suture hanging from the needle's tail, simulated by position-based dynamics.

    A chain of ``segments`` + 1 particles (m, world): particle 0 is pinned to the tail and
    particle 1 one segment out along the tail's axis (the swaged thread leaves straight);
    the rest fall (slowly: :attr:`ThreadDraw.fall_m_s2`), sway sideways, keep
    their segment lengths (alternating even/odd passes, vectorised), resist sharp bends,
    and rest on the tissue / drape with friction. The state depends only on the sequence of
    tail poses it was driven with, so a replay that re-runs its frames from the first one
    reproduces it exactly.

    Args:
        draw: The thread's parameters.
        substep_s: Longest simulation step, s.
        pad_shape: The shape of the pad it rests on (:data:`~.pybullet_scene.PAD_SHAPES`).
    """

    DAMPING = 0.8  # velocity kept per substep
    ITERATIONS = 4
    FRICTION = 0.5  # fraction of sideways motion removed on contact

    def __init__(
        self, draw: ThreadDraw, substep_s: float = 0.025, pad_shape: str = "incisions"
    ) -> None:
        self.draw = draw
        self.pad_shape = pad_shape
        self.substep_s = substep_s
        self.seg = 1e-3 * draw.length_mm / draw.segments
        self.radius = 1e-3 * draw.radius_mm
        n = draw.segments + 1
        self.x = np.zeros((n, 3))
        self.x_prev = np.zeros((n, 3))
        self.t: float | None = None
        self.tail = np.zeros(3)
        self.axis = np.array([1.0, 0.0, 0.0])
        # inverse masses: the two pinned particles do not move under constraints
        self._w = np.ones(n)
        self._w[:2] = 0.0
        # segments starting at even / odd particles, and each end's share of a correction
        self._pairs = {k: len(range(k, draw.segments, 2)) for k in (0, 1)}
        self._wa: dict[int, F64] = {}
        self._wb: dict[int, F64] = {}
        for k, m in self._pairs.items():
            wa, wb = self._w[k : k + 2 * m : 2], self._w[k + 1 : k + 2 * m : 2]
            total = np.maximum(wa + wb, 1e-12)
            self._wa[k], self._wb[k] = (wa / total)[:, None], (wb / total)[:, None]

    def _lay(self, tail: F64, axis: F64) -> None:
        """Initial shape: out along the tail's axis, down to the tissue, then a curling path
        along it, every segment at its length (a lay shorter than the thread would buckle)."""
        d = self.draw
        n = d.segments + 1
        turns = np.random.default_rng(d.lay_seed).normal(0.0, d.curl, n)
        heading = d.heading + np.cumsum(turns)
        x = np.empty((n, 3))
        x[0], x[1] = tail, tail + self.seg * axis
        for i in range(2, n):  # once per replay: a plain loop is fine
            above = x[i - 1, 2] - (floor_height(x[i - 1 : i, :2], self.pad_shape)[0] + self.radius)
            drop = float(np.clip(above, 0.0, 0.7 * self.seg))
            run = np.sqrt(self.seg**2 - drop**2)
            x[i] = x[i - 1] + (run * np.cos(heading[i]), run * np.sin(heading[i]), -drop)
        self.x = x
        self.x_prev = x.copy()

    def advance(self, t: float, T_world_needle: F64, tail_local_m: F64, axis_local: F64) -> F64:
        """Move the tail to its pose at time ``t`` (s) and simulate up to ``t``.

        Args:
            t: Time, s (non-decreasing over calls).
            T_world_needle: (4, 4) needle pose, m.
            tail_local_m: (3,) tail point in the needle frame, m.
            axis_local: (3,) unit direction the thread leaves the tail in, needle frame.

        Returns:
            (segments + 1, 3) particle positions, world, m (a copy).
        """
        tail = T_world_needle[:3, :3] @ tail_local_m + T_world_needle[:3, 3]
        axis = T_world_needle[:3, :3] @ axis_local
        if self.t is None:
            self._lay(tail, axis)
            self.tail, self.axis, self.t = tail, axis, t
            self._simulate(t - 2.0, t, tail, axis)  # let it settle on the tissue
        else:
            self._simulate(self.t, t, tail, axis)
        self.tail, self.axis, self.t = tail, axis, t
        return self.x.copy()

    def _simulate(self, t0: float, t1: float, tail: F64, axis: F64) -> None:
        n_sub = max(1, int(np.ceil((t1 - t0) / self.substep_s - 1e-9)))
        dt = (t1 - t0) / n_sub if t1 > t0 else self.substep_s
        d = self.draw
        for s in range(1, n_sub + 1):
            a = s / n_sub
            tail_s = (1 - a) * self.tail + a * tail
            axis_s = (1 - a) * self.axis + a * axis
            axis_s = axis_s / max(float(np.linalg.norm(axis_s)), 1e-12)
            ts = t0 + s * dt
            sway = 1e-3 * d.sway_mm_s2 * np.sin(2 * np.pi * d.sway_hz * ts + d.sway_phase)
            acc = np.array([sway * np.cos(d.heading + 1.3), sway * np.sin(d.heading + 1.3), 0.0])
            acc[2] -= d.fall_m_s2
            v = (self.x - self.x_prev) * self.DAMPING
            self.x_prev = self.x.copy()
            self.x = self.x + v + acc * dt * dt
            self.x[0] = tail_s
            self.x[1] = tail_s + self.seg * axis_s
            floor = floor_height(self.x[:, :2], self.pad_shape) + self.radius
            for _ in range(self.ITERATIONS):
                self._lengths(0)
                self._lengths(1)
                self._bend()
                np.maximum(self.x[:, 2], floor, out=self.x[:, 2])
            self._friction(floor)

    def _lengths(self, start: int) -> None:
        """Restore the lengths of every other segment from ``start`` (disjoint pairs; views)."""
        m = self._pairs[start]
        a, b = self.x[start : start + 2 * m : 2], self.x[start + 1 : start + 2 * m : 2]
        wa, wb = self._wa[start], self._wb[start]
        delta = b - a
        length = np.sqrt(np.einsum("ij,ij->i", delta, delta))[:, None]
        corr = delta * ((length - self.seg) / np.maximum(length, 1e-12))
        a += wa * corr
        b -= wb * corr

    def _bend(self) -> None:
        """Push particles two apart towards at least 1.7 segments (bends under ~64°)."""
        delta = self.x[2:] - self.x[:-2]
        length = np.maximum(np.linalg.norm(delta, axis=1, keepdims=True), 1e-12)
        short = np.minimum(length - 1.7 * self.seg, 0.0)
        wa, wb = self._w[:-2, None], self._w[2:, None]
        corr = 0.5 * delta * (short / length) / np.maximum(wa + wb, 1e-12)
        self.x[:-2] += wa * corr
        self.x[2:] -= wb * corr

    def _friction(self, floor: F64) -> None:
        """Remove most sideways motion of the particles resting on the floor."""
        resting = self.x[:, 2] <= floor + 1e-6
        self.x_prev[resting, :2] += self.FRICTION * (self.x[resting, :2] - self.x_prev[resting, :2])


def needle_tail(model: ObjectModel) -> tuple[F64, F64]:
    """The tail point (m) and outward thread direction of a needle model, in its frame.

    Uses :func:`bopsurg.needle.fit_needle`, so any needle mesh works: the direction is the
    arc's tangent at the tail, pointing away from the tip.

    Args:
        model: The needle's model, mm.
    """
    arc = fit_needle(model, name="needle")
    toward_tip = np.cross(arc.normal, arc.tail - arc.center)
    out = -toward_tip / np.linalg.norm(toward_tip)
    return 1e-3 * np.asarray(arc.tail, np.float64), out


class DomainReplay:
    """A replay's domain draw applied to its backend: camera offset, materials, thread.

    Args:
        domain: The replay's draw.
        backend: The replay's backend, scene loaded (must implement :class:`DomainBackend`).
        needle_positions: (F, 3) the needle's world positions (m) at the replay's frames.
        T_world_cam: The drawn (ECM) camera pose, m.

    Raises:
        InputError: The backend does not implement :class:`DomainBackend`.
    """

    def __init__(
        self, domain: DomainDraw, backend: RenderBackend, needle_positions: F64, T_world_cam: F64
    ) -> None:
        needle_model = backend.object_model(NEEDLE)
        if not isinstance(backend, DomainBackend):
            raise InputError(
                f"the render backend {type(backend).__name__} does not support "
                f"--domain {domain.profile} (it lacks set_appearance/set_thread)",
                field="--domain",
            )
        self.domain = domain
        self.backend: DomainBackend = backend
        ref = np.median(np.asarray(needle_positions, np.float64).reshape(-1, 3), axis=0)
        #: ``T_cam_newcam``: the camera moved to the drawn distance (:func:`dolly_offset`),
        #: or placed around the needle (:func:`orbit_offset`).
        if domain.orbit is None:
            self.camera_offset = dolly_offset(T_world_cam, ref, domain.distance_mm)
        else:
            self.camera_offset = orbit_offset(T_world_cam, ref, domain.distance_mm, domain.orbit)
        backend.set_appearance(domain.appearance)
        log.debug(
            "domain %s: needle at %.1f mm, camera moved by %s m, light %s",
            domain.profile,
            domain.distance_mm,
            np.round(self.camera_offset[:3, 3], 4).tolist(),
            domain.light_setup,
        )
        self.thread = None
        if domain.thread is not None:
            shape = domain.appearance.phantom_shape
            self.thread = SutureThread(domain.thread, pad_shape=shape)
            self._tail = needle_tail(needle_model)

    def frame(self, t: float, T_world_needle: F64) -> None:
        """Advance the thread to time ``t`` (s) with the needle at ``T_world_needle`` (m)."""
        if self.thread is None:
            return
        pts = self.thread.advance(t, np.asarray(T_world_needle, np.float64), *self._tail)
        d = self.thread.draw
        self.backend.set_thread(pts, d.radius_mm, d.rgba)


__all__ = [
    "BACKGROUNDS",
    "DEFAULT_DOMAIN",
    "DOMAINS",
    "GROOVE_SHARE",
    "LIGHT_SETUPS",
    "MARKS_SHARE",
    "MARK_COLOURS",
    "ORBIT_SHARE",
    "PHANTOM_SURFACES",
    "PHANTOM_TINTS",
    "THREAD_COLOURS",
    "WIDE_DISTANCE_MM",
    "Appearance",
    "DomainBackend",
    "DomainDraw",
    "DomainReplay",
    "MarksDraw",
    "OrbitDraw",
    "SutureThread",
    "ThreadDraw",
    "dolly_offset",
    "draw_domain",
    "floor_height",
    "needle_tail",
    "orbit_offset",
    "profile_scene",
]
