"""The needle model built by code."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from bopsurg.bop.meshes import compute_model_info
from bopsurg.needle import NeedleSpec, needle_mesh


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
