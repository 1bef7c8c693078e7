"""The needle model built by code."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from bopsurg.bop.meshes import compute_model_info
from bopsurg.errors import ModelError
from bopsurg.needle import NeedleSpec, fit_needle, needle_mesh


def test_default_needle_is_a_closed_mesh_of_the_papers_size():
    m = needle_mesh()
    mesh = trimesh.Trimesh(m.pts, m.faces, process=False)
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.volume > 0  # outward-facing triangles
    info = compute_model_info(m.pts)
    assert info["diameter"] == pytest.approx(18.65, abs=0.15)
    assert info["size_z"] == pytest.approx(0.72 * NeedleSpec().swage_scale, rel=1e-3)


def test_tip_and_tail_are_distinguishable():
    spec = NeedleSpec()
    m = needle_mesh(spec)
    tip = m.pts[-1]
    assert np.linalg.norm(tip) == pytest.approx(spec.arc_radius)
    angle = np.degrees(np.arctan2(tip[1], tip[0]))
    assert angle == pytest.approx(spec.total_deg)
    assert m.pts[0] == pytest.approx([spec.arc_radius, 0, 0])  # tail-cap centre
    ring = m.pts[1 : 1 + spec.sides]
    assert np.linalg.norm(ring - m.pts[0], axis=1) == pytest.approx(
        np.full(spec.sides, 0.5 * spec.wire_diameter * spec.swage_scale)
    )


def test_half_circle_needle():
    spec = NeedleSpec.circle_fraction(0.5)
    assert spec.total_deg == pytest.approx(180.0)
    info = compute_model_info(needle_mesh(spec).pts)
    outer = spec.arc_radius + 0.5 * spec.wire_diameter * spec.swage_scale
    assert 2 * spec.arc_radius < info["diameter"] < 2 * outer


# --------------------------------------------------------------------------- fit_needle


def _rigid(seed: int) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    return Rotation.random(random_state=rng).as_matrix(), rng.uniform(-30, 30, 3)


def test_fit_recovers_the_built_needle_in_its_own_frame():
    spec = NeedleSpec()
    m = needle_mesh(spec)
    arc = fit_needle(m)
    assert arc.center == pytest.approx([0, 0, 0], abs=0.02)
    assert arc.normal == pytest.approx([0, 0, 1], abs=1e-6)
    assert arc.radius == pytest.approx(spec.arc_radius, abs=0.01)
    assert arc.extent_deg == pytest.approx(spec.total_deg, abs=0.5)
    assert arc.tip == pytest.approx(m.pts[-1], abs=0.05)
    assert arc.tail == pytest.approx(m.pts[0], abs=0.05)
    assert arc.wire_radius == pytest.approx(0.5 * spec.wire_diameter, rel=0.05)
    R, t = arc.frame()
    np.testing.assert_allclose(R, np.eye(3), atol=1e-9)
    assert t == pytest.approx([0, 0, 0], abs=0.02)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_fit_follows_rigid_motions_of_the_mesh(seed):
    """Moved by (Q, q), the fitted arc and its frame move the same way."""
    Q, q = _rigid(seed)
    m = needle_mesh()
    ref = fit_needle(m)
    moved = fit_needle(m.pts @ Q.T + q)
    assert moved.radius == pytest.approx(ref.radius, abs=1e-9)
    assert moved.extent_deg == pytest.approx(ref.extent_deg, abs=1e-6)
    assert moved.normal == pytest.approx(Q @ ref.normal, abs=1e-9)
    assert moved.tip == pytest.approx(Q @ ref.tip + q, abs=1e-9)
    assert moved.tail == pytest.approx(Q @ ref.tail + q, abs=1e-9)
    R0, t0 = ref.frame()
    R1, t1 = moved.frame()
    np.testing.assert_allclose(R1, Q @ R0, atol=1e-9)
    assert t1 == pytest.approx(Q @ t0 + q, abs=1e-9)


@pytest.mark.parametrize(
    "spec",
    [
        NeedleSpec(arc_radius=6.5, wire_diameter=0.4),
        NeedleSpec.circle_fraction(0.5),
        NeedleSpec.circle_fraction(5 / 8, arc_radius=13.0, wire_diameter=1.0),
        NeedleSpec(body_deg=80.0, tip_deg=12.0, rings=48, sides=8),
    ],
)
def test_fit_other_radii_and_arcs(spec):
    m = needle_mesh(spec)
    Q, q = _rigid(7)
    arc = fit_needle(m.pts @ Q.T + q)
    assert arc.radius == pytest.approx(spec.arc_radius, rel=2e-3)
    assert arc.extent_deg == pytest.approx(spec.total_deg, abs=1.0)
    assert arc.tip == pytest.approx(Q @ m.pts[-1] + q, abs=0.05)
    assert arc.tail == pytest.approx(Q @ m.pts[0] + q, abs=0.05)


def test_fit_a_needle_whose_arc_runs_clockwise():
    """A mesh built tip-first, clockwise about +Z (as the AMBF needle): the normal is -Z."""
    m = needle_mesh()
    mirrored = m.pts * [1.0, -1.0, -1.0]  # half a turn about X: a rigid motion
    arc = fit_needle(mirrored)
    assert arc.normal == pytest.approx([0, 0, -1], abs=1e-6)
    assert arc.tip == pytest.approx(mirrored[-1], abs=0.05)


def _tube(angles_deg: np.ndarray, radius: float = 10.0, wire: float = 0.4) -> np.ndarray:
    """Surface points of a constant-radius tube along an arc (no taper at either end)."""
    s = np.deg2rad(angles_deg)[:, None]
    phi = np.linspace(0, 2 * np.pi, 12, endpoint=False)[None, :]
    r = radius + wire * np.cos(phi) + 0 * s
    z = wire * np.sin(phi) + 0 * s
    return np.stack([r * np.cos(s), r * np.sin(s), z], axis=2).reshape(-1, 3)


@pytest.mark.parametrize(
    ("pts", "match"),
    [
        (
            trimesh.creation.box(extents=(10, 10, 10)).subdivide().subdivide().vertices,
            "near a plane",
        ),
        (trimesh.creation.icosphere(subdivisions=2, radius=5.0).vertices, "near a plane"),
        (
            np.stack(
                [*np.meshgrid(np.arange(20.0), np.arange(20.0)), np.zeros((20, 20))], -1
            ).reshape(-1, 3),
            "thin arc",
        ),
        (_tube(np.linspace(0, 360, 200, endpoint=False)), "arc spans"),
        (_tube(np.linspace(0, 25, 40), wire=0.05), "arc spans"),
        (_tube(np.linspace(0, 130, 100)), "neither end tapers"),
        (np.zeros((5, 3)), "expected"),
    ],
    ids=["cube", "sphere", "plate", "ring", "short-arc", "no-taper", "too-few"],
)
def test_fit_refuses_what_is_not_a_needle(pts, match):
    with pytest.raises(ModelError, match=match) as err:
        fit_needle(np.asarray(pts, dtype=np.float64), name="thing.ply")
    assert str(err.value).startswith("thing.ply: not a needle")
    assert "\n" not in str(err.value)
