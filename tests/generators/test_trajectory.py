"""Synthetic suturing episodes: determinism, limits, grasp attachment, through-tissue path."""

from __future__ import annotations

import numpy as np
import pytest

from bopsurg.errors import InputError
from bopsurg.generators.kinematics import (
    DEFAULT_LAYOUT,
    ECM_JOINT_LIMITS,
    JAW_LIMITS,
    PSM_JOINT_LIMITS,
    in_limits,
    psm_tip_pose,
)
from bopsurg.generators.pybullet_scene import pad_height
from bopsurg.generators.trajectory import (
    GRASP_JAW_THRESHOLD,
    TREMOR_HZ,
    TREMOR_RMS,
    _tremor,
    min_jerk,
    needle_grasp,
    synthesize_suturing,
)
from bopsurg.needle import NeedleSpec, needle_radius_profile

ARMS = ("psm1", "psm2")


@pytest.fixture(scope="module", params=[(7, 30.0), (3, 45.0)], ids=["30s", "45s"])
def episode(request):
    seed, duration = request.param
    return synthesize_suturing(seed, duration=duration)


def _tip_poses(rec, arm):
    base = DEFAULT_LAYOUT.psm_base(ARMS.index(arm))
    return np.stack([base @ psm_tip_pose(q) for q in rec.psm_joints[arm][1]])


def _needle_point(rec, deg: float) -> np.ndarray:
    """World positions (T, 3) of the needle's centre line at arc angle ``deg`` from the tail."""
    spec = NeedleSpec()
    a = np.deg2rad(deg)
    p = np.array([np.cos(a), np.sin(a), 0.0]) * spec.arc_radius * 1e-3
    T = rec.needle_pose[1]
    return T[:, :3, :3] @ p + T[:, :3, 3]


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    idx = np.flatnonzero(mask)
    return [r for r in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if len(r)]


def test_deterministic_per_seed():
    a = synthesize_suturing(5, duration=5.0, rate_hz=20.0)
    b = synthesize_suturing(5, duration=5.0, rate_hz=20.0)
    c = synthesize_suturing(6, duration=5.0, rate_hz=20.0)
    for arm in ARMS:
        np.testing.assert_array_equal(a.psm_joints[arm][1], b.psm_joints[arm][1])
        np.testing.assert_array_equal(a.jaws[arm][1], b.jaws[arm][1])
    np.testing.assert_array_equal(a.needle_pose[1], b.needle_pose[1])
    np.testing.assert_array_equal(a.ecm_joints[1], b.ecm_joints[1])
    assert a.meta == b.meta
    assert not np.array_equal(a.psm_joints["psm1"][1], c.psm_joints["psm1"][1])
    assert not np.array_equal(a.needle_pose[1], c.needle_pose[1])


def test_sampling_and_meta(episode):
    times = episode.psm_joints["psm1"][0]
    rate = episode.meta["rate_hz"]
    np.testing.assert_array_equal(times, np.arange(len(times)) / rate)
    assert times[-1] == pytest.approx(episode.meta["duration"])
    assert episode.meta["ik_failures"] == 0
    assert episode.meta["seed"] in (7, 3)
    assert episode.meta["throws"] in (1, 2)
    assert episode.duration == pytest.approx(episode.meta["duration"])
    assert [e["t0"] for e in episode.meta["events"]] == sorted(
        e["t0"] for e in episode.meta["events"]
    )


def test_joints_within_limits(episode):
    for arm in ARMS:
        assert in_limits(episode.psm_joints[arm][1], PSM_JOINT_LIMITS, tol=0.0).all()
        jaw = episode.jaws[arm][1]
        assert (jaw >= JAW_LIMITS[0]).all()
        assert (jaw <= JAW_LIMITS[1]).all()
    assert in_limits(episode.ecm_joints[1], ECM_JOINT_LIMITS, tol=0.0).all()


def test_needle_rests_then_is_attached_to_the_closed_jaw(episode):
    needle = episode.needle_pose[1]
    held_any = np.zeros(len(needle), dtype=bool)
    for arm in ARMS:
        closed = episode.jaws[arm][1] <= GRASP_JAW_THRESHOLD
        held_any |= closed
        tips = _tip_poses(episode, arm)
        rel = np.linalg.inv(tips) @ needle  # T_tip_needle
        runs = _runs(closed)
        assert runs, f"{arm} never grasps"
        for run in runs:
            assert len(run) > 50  # held for more than a second
            np.testing.assert_allclose(
                rel[run], np.broadcast_to(rel[run[0]], rel[run].shape), atol=1e-5
            )
            # the grasp point is on the wire, within the jaws (a few mm from the pivot)
            assert 1.0 < np.linalg.norm(np.linalg.inv(rel[run[0]])[:3, 3]) * 1e3 < 15.0
    first = np.flatnonzero(held_any)[0]
    assert first > 50
    np.testing.assert_array_equal(needle[:first], needle[:1].repeat(first, axis=0))
    # at rest: flat on the pad (model +Z up), its wire touching the surface and nowhere in it
    np.testing.assert_allclose(needle[0][:3, 2], [0.0, 0.0, 1.0], atol=1e-9)
    spec = NeedleSpec()
    degs = np.linspace(0.0, spec.total_deg, 181)
    centre = np.stack([_needle_point(episode, d)[0] for d in degs])  # m
    surface = pad_height(1e3 * centre[:, 0], 1e3 * centre[:, 1]) * 1e-3
    clearance = centre[:, 2] - needle_radius_profile(spec, degs) * 1e-3 - surface
    assert clearance.min() == pytest.approx(0.0, abs=2e-5)  # 20 µm: the test's finer sampling
    # after the first grasp the needle is always held by someone
    assert held_any[first:].all()


def test_needle_goes_through_the_tissue(episode):
    spec = NeedleSpec()
    times = episode.needle_pose[0]
    tip = _needle_point(episode, spec.total_deg)
    tail = _needle_point(episode, 0.0)
    entry = np.flatnonzero(tip[:, 2] < -1e-3)
    assert entry.size, "the tip never goes below the tissue surface"
    # the tip dives (1.5-4 mm deep), comes back up, and the whole needle follows
    assert -4e-3 < tip[:, 2].min() < -1.5e-3
    assert (tip[entry[-1] :, 2] > -1e-3).any()
    tail_below = np.flatnonzero(tail[:, 2] < -1e-3)
    assert tail_below.size
    assert tail_below[0] > entry[0]
    assert tip[-1, 2] > 0.0
    assert tail[-1, 2] > 0.0
    # one dive of the tip per throw
    dives = _runs(tip[:, 2] < 0.0)
    assert len(dives) == episode.meta["throws"]
    # the tip enters and leaves a chord apart (the needle turns about its arc centre)
    for run in dives:
        chord = np.linalg.norm(tip[run[-1], :2] - tip[run[0], :2])
        assert 10e-3 < chord < 16e-3, chord
    assert times[dives[0][0]] > 3.0


def test_tools_stay_above_the_tissue(episode):
    for arm in ARMS:
        assert _tip_poses(episode, arm)[:, 2, 3].min() > 0.5e-3


def test_smooth_bounded_joint_velocities(episode):
    rate = episode.meta["rate_hz"]
    limit = np.array([1.0, 1.0, 0.1, 5.0, 4.0, 5.0])  # rad/s, insertion m/s
    for arm in ARMS:
        q = episode.psm_joints[arm][1]
        v = np.abs(np.diff(q, axis=0)) * rate
        assert (v.max(axis=0) < limit).all(), v.max(axis=0)
        # no jumps: the largest step is a small multiple of the typical moving step
        a = np.abs(np.diff(q, n=2, axis=0)) * rate**2
        assert (a.max(axis=0) < 10.0 * limit * rate**0.5).all()
    jaw_v = np.abs(np.diff(episode.jaws["psm1"][1])) * rate
    assert jaw_v.max() < 6.0


def test_tremor_band_and_amplitude():
    rng = np.random.default_rng(1)
    times = np.arange(5000) / 200.0
    x = _tremor(rng, times)
    rms = np.sqrt(np.mean(np.sum(x**2, axis=1)))
    assert 0.6 * TREMOR_RMS[0] < rms < 1.4 * TREMOR_RMS[1]
    spectrum = np.abs(np.fft.rfft(x[:, 0]))
    freqs = np.fft.rfftfreq(len(times), 1 / 200.0)
    assert TREMOR_HZ[0] - 0.5 <= freqs[np.argmax(spectrum)] <= TREMOR_HZ[1] + 0.5


def test_min_jerk_profile():
    s = min_jerk(np.linspace(-0.5, 1.5, 401))
    assert s[0] == 0.0
    assert s[-1] == 1.0
    assert (np.diff(s) >= 0.0).all()
    assert min_jerk(np.array([0.5]))[0] == pytest.approx(0.5)


def test_grasp_offset_puts_the_wire_between_the_jaws():
    spec = NeedleSpec()
    G = needle_grasp(spec, 12.0, approach=-1, tilt_deg=0.0, depth_mm=3.0)
    a = np.deg2rad(12.0)
    p_needle = np.array([np.cos(a), np.sin(a), 0.0, 1e3 / spec.arc_radius]) * spec.arc_radius
    p_tip = G @ (p_needle * 1e-3)  # the grasp point in the tip frame
    np.testing.assert_allclose(p_tip[:3], [0.0, 0.0, 3e-3], atol=1e-12)
    # the jaw hinge axis (tip x) runs along the wire; the jaws (tip z) cross the needle plane
    tangent = np.array([-np.sin(a), np.cos(a), 0.0])
    np.testing.assert_allclose(np.linalg.inv(G)[:3, 0], tangent, atol=1e-12)
    np.testing.assert_allclose(np.linalg.inv(G)[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)
    flipped = needle_grasp(spec, 12.0, approach=-1, tilt_deg=0.0, depth_mm=3.0, flip=True)
    np.testing.assert_allclose(np.linalg.inv(flipped)[:3, 0], -tangent, atol=1e-12)


def test_state_at_replays_the_samples(episode):
    times = episode.needle_pose[0]
    i = len(times) // 3
    state = episode.state_at(float(times[i]))
    np.testing.assert_allclose(state.needle_pose, episode.needle_pose[1][i], atol=1e-12)
    np.testing.assert_allclose(state.psm_joints["psm2"], episode.psm_joints["psm2"][1][i])


def test_short_episode_and_other_needles():
    rec = synthesize_suturing(2, duration=8.0, rate_hz=25.0, needle=NeedleSpec.circle_fraction(0.5))
    assert rec.meta["throws"] == 1
    assert rec.meta["ik_failures"] == 0
    assert rec.meta["needle"]["body_deg"] == pytest.approx(171.5)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"duration": 0.0}, "duration"),
        ({"rate_hz": -1.0}, "rate"),
        ({"needle": NeedleSpec(body_deg=60.0)}, "too short"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(InputError, match=match):
        synthesize_suturing(0, **kwargs)
