"""The needle's arc fitted to depth: back-projection, nearest arc points, the fit and its guard."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

torch = pytest.importorskip("torch")

from bopsurg import metrics  # noqa: E402
from bopsurg.models.predict_config import PointsFitSettings  # noqa: E402
from bopsurg.models.refine.arc import ArcModel, exp_so3, half_turn  # noqa: E402
from bopsurg.models.refine.depth_fit import fit_depth  # noqa: E402
from bopsurg.models.refine.lm import normal_equations  # noqa: E402
from bopsurg.models.refine.wire3d import (  # noqa: E402
    camera_normal_equations,
    depth_points,
    nearest_arc_points,
    wire_distances,
    wire_residuals,
    wire_residuals_model,
)

ARC = ArcModel()
K = np.array([[350.807, 0.0, 320.0], [0.0, 350.807, 240.0], [0.0, 0.0, 1.0]])


def wire_surface(
    R: np.ndarray, t: np.ndarray, rng: np.random.Generator, n: int = 600, arc: ArcModel = ARC
):
    """Points of the wire's surface that face the camera (what a depth camera sees), mm."""
    s = rng.uniform(0, arc.arc_rad, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    radial = np.stack([np.cos(s), np.sin(s), np.zeros(n)], axis=1)
    off = arc.wire_radius * (np.cos(phi)[:, None] * radial + np.sin(phi)[:, None] * [0, 0, 1.0])
    P = (arc.radius * radial + off) @ R.T + t
    return P[np.einsum("ni,ni->n", off @ R.T, P) < 0]


def tilt_mirror(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The pose whose arc projects onto the same pixels with its depths reflected through
    the line of sight (the image fit's two-fold ambiguity, exact under weak perspective)."""
    v = t / np.linalg.norm(t)
    return (np.eye(3) - 2 * np.outer(v, v)) @ R @ np.diag([1.0, 1.0, -1.0])


def test_depth_points_back_project_the_pixels_a_point_projects_to():
    P = np.array([[3.0, -2.0, 50.0], [-10.0, 4.0, 80.0], [0.0, 0.0, 30.0]])
    uv = (P @ K.T)[:, :2] / P[:, 2:]
    depth = np.zeros((480, 640))
    ij = np.round(uv).astype(int)
    depth[ij[:, 1], ij[:, 0]] = P[:, 2]
    # a point with no reading and one outside the image are dropped
    uv_all = np.vstack([uv, [[5.0, 5.0], [-3.0, 900.0]]])
    np.testing.assert_allclose(depth_points(uv_all, depth, K), P, atol=1e-9)


def test_nearest_arc_points_clamp_to_the_nearer_end():
    a = ARC.arc_rad
    q = np.array(
        [
            [20 * np.cos(a / 2), 20 * np.sin(a / 2), 3.0],  # over the arc: same angle
            [5 * np.cos(a + 0.2), 5 * np.sin(a + 0.2), 0.0],  # just past the tip
            [5 * np.cos(-0.2), 5 * np.sin(-0.2), 0.0],  # just before the tail
        ]
    )
    c = nearest_arc_points(torch.as_tensor(q), ARC).numpy()
    r = ARC.radius
    np.testing.assert_allclose(c[0], [r * np.cos(a / 2), r * np.sin(a / 2), 0], atol=1e-12)
    np.testing.assert_allclose(c[1], [r * np.cos(a), r * np.sin(a), 0], atol=1e-12)
    np.testing.assert_allclose(c[2], [r, 0, 0], atol=1e-12)


def _nearest_by_angle(q: np.ndarray, arc: ArcModel) -> np.ndarray:
    """The definition, worked with angles: the circle's point at the point's angle on the arc,
    else the end nearer in angle (past the tip, or before the tail going round)."""
    a = np.mod(np.arctan2(q[:, 1], q[:, 0]), 2 * np.pi)
    end = np.where(a - arc.arc_rad < 2 * np.pi - a, arc.arc_rad, 0.0)
    ang = np.where(a <= arc.arc_rad, a, end)
    return arc.radius * np.stack([np.cos(ang), np.sin(ang), np.zeros(len(q))], 1)


@pytest.mark.parametrize("arc_deg", [128.5, 180.0, 250.0])
def test_nearest_arc_points_without_angles_match_the_angle_definition(arc_deg):
    """The cross and dot tests give the angles' answer for arcs shorter and longer than a
    half turn, on points all round the plane (both ends, behind the centre)."""
    arc = ArcModel(radius=10.0, arc_rad=float(np.deg2rad(arc_deg)))
    rng = np.random.default_rng(5)
    q = np.concatenate([rng.normal(0, 12, (4000, 3)), [[0.0, 0.0, 2.0], [-3.0, 0.0, 0.0]]])
    got = nearest_arc_points(torch.as_tensor(q), arc).numpy()
    np.testing.assert_allclose(got, _nearest_by_angle(q, arc), rtol=0, atol=1e-12)


def test_model_frame_derivatives_give_the_camera_frames_normal_equations():
    rng = np.random.default_rng(6)
    R = torch.as_tensor(Rotation.random(2, random_state=2).as_matrix())
    t = torch.as_tensor([[1.0, -2.0, 60.0], [0.0, 3.0, 80.0]])
    P = t[:, None] + torch.as_tensor(rng.normal(0, 8, (2, 50, 3)))
    w = torch.as_tensor(rng.uniform(0.1, 1.0, (2, 50)))
    r_cam, J_cam = wire_residuals(R, t, P, ARC)
    r, J = wire_residuals_model(R, t, P.transpose(1, 2), ARC)  # by axis
    torch.testing.assert_close(r, r_cam)
    H, g = camera_normal_equations(*normal_equations(r, w, J, by_row=True), R)
    H_cam, g_cam = normal_equations(r_cam, w, J_cam)
    torch.testing.assert_close(H, H_cam, atol=1e-9, rtol=1e-12)
    torch.testing.assert_close(g, g_cam, atol=1e-9, rtol=1e-12)
    # and the camera frame's derivatives are the residuals' (central differences)
    step = 1e-6
    for k in range(6):
        d = torch.zeros(2, 6, dtype=torch.float64)
        d[:, k] = step
        r_hi = wire_residuals(exp_so3(d[:, :3]) @ R, t + d[:, 3:], P, ARC)[0]
        r_lo = wire_residuals(exp_so3(-d[:, :3]) @ R, t - d[:, 3:], P, ARC)[0]
        torch.testing.assert_close((r_hi - r_lo) / (2 * step), J_cam[..., k], atol=1e-5, rtol=0)


def test_surface_points_lie_on_the_wire_at_the_true_pose():
    rng = np.random.default_rng(0)
    R, t = Rotation.random(random_state=1).as_matrix(), np.array([2.0, -3.0, 60.0])
    P = torch.as_tensor(wire_surface(R, t, rng))[None]
    d = wire_distances(torch.as_tensor(R)[None], torch.as_tensor(t)[None], P, ARC).numpy()
    assert np.abs(d).max() < 1e-9


@pytest.mark.parametrize("mirrored", [False, True])
def test_the_fit_recovers_tilt_and_depth_and_keeps_the_image_fits_tip(mirrored):
    """From the image fit's pose (a few degrees and mm off, or its tilt mirror, which puts
    the arc on the same pixels), noisy depth with a fifth of the points reading the tissue
    behind the wire: the true pose, with the tip where the start had it."""
    rng = np.random.default_rng(3)
    res = []
    for i in range(12):
        R = Rotation.random(random_state=100 + i).as_matrix()
        t = np.array([rng.uniform(-10, 10), rng.uniform(-10, 10), rng.uniform(25, 120)])
        P = wire_surface(R, t, rng)
        P[:, 2] += rng.normal(0, 0.2, len(P))
        rim = rng.random(len(P)) < 0.2
        P[rim] *= 1 + rng.uniform(5, 30, (rim.sum(), 1)) / P[rim, 2:]  # tissue behind
        R0 = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix() @ R
        R0 = tilt_mirror(R0, t) if mirrored else R0
        fit = fit_depth(R0, t + rng.normal(0, 1.0, 3), P, ARC)
        assert fit.used
        res.append((metrics.re(R0, R)[0], metrics.re(fit.R, R)[0], np.linalg.norm(fit.t - t)))
    re0, re, te = np.array(res).T
    if mirrored:
        assert np.median(re0) > 20.0  # the start's tilt is wrong
    assert re.max() < 6.0  # deg
    assert np.median(re) < 2.0
    assert te.max() < 0.6  # mm


def test_the_guard_keeps_the_pose_without_a_wire_in_the_points():
    rng = np.random.default_rng(5)
    R, t = Rotation.random(random_state=7).as_matrix(), np.array([0.0, 0.0, 60.0])
    blob = t + rng.normal(0, 6.0, (300, 3))  # tissue, not a wire
    fit = fit_depth(R, t, blob, ARC)
    assert not fit.used
    np.testing.assert_array_equal(fit.R, R)
    np.testing.assert_array_equal(fit.t, t)
    few = wire_surface(R, t, rng)[:5]
    assert not fit_depth(R, t, few, ARC, PointsFitSettings(min_points=12)).used
    # points on one line (or one point) leave the arc free to turn about it, though an arc
    # passes through them: here the line touches the start's wire at its middle
    a = ARC.arc_rad / 2
    mid = ARC.radius * np.array([np.cos(a), np.sin(a), 0.0])
    tangent = np.array([-np.sin(a), np.cos(a), 0.0])
    line = (mid + np.linspace(-3.0, 3.0, 50)[:, None] * tangent) @ R.T + t
    assert not fit_depth(R, t, line, ARC).used
    assert not fit_depth(R, t, np.repeat(line[:1], 40, axis=0), ARC).used


def test_tip_and_tail_follow_the_start():
    """The points cannot tell the ends apart: a start with tip and tail swapped stays so."""
    rng = np.random.default_rng(9)
    R, t = Rotation.random(random_state=11).as_matrix(), np.array([5.0, 2.0, 50.0])
    P = wire_surface(R, t, rng)
    swapped = R @ half_turn(ARC)
    fit = fit_depth(swapped, t, P, ARC)
    assert metrics.re(fit.R, swapped)[0] < 1.0
