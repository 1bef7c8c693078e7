"""``bopsurg eval --device``: the evaluation's MSSD, MSPD and ADD on numpy or torch."""

from __future__ import annotations

import numpy as np
import pytest

from bopsurg import metrics
from bopsurg.errors import BopsurgError
from bopsurg.evaluation import device
from tests.bopsurg.metrics._data import CONT_Z, K_CAM, arc_model, assert_close, pose_pairs


def test_unknown_device_is_refused() -> None:
    with pytest.raises(BopsurgError, match="--device tpu"), device.metric_device("tpu"):
        pass


def test_cuda_without_a_gpu_is_one_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(device, "cuda_available", lambda: False)
    error = pytest.raises(BopsurgError, match="--device cuda: torch with a CUDA GPU")
    with error, device.metric_device("cuda"):
        pass


def test_auto_keeps_small_batches_on_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_torch() -> bool:
        raise AssertionError("a small batch must not look for torch")

    monkeypatch.setattr(device, "cuda_available", no_torch)
    rng = np.random.default_rng(0)
    pts = arc_model(rng, 200)
    pairs = pose_pairs(rng, 5)
    with device.metric_device("auto"):
        assert_close(device.add(*pairs, pts), metrics.add(*pairs, pts))


def test_torch_dispatch_equals_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("torch")
    monkeypatch.setattr(device, "cuda_available", lambda: True)
    monkeypatch.setattr(device, "TORCH_DEVICE", "cpu")  # the torch path, on the CPU
    monkeypatch.setattr(device, "AUTO_MIN_WORK", 0)
    rng = np.random.default_rng(1)
    pts = arc_model(rng, 300)
    pairs = pose_pairs(rng, 8)
    syms = metrics.symmetry_transforms(CONT_Z, 0.1)
    for choice in ("cuda", "auto"):
        with device.metric_device(choice):
            assert_close(device.mssd(*pairs, pts, syms), metrics.mssd(*pairs, pts, syms))
            got = device.mspd(*pairs, K_CAM, pts, syms)
            assert_close(got, metrics.mspd(*pairs, K_CAM, pts, syms))
            assert_close(device.add(*pairs, pts), metrics.add(*pairs, pts))
