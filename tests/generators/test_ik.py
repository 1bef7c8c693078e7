"""PSM inverse kinematics: FK∘IK round trips, limits, unreachable poses, trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from bopsurg.errors import InputError
from bopsurg.generators.ik import IKError, cold_seed, psm_ik, psm_ik_solve, psm_ik_trajectory
from bopsurg.generators.kinematics import PSM_JOINT_LIMITS, in_limits, psm_tip_pose

LO, HI = PSM_JOINT_LIMITS[:, 0], PSM_JOINT_LIMITS[:, 1]


def _pose_error(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """Position error (mm) and rotation error (deg) between two poses."""
    dp = np.linalg.norm(A[:3, 3] - B[:3, 3]) * 1e3
    cos = np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(dp), float(np.degrees(np.arccos(cos)))


def _random_joints(rng: np.random.Generator, n: int) -> np.ndarray:
    margin = 0.05 * (HI - LO)
    return rng.uniform(LO + margin, HI - margin, size=(n, 6))


@pytest.mark.parametrize("warm", [False, True])
def test_round_trip_random_reachable_poses(warm):
    rng = np.random.default_rng(0)
    for q_true in _random_joints(rng, 60):
        T = psm_tip_pose(q_true)
        seed = q_true + rng.normal(0.0, 0.05, 6) if warm else None
        q = psm_ik(T, seed)
        dp, dr = _pose_error(psm_tip_pose(q), T)
        assert dp < 0.01
        assert dr < 0.01
        assert in_limits(q, PSM_JOINT_LIMITS, tol=0.0).all()


def test_solve_reports_residuals_and_iterations():
    q_true = np.array([0.2, -0.1, 0.12, 0.5, 0.3, -0.2])
    res = psm_ik_solve(psm_tip_pose(q_true), q_true + 0.01)
    assert res.converged
    assert res.pos_err_mm < 1e-3
    assert res.rot_err_deg < 1e-3
    assert 1 <= res.iterations <= 10


def test_cold_seed_points_the_shaft_at_the_wrist():
    q_true = np.array([0.3, -0.2, 0.15, 0.0, 0.0, 0.0])  # straight wrist: exact
    np.testing.assert_allclose(cold_seed(psm_tip_pose(q_true)), q_true, atol=1e-9)


def test_unreachable_pose_raises_one_line_error():
    T = psm_tip_pose(np.zeros(6))
    T[:3, 3] += [0.0, 0.0, -1.0]  # a metre beyond the longest insertion
    res = psm_ik_solve(T, None)
    assert not res.converged
    assert in_limits(res.q, PSM_JOINT_LIMITS, tol=0.0).all()
    with pytest.raises(IKError, match="unreachable") as exc:
        psm_ik(T)
    assert isinstance(exc.value, InputError)
    assert "\n" not in str(exc.value)


def test_pose_needing_a_joint_beyond_its_limit_is_not_faked():
    q = np.array([0.1, 1.2, 0.12, 0.2, 0.1, 0.1])  # outer pitch beyond +0.925 rad
    res = psm_ik_solve(psm_tip_pose(q), np.clip(q, LO, HI))
    assert in_limits(res.q, PSM_JOINT_LIMITS, tol=0.0).all()
    assert not res.converged


def test_bad_input_shapes():
    with pytest.raises(IKError, match="4, 4"):
        psm_ik(np.eye(3))
    with pytest.raises(IKError, match="q_seed"):
        psm_ik(np.eye(4), np.zeros(5))


def test_trajectory_warm_starts_and_flags():
    t = np.linspace(0.0, 1.0, 80)[:, None]
    q_path = np.array([0.1, -0.2, 0.12, -0.5, 0.2, 0.1]) + t * np.array(
        [0.3, 0.3, 0.04, 2.0, -0.6, 0.5]
    )
    Ts = np.stack([psm_tip_pose(q) for q in q_path])
    q, ok = psm_ik_trajectory(Ts, q_path[0])
    assert ok.all()
    # Warm starts stay on the same branch: the joint path itself comes back.
    np.testing.assert_allclose(q, q_path, atol=1e-6)

    bad = Ts.copy()
    bad[40, :3, 3] += [0.0, 0.0, -1.0]
    with pytest.raises(IKError, match="sample 40"):
        psm_ik_trajectory(bad, q_path[0])
    q, ok = psm_ik_trajectory(bad, q_path[0], strict=False)
    assert not ok[40]
    assert ok[:40].all()
    assert ok[41:].all()
    with pytest.raises(IKError, match="N, 4, 4"):
        psm_ik_trajectory(np.eye(4))
