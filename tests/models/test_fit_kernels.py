"""The needle fit's kernels against the plainer ones they replaced, on seeded random input:
the maps' gradients taken where the fit reads them (against bilinear sampling of
``numpy.gradient`` maps), the outline distance from the mask's box (against the whole grid's
transform), the reverse term's Jacobian by component-row lookups (against element gathers and an
einsum), the nearest-sample argmin, and the split of a fit over worker threads."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

from bopsurg.models.predict_config import FitSettings  # noqa: E402
from bopsurg.models.refine import workers  # noqa: E402
from bopsurg.models.refine.arc import ArcModel  # noqa: E402
from bopsurg.models.refine.fit import (  # noqa: E402
    Evidence,
    EvidenceBatch,
    _argmin_last,
    _Nearest,
    _Problem,
    _reverse_jacobian,
)

CPU = torch.device("cpu")


def _old_bilinear(maps: np.ndarray, xy: np.ndarray, size: int) -> np.ndarray:
    """Bilinear samples (C, Q) of maps (C, S, S) at grid coordinates ``xy`` (Q, 2), clamped to
    the border as the fit clamps them: the kernel before the gradients were taken in the fit."""
    x = np.minimum(np.maximum(xy[:, 0], 0.0), size - 1)
    y = np.minimum(np.maximum(xy[:, 1], 0.0), size - 1)
    x0 = np.minimum(np.floor(x).astype(int), size - 2)
    y0 = np.minimum(np.floor(y).astype(int), size - 2)
    fx, fy = x - x0, y - y0
    g = [maps[:, y0, x0], maps[:, y0, x0 + 1], maps[:, y0 + 1, x0], maps[:, y0 + 1, x0 + 1]]
    top_row = g[0] * (1 - fx) + g[1] * fx
    return top_row * (1 - fy) + (g[2] * (1 - fx) + g[3] * fx) * fy


def _with_gradients(f: np.ndarray, step: float) -> np.ndarray:
    """(3, S, S): ``f`` and its x, y gradient (``numpy.gradient``, px apart ``step``)."""
    gy, gx = np.gradient(f, step)
    return np.stack([f, gx, gy])


def _problem(evidence: list[Evidence]) -> _Problem:
    ev = EvidenceBatch.stack(evidence, CPU)
    roi = torch.arange(len(evidence))
    K = torch.eye(3, dtype=torch.float64).expand(len(evidence), 3, 3)
    return _Problem(ArcModel(), ev, K, FitSettings(), roi)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_maps_gradients_sampled_in_the_fit_are_numpys_maps_sampled(seed):
    """Two grids of other sides (the smaller padded) and points inside, on and past their
    borders: the fit's samples of both maps and their gradients equal those of the full
    ``numpy.gradient`` maps to roundoff."""
    rng = np.random.default_rng(seed)
    sides, steps = (23, 17), (0.7, 1.3)
    evidence = [
        Evidence.from_mask(rng.uniform(size=(s, s)) > 0.85, rng.normal(size=2) * 20, st)
        for s, st in zip(sides, steps, strict=True)
    ]
    prob = _problem(evidence)
    q = 300
    uv = np.empty((2, q, 2))
    for i, (e, s) in enumerate(zip(evidence, sides, strict=True)):
        grid = rng.uniform(-2.0, s + 1.0, size=(q, 2))
        grid[:20] = rng.integers(0, s, size=(20, 2))  # on pixel centres and borders
        uv[i] = e.origin + e.step * grid
    for plane, name in enumerate(("dist", "sdf")):
        got = prob._bilinear(torch.full((q,), plane), torch.as_tensor(uv)).numpy()  # (3, 2, Q)
        for i, (e, s) in enumerate(zip(evidence, sides, strict=True)):
            want = _old_bilinear(
                _with_gradients(getattr(e, name), e.step), (uv[i] - e.origin) / e.step, s
            )
            np.testing.assert_allclose(got[:, i], want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_the_outline_distance_from_the_masks_box_is_the_whole_grids(seed):
    """The signed outline distance takes the inside transform on the mask's box grown by one
    pixel: the same as on the whole grid, to float32 rounding (OpenCV's transform rounds
    differently with the image's width), for masks inside, on the border and filling it."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((40, 40), bool)
    y, x = rng.integers(0, 30, size=2)
    mask[y : y + rng.integers(1, 12), x : x + rng.integers(1, 12)] = True
    mask |= rng.uniform(size=mask.shape) > 0.97
    if seed == 3:
        mask[:, :3] = True  # on the grid's border
    step = 0.8
    ev = Evidence.from_mask(mask, np.zeros(2), step)
    whole = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    np.testing.assert_allclose(ev.sdf, ev.dist - step * whole.astype(float), rtol=0, atol=1e-5)
    assert (ev.sdf[~mask] == ev.dist[~mask]).all()


def _old_take(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    flat = index.reshape(index.shape[0], -1, *([1] * (x.ndim - 2)))
    out = torch.gather(x, 1, flat.expand(-1, -1, *x.shape[2:]))
    return out.reshape(*index.shape, *x.shape[2:])


def _old_reverse_jacobian(near: _Nearest, Jp: torch.Tensor, drho: torch.Tensor) -> torch.Tensor:
    k, tk, dv, sv = near.k, near.tk, near.dv, near.sv
    Jc = (1 - tk[..., None]) * _old_take(Jp, k) + tk[..., None] * _old_take(Jp, k + 1)
    seg_n = torch.stack([-sv[..., 1], sv[..., 0]], -1)
    seg_n = seg_n / torch.linalg.vector_norm(seg_n, dim=-1, keepdim=True).clamp(min=1e-12)
    seg_n = torch.where((seg_n * dv).sum(-1, keepdim=True) < 0, -seg_n, seg_n)
    interior = (tk > 0) & (tk < 1)
    unit = dv / near.d_line[..., None].clamp(min=1e-9)
    u_hat = torch.where(interior | (near.d_line[..., None] < 1e-9), seg_n, unit)
    drho_c = (1 - tk) * _old_take(drho, k) + tk * _old_take(drho, k + 1)
    J_rev = -torch.einsum("bnk,bnkp->bnp", u_hat, Jc) - drho_c
    return J_rev * (near.d_rev > 0)[..., None]


def test_the_reverse_jacobian_by_column_lookups_is_the_gathered_one():
    """The component-major kernel (gathers of whole component rows, the coefficients applied
    by multiply-adds) against element gathers and an einsum in the point-major layout."""
    g = torch.Generator().manual_seed(5)
    b, n, m = 5, 70, 12
    tk = torch.rand(b, n, 1, generator=g, dtype=torch.float64)
    tk[:, :10] = torch.tensor([0.0, 1.0], dtype=torch.float64).repeat(5)[:, None]  # the ends
    d_line = torch.rand(b, n, generator=g, dtype=torch.float64) * 3
    d_line[:, 10:12] = 0.0  # a point on the centre line
    near = _Nearest(
        d_rev=torch.where(torch.rand(b, n, generator=g) > 0.3, d_line, 0.0),
        d_line=d_line,
        dv=torch.randn(b, n, 2, generator=g, dtype=torch.float64),
        sv=torch.randn(b, n, 2, generator=g, dtype=torch.float64),
        k=torch.randint(0, m - 1, (b, n), generator=g),
        tk=tk,
    )
    Jp = torch.randn(b, m, 2, 6, generator=g, dtype=torch.float64)
    drho = torch.randn(b, m, 6, generator=g, dtype=torch.float64)
    by_component = near._replace(
        dv=near.dv.permute(2, 0, 1), sv=near.sv.permute(2, 0, 1), tk=near.tk[..., 0]
    )
    got = _reverse_jacobian(by_component, Jp.permute(2, 3, 0, 1), drho.permute(2, 0, 1))
    want = _old_reverse_jacobian(near, Jp, drho)
    assert got.shape == (6, b, n)
    torch.testing.assert_close(got.permute(1, 2, 0), want, rtol=1e-13, atol=1e-13)


def test_the_argmin_is_torchs_with_the_first_of_equals():
    g = torch.Generator().manual_seed(2)
    x = torch.randint(0, 4, (6, 50, 9), generator=g).float()  # many ties
    np.testing.assert_array_equal(_argmin_last(x).numpy(), x.argmin(-1).numpy())
    assert _argmin_last(x).dtype == torch.int64


def test_the_split_keeps_order_and_balances_size():
    rows = np.arange(10, 20)
    groups = workers.split(rows, 2)
    np.testing.assert_array_equal(np.concatenate(groups), rows)
    assert [len(grp) for grp in groups] == [5, 5]
    assert len(workers.split(rows[:1], 4)) == 1
    assert [len(grp) for grp in workers.split(rows, 3)] == [4, 3, 3]
    assert [len(grp) for grp in workers.split(rows[:2], 3)] == [1, 1]
    assert [len(grp) for grp in workers.split(rows[:0], 2)] == [0]


def test_workers_run_in_order_and_raise():
    assert workers.run(lambda g: g * 2, [1, 2, 3]) == [2, 4, 6]

    def boom(g: int) -> int:
        if g == 0:
            raise ValueError("no")
        return g

    with pytest.raises(ValueError, match="no"):
        workers.run(boom, [0, 1])


def test_cpu_workers_give_the_threads_and_hold_one_per_op():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with workers.cpu_workers(CPU) as parts:
            assert parts == 2
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_forked_child_starts_its_own_pool():
    """A child forked after the pool started has none of its threads: it must not wait on
    them."""
    mp = pytest.importorskip("multiprocessing")
    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork on this platform")
    assert workers.run(lambda g: g, [1, 2]) == [1, 2]  # the parent's pool exists
    ctx = mp.get_context("fork")
    with ctx.Pool(1) as pool:
        assert pool.apply_async(workers.run, (abs, [-1, -2])).get(timeout=60) == [1, 2]
