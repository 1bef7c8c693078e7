"""The shared Levenberg-Marquardt of the needle fits: it reaches a least-squares minimum from
every start at once, steps through a Hessian singular in some direction when given a floor,
keeps a start whose steps all fail, honours a prior, and moves tuple states by ``apply``."""

from __future__ import annotations

import numpy as np
import pytest

from bopsurg.models.refine.lm import levenberg_marquardt

A = np.random.default_rng(0).normal(size=(20, 6))
B = np.random.default_rng(1).normal(size=20)


def _linear(A: np.ndarray, b: np.ndarray):
    """Residuals A x - b for every start: the least-squares solution is the minimum."""

    def objective(x: np.ndarray):
        r = x @ A.T - b
        return 0.5 * (r**2).sum(1), r, np.ones_like(r), np.broadcast_to(A, (len(x), *A.shape))

    return objective


def test_every_start_reaches_the_least_squares_minimum():
    x0 = np.random.default_rng(2).normal(scale=5.0, size=(4, 6))
    x, cost = levenberg_marquardt(_linear(A, B), x0, np.add, 50, 1e-3, rtol=None)
    want, *_ = np.linalg.lstsq(A, B, rcond=None)
    np.testing.assert_allclose(x, np.broadcast_to(want, x.shape), atol=1e-8)
    np.testing.assert_allclose(cost, 0.5 * ((A @ want - B) ** 2).sum(), rtol=1e-10)


def test_a_free_direction_needs_the_floor():
    A0 = A.copy()
    A0[:, 5] = 0.0  # the residuals do not depend on x[5]: H is singular
    x0 = np.zeros((2, 6))
    with pytest.raises(np.linalg.LinAlgError):
        levenberg_marquardt(_linear(A0, B), x0, np.add, 5, 1e-3)
    x, _ = levenberg_marquardt(_linear(A0, B), x0, np.add, 50, 1e-3, floor=1e-9)
    assert np.isfinite(x).all()
    want, *_ = np.linalg.lstsq(A0[:, :5], B, rcond=None)
    np.testing.assert_allclose(x[:, :5], np.broadcast_to(want, (2, 5)), atol=1e-6)
    assert np.abs(x[:, 5]).max() < 1e-3  # the free direction barely moves


def test_a_start_whose_steps_all_fail_is_kept():
    base = _linear(A, B)

    def objective(x):
        c, r, w, J = base(x)
        c = np.where(np.arange(len(x)) == 1, np.where((x == 0).all(1), c, np.nan), c)
        return c, r, w, J  # start 1: every moved state costs NaN

    x, cost = levenberg_marquardt(objective, np.zeros((2, 6)), np.add, 10, 1e-3)
    assert (x[1] == 0).all()
    assert cost[1] == base(np.zeros((1, 6)))[0][0]
    assert cost[0] < cost[1]


def test_the_prior_pulls_to_its_centre():
    centre = np.full((1, 6), 3.0)
    strong = np.full(6, 1e3)

    def objective(x):
        c, r, w, J = _linear(A, B)(x)
        return c + 0.5 * ((strong * (x - centre)) ** 2).sum(1), r, w, J

    def prior(x):
        return np.diag(strong**2), strong**2 * (x - centre)

    x, _ = levenberg_marquardt(objective, np.zeros((1, 6)), np.add, 50, 1e-3, prior=prior)
    np.testing.assert_allclose(x, centre, atol=1e-3)


def test_a_tuple_state_moves_by_apply_and_stops_early():
    calls = []

    def objective(state):
        a, b = state
        calls.append(1)
        x = np.concatenate([a, b], axis=1)
        return _linear(A, B)(x)

    def apply(state, step):
        return state[0] + step[:, :3], state[1] + step[:, 3:]

    (a, b), _ = levenberg_marquardt(
        objective, (np.zeros((3, 3)), np.zeros((3, 3))), apply, 100, 1e-3
    )
    want, *_ = np.linalg.lstsq(A, B, rcond=None)
    np.testing.assert_allclose(np.concatenate([a, b], 1), np.broadcast_to(want, (3, 6)), atol=1e-6)
    assert len(calls) < 101  # rtol stopped it once no start moved
