"""The torch path equals the numpy path; CUDA tests run only where a GPU is present."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from bopsurg.errors import ShapeError
from bopsurg.metrics import add, mspd, mssd, re, symmetry_transforms, te
from bopsurg.metrics.reference import mspd_ref

from ._data import CONT_Z, K_CAM, arc_model, assert_close, box_model, pose_pairs

torch = pytest.importorskip("torch")
tb = pytest.importorskip("bopsurg.metrics.torch_backend")

pytestmark = pytest.mark.torch
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")

INFO = {
    "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
    "symmetries_discrete": [np.diag([1.0, -1.0, -1.0, 1.0]).reshape(-1).tolist()],
}


def _data(seed: int = 0, n: int = 12):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    pts = arc_model(rng, 300) if seed % 2 else box_model(rng, 300)
    return pose_pairs(rng, n, deg=10.0), pts, symmetry_transforms(INFO, 0.1)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


@pytest.fixture(params=["matmul", "broadcast"])
def products(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Runs a test with the CPU's own small matrix products and with the broadcast sums that
    CUDA uses, so that the GPU's formulation is tested on the CPU too."""
    if request.param == "broadcast":
        monkeypatch.setattr(tb, "BROADCAST_PRODUCTS", frozenset({"cpu", "cuda"}))
    return str(request.param)


@pytest.mark.parametrize(
    "shapes",
    [
        ((5, 3, 3), (5, 3, 3)),
        ((5, 3, 3), (1, 3, 1)),
        ((4, 1, 3, 3), (1, 7, 3, 1)),
        ((6, 6, 4), (6, 4, 1)),
    ],
)
def test_broadcast_products_equal_matmul(shapes: tuple[tuple[int, ...], ...]) -> None:
    g = torch.Generator().manual_seed(0)
    a, b = (torch.randn(s, generator=g, dtype=torch.float64) for s in shapes)
    want = a @ b
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(tb, "BROADCAST_PRODUCTS", frozenset({"cpu"}))
        got = tb._mm(a, b)
    assert got.shape == want.shape
    torch.testing.assert_close(got, want, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("seed", [0, 1])
def test_cpu_torch_equals_numpy(seed: int, products: str) -> None:
    pairs, pts, syms = _data(seed)
    R_est, t_est, R_gt, t_gt = pairs
    assert_close(_np(tb.mssd_torch(*pairs, pts, syms, device="cpu")), mssd(*pairs, pts, syms))
    assert_close(
        _np(tb.mspd_torch(*pairs, K_CAM, pts, syms, device="cpu")), mspd(*pairs, K_CAM, pts, syms)
    )
    assert_close(_np(tb.add_torch(*pairs, pts, device="cpu")), add(*pairs, pts))
    assert_close(_np(tb.re_torch(R_est, R_gt, device="cpu")), re(R_est, R_gt))
    assert_close(_np(tb.te_torch(t_est, t_gt, device="cpu")), te(t_est, t_gt))


def test_torch_inputs_float64_default_and_float32_option() -> None:
    pairs, pts, syms = _data(2)
    tens = [torch.as_tensor(a) for a in pairs]
    out = tb.mssd_torch(*tens, torch.as_tensor(pts), syms, device="cpu")
    assert out.dtype == torch.float64
    assert out.shape == (12,)
    assert_close(_np(out), mssd(*pairs, pts, syms))
    f32 = tb.mspd_torch(*tens, K_CAM, pts, syms, device="cpu", dtype=torch.float32)
    assert f32.dtype == torch.float32
    np.testing.assert_allclose(_np(f32), mspd(*pairs, K_CAM, pts, syms), rtol=1e-3, atol=1e-3)


def test_small_chunks_and_broadcasting(monkeypatch: pytest.MonkeyPatch, products: str) -> None:
    monkeypatch.setattr(tb, "CPU_BUDGET", 5000)  # forces many pose and symmetry chunks
    (R_est, t_est, R_gt, t_gt), pts, syms = _data(3)
    got = tb.mssd_torch(R_est, t_est, R_gt[0], t_gt[0], pts, syms, device="cpu")
    assert_close(_np(got), mssd(R_est, t_est, R_gt[0], t_gt[0], pts, syms))
    got = tb.mspd_torch(R_est, t_est, R_gt[0], t_gt[0], K_CAM, pts, syms, device="cpu")
    assert_close(_np(got), mspd(R_est, t_est, R_gt[0], t_gt[0], K_CAM, pts, syms))


def test_nan_rule_matches_numpy_and_reference(products: str) -> None:
    pts = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 30.0, 5.0], [-20.0, 5.0, -5.0]])
    syms = symmetry_transforms(CONT_Z, 0.5)
    args = (np.eye(3), np.array([1.0, 2.0, 0.0]), np.eye(3), np.zeros(3), K_CAM, pts)
    got = tb.mspd_torch(*args, syms, device="cpu")
    assert np.isnan(_np(got)[0])
    assert np.isnan(mspd_ref(*args, syms))


def test_bad_input_names_the_field() -> None:
    pairs, pts, _ = _data(0)
    with pytest.raises(ShapeError) as exc:
        tb.mssd_torch(pairs[0][:, :2], *pairs[1:], pts, device="cpu")
    assert exc.value.field == "R_est"
    with pytest.raises(ShapeError) as exc:
        tb.add_torch(*pairs, pts * np.nan, device="cpu")
    assert exc.value.field == "pts"
    with pytest.raises(ShapeError) as exc:
        tb.mspd_torch(*pairs, np.eye(4), pts, device="cpu")
    assert exc.value.field == "K"


def test_importing_metrics_does_not_import_torch() -> None:
    code = "import sys, bopsurg.metrics; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


@cuda
def test_cuda_equals_numpy() -> None:
    pairs, pts, syms = _data(4, n=64)
    got = tb.mssd_torch(*pairs, pts, syms, device="cuda")
    assert got.device.type == "cuda"
    assert_close(_np(got), mssd(*pairs, pts, syms))
    assert_close(
        _np(tb.mspd_torch(*pairs, K_CAM, pts, syms, device="cuda")), mspd(*pairs, K_CAM, pts, syms)
    )
    assert_close(_np(tb.add_torch(*pairs, pts, device="cuda")), add(*pairs, pts))
    assert tb.resolve_device("auto").type == "cuda"


@pytest.mark.parametrize("model", ["box", "arc"])
def test_bop_symmetry_set_prunes_to_the_numpy_values(model: str, products: str) -> None:
    """315 symmetries and more vertices than the second bound: every stage of the search runs
    (bounds, refinement, full evaluations of the survivors), values as the numpy path."""
    rng = np.random.default_rng(7)
    pts = box_model(rng, 1200) if model == "box" else arc_model(rng, 1200)
    pairs = pose_pairs(rng, 40, deg=8.0, mm=4.0)
    syms = symmetry_transforms(CONT_Z, 0.01)
    assert_close(_np(tb.mssd_torch(*pairs, pts, syms, device="cpu")), mssd(*pairs, pts, syms))
    assert_close(
        _np(tb.mspd_torch(*pairs, K_CAM, pts, syms, device="cpu")), mspd(*pairs, K_CAM, pts, syms)
    )


def test_off_centre_model_keeps_float64_accuracy(products: str) -> None:
    """A model far from its origin: the squared-distance products are taken about the
    vertices' centre, so the search stays exact (the value is recomputed directly anyway)."""
    rng = np.random.default_rng(8)
    pts = box_model(rng, 400) + np.array([800.0, -500.0, 300.0])
    (R_est, t_est, R_gt, t_gt), _, syms = _data(0)
    t_est, t_gt = t_est + 2000.0, t_gt + 2000.0
    got = tb.mssd_torch(R_est, t_est, R_gt, t_gt, pts, syms, device="cpu")
    assert_close(_np(got), mssd(R_est, t_est, R_gt, t_gt, pts, syms))


def test_float32_bulk_work_returns_near_float64_values(products: str) -> None:
    pairs, pts, syms = _data(5, n=30)
    got = tb.mssd_torch(*pairs, pts, syms, device="cpu", dtype=torch.float32)
    assert got.dtype == torch.float32
    np.testing.assert_allclose(_np(got), mssd(*pairs, pts, syms), rtol=1e-5)


def test_empty_batch_and_explicit_candidates() -> None:
    pairs, pts, syms = _data(6)
    empty = [a[:0] for a in pairs]
    assert tb.mssd_torch(*empty, pts, syms, device="cpu").shape == (0,)
    assert tb.mspd_torch(*empty, K_CAM, pts, syms, device="cpu").shape == (0,)
    got = tb.mssd_torch(*pairs, pts, syms, candidates=pts, device="cpu")  # all vertices
    assert_close(_np(got), mssd(*pairs, pts, syms))
