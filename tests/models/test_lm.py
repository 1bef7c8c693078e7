"""The shared Levenberg-Marquardt of the needle fits: it reaches a least-squares minimum from
every start at once, steps through a Hessian singular in some direction when given a floor,
keeps a start whose steps all fail, honours a prior, moves tuple states by ``apply``, and stops
each problem of a batch as if it ran alone."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from bopsurg.models.refine.lm import (  # noqa: E402
    fit_threads,
    levenberg_marquardt,
    normal_equations,
)

A = torch.as_tensor(np.random.default_rng(0).normal(size=(20, 6)))
B = torch.as_tensor(np.random.default_rng(1).normal(size=20))
WANT = torch.as_tensor(np.linalg.lstsq(A.numpy(), B.numpy(), rcond=None)[0])


def _linear(A, b):
    """Residuals A x - b for every start: the least-squares solution is the minimum."""

    def objective(x):
        r = x @ A.T - b
        return 0.5 * (r**2).sum(1), *normal_equations(
            r, torch.ones_like(r), A.expand(len(x), *A.shape)
        )

    return objective


def _starts(n: int, seed: int = 2):
    return torch.as_tensor(np.random.default_rng(seed).normal(scale=5.0, size=(n, 6)))


def test_every_start_reaches_the_least_squares_minimum():
    x, cost = levenberg_marquardt(_linear(A, B), _starts(4), torch.add, 50, 1e-3, rtol=None)
    torch.testing.assert_close(x, WANT.expand(4, 6), atol=1e-8, rtol=0)
    want_cost = 0.5 * ((A @ WANT - B) ** 2).sum()
    torch.testing.assert_close(cost, want_cost.expand(4), rtol=1e-10, atol=0)


def test_a_free_direction_needs_the_floor():
    A0 = A.clone()
    A0[:, 5] = 0.0  # the residuals do not depend on x[5]: H is singular
    x0 = torch.zeros(2, 6, dtype=torch.float64)
    with pytest.raises(RuntimeError, match="singular"):
        levenberg_marquardt(_linear(A0, B), x0, torch.add, 5, 1e-3)
    x, _ = levenberg_marquardt(_linear(A0, B), x0, torch.add, 50, 1e-3, floor=1e-9)
    assert torch.isfinite(x).all()
    want = torch.as_tensor(np.linalg.lstsq(A0[:, :5].numpy(), B.numpy(), rcond=None)[0])
    torch.testing.assert_close(x[:, :5], want.expand(2, 5), atol=1e-6, rtol=0)
    assert x[:, 5].abs().max() < 1e-3  # the free direction barely moves


def test_a_start_whose_steps_all_fail_is_kept():
    base = _linear(A, B)

    def objective(x):
        c, H, g = base(x)
        moved = ~(x == 0).all(1)
        c = torch.where((torch.arange(len(x)) == 1) & moved, torch.nan, c)
        return c, H, g  # start 1: every moved state costs NaN

    x, cost = levenberg_marquardt(
        objective, torch.zeros(2, 6, dtype=torch.float64), torch.add, 10, 1e-3
    )
    assert (x[1] == 0).all()
    assert cost[1] == base(torch.zeros(1, 6, dtype=torch.float64))[0][0]
    assert cost[0] < cost[1]


def test_the_prior_pulls_to_its_centre():
    centre = torch.full((1, 6), 3.0, dtype=torch.float64)
    strong = torch.full((6,), 1e3, dtype=torch.float64)

    def objective(x):
        c, H, g = _linear(A, B)(x)
        return c + 0.5 * ((strong * (x - centre)) ** 2).sum(1), H, g

    def prior(x):
        return torch.diag(strong**2), strong**2 * (x - centre)

    x0 = torch.zeros(1, 6, dtype=torch.float64)
    x, _ = levenberg_marquardt(objective, x0, torch.add, 50, 1e-3, prior=prior)
    torch.testing.assert_close(x, centre, atol=1e-3, rtol=0)


def test_a_tuple_state_moves_by_apply_and_stops_early():
    calls = []

    def objective(state):
        calls.append(1)
        return _linear(A, B)(torch.cat(state, dim=1))

    def apply(state, step):
        return state[0] + step[:, :3], state[1] + step[:, 3:]

    zeros = torch.zeros(3, 3, dtype=torch.float64)
    (a, b), _ = levenberg_marquardt(objective, (zeros, zeros), apply, 100, 1e-3)
    torch.testing.assert_close(torch.cat([a, b], 1), WANT.expand(3, 6), atol=1e-6, rtol=0)
    assert len(calls) < 101  # rtol stopped it once no start moved


def test_each_problem_of_a_batch_stops_as_if_it_ran_alone():
    """Two problems (different data) in one batch: each one's rows equal those of a run of
    that problem alone, though the one converges steps before the other (its rows freeze)."""
    B2 = B + torch.as_tensor(np.random.default_rng(4).normal(scale=30.0, size=20))
    x0 = _starts(5) * torch.tensor([1.0, 1.0, 1e3, 1e3, 1e3])[:, None]  # the second: far off
    group = torch.tensor([0, 0, 1, 1, 1])

    def objective(x):
        b = torch.where((group == 0)[:, None], B, B2)
        r = x @ A.T - b
        return 0.5 * (r**2).sum(1), *normal_equations(
            r, torch.ones_like(r), A.expand(len(x), *A.shape)
        )

    # a loose tolerance stops them short of the minimum, where the step count shows
    x, cost = levenberg_marquardt(objective, x0, torch.add, 30, 10.0, rtol=1e-2, group=group)
    alone0 = levenberg_marquardt(_linear(A, B), x0[:2], torch.add, 30, 10.0, rtol=1e-2)
    alone1 = levenberg_marquardt(_linear(A, B2), x0[2:], torch.add, 30, 10.0, rtol=1e-2)
    torch.testing.assert_close(x, torch.cat([alone0[0], alone1[0]]), atol=1e-12, rtol=0)
    torch.testing.assert_close(cost, torch.cat([alone0[1], alone1[1]]), atol=1e-12, rtol=1e-15)
    # run as one problem, the batch moves on: the first problem's rows differ
    together, _ = levenberg_marquardt(objective, x0, torch.add, 30, 10.0, rtol=1e-2)
    assert not torch.allclose(together[:2], alone0[0], atol=1e-9, rtol=0)


def test_normal_equations_by_row_equal_the_per_point_layout():
    rng = np.random.default_rng(7)
    J = torch.as_tensor(rng.normal(size=(3, 40, 6)))
    r, w = torch.as_tensor(rng.normal(size=(3, 40))), torch.as_tensor(rng.uniform(size=(3, 40)))
    H, g = normal_equations(r, w, J)
    want_H = torch.einsum("bmi,bm,bmj->bij", J, w, J)
    torch.testing.assert_close(H, want_H, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(g, torch.einsum("bmi,bm,bm->bi", J, w, r), atol=1e-12, rtol=1e-12)
    H_t, g_t = normal_equations(r, w, J.transpose(1, 2).contiguous(), by_row=True)
    torch.testing.assert_close(H_t, H, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(g_t, g, atol=1e-12, rtol=1e-12)


def test_fit_threads_hold_one_cpu_thread_and_restore():
    before = torch.get_num_threads()
    with fit_threads(torch.device("cpu")):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
