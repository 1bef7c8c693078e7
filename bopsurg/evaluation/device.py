"""Where the evaluation computes MSSD, MSPD and ADD: the numpy path on the CPU or torch on CUDA.

``bopsurg eval --device`` sets it for the duration of a run (:func:`metric_device`); the
evaluation modules call :func:`mssd`, :func:`mspd` and :func:`add` here instead of
:mod:`bopsurg.metrics` directly. Both paths give the same values (≤ 1e-9 relative).

* ``cpu``: the numpy path (default of the Python API).
* ``cuda``: :mod:`bopsurg.metrics.torch_backend` on the GPU, for every batch.
* ``auto`` (default of ``bopsurg eval``): CUDA for batches of at least :data:`AUTO_MIN_WORK`
  distance evaluations (poses × symmetries × vertices) when torch and a GPU are present; the
  numpy path otherwise. Small evaluations never import torch (seconds of start-up).
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from bopsurg import metrics
from bopsurg.errors import BopsurgError
from bopsurg.metrics.registry import PairBatch
from bopsurg.metrics.symmetry import Symmetries

F64 = NDArray[np.float64]

DEVICES = ("auto", "cpu", "cuda")
#: Poses × symmetries × vertices of one batch from which ``auto`` moves it to the GPU.
AUTO_MIN_WORK = 1e9
#: The torch device of ``cuda`` and ``auto`` (tests point it at the CPU).
TORCH_DEVICE = "cuda"

_device: ContextVar[str] = ContextVar("bopsurg_metric_device", default="cpu")


@lru_cache(maxsize=1)
def cuda_available() -> bool:
    """torch is installed and sees a CUDA device (imports torch; cached)."""
    if importlib.util.find_spec("torch") is None:
        return False
    from bopsurg.metrics import torch_backend

    return torch_backend.resolve_device("auto").type == "cuda"


@contextmanager
def metric_device(device: str) -> Iterator[None]:
    """Compute the batched metrics on ``device`` (``auto``, ``cpu`` or ``cuda``) inside.

    Raises:
        BopsurgError: An unknown device, or ``cuda`` without torch or a GPU.
    """
    if device not in DEVICES:
        raise BopsurgError(f"--device {device}: choose one of {', '.join(DEVICES)}")
    if device == "cuda" and not cuda_available():
        raise BopsurgError("--device cuda: torch with a CUDA GPU is needed (pip install torch)")
    token = _device.set(device)
    try:
        yield
    finally:
        _device.reset(token)


def _on_gpu(work: float) -> bool:
    device = _device.get()
    if device == "cpu":
        return False
    return device == "cuda" or (work >= AUTO_MIN_WORK and cuda_available())


def _n_syms(syms: Symmetries | None) -> int:
    return 1 if syms is None else int(np.asarray(syms[0]).shape[0])


def mssd(R_est: F64, t_est: F64, R_gt: F64, t_gt: F64, pts: F64, syms: Symmetries | None) -> F64:
    """:func:`bopsurg.metrics.mssd` on the chosen device, mm."""
    if _on_gpu(R_est.shape[0] * _n_syms(syms) * pts.shape[0]):
        from bopsurg.metrics import torch_backend as tb

        dev = TORCH_DEVICE
        out: F64 = tb.mssd_torch(R_est, t_est, R_gt, t_gt, pts, syms, device=dev).cpu().numpy()
        return out
    return metrics.mssd(R_est, t_est, R_gt, t_gt, pts, syms)


def mspd(
    R_est: F64, t_est: F64, R_gt: F64, t_gt: F64, K: F64, pts: F64, syms: Symmetries | None
) -> F64:
    """:func:`bopsurg.metrics.mspd` on the chosen device, px."""
    if _on_gpu(R_est.shape[0] * _n_syms(syms) * pts.shape[0]):
        from bopsurg.metrics import torch_backend as tb

        dev = TORCH_DEVICE
        out: F64 = tb.mspd_torch(R_est, t_est, R_gt, t_gt, K, pts, syms, device=dev).cpu().numpy()
        return out
    return metrics.mspd(R_est, t_est, R_gt, t_gt, K, pts, syms)


def add(R_est: F64, t_est: F64, R_gt: F64, t_gt: F64, pts: F64) -> F64:
    """:func:`bopsurg.metrics.add` on the chosen device, mm."""
    if _on_gpu(R_est.shape[0] * pts.shape[0]):
        from bopsurg.metrics import torch_backend as tb

        out: F64 = tb.add_torch(R_est, t_est, R_gt, t_gt, pts, device=TORCH_DEVICE).cpu().numpy()
        return out
    return metrics.add(R_est, t_est, R_gt, t_gt, pts)


def batched(name: str) -> Callable[[PairBatch], F64] | None:
    """The device-dispatching version of registered metric ``name`` (PairBatch → (N,)), or
    None when the metric only has the numpy path."""
    return _BATCHED.get(name)


def _mssd_batch(b: PairBatch) -> F64:
    assert b.pts is not None
    return mssd(b.R_est, b.t_est, b.R_gt, b.t_gt, b.pts, b.syms)


def _mspd_batch(b: PairBatch) -> F64:
    assert b.pts is not None
    assert b.K is not None
    return mspd(b.R_est, b.t_est, b.R_gt, b.t_gt, b.K, b.pts, b.syms)


def _add_batch(b: PairBatch) -> F64:
    assert b.pts is not None
    return add(b.R_est, b.t_est, b.R_gt, b.t_gt, b.pts)


_BATCHED: dict[str, Callable[[PairBatch], F64]] = {
    "mssd": _mssd_batch,
    "mspd": _mspd_batch,
    "add": _add_batch,
}
