"""The shared epoch loop (``models/training.fit``) on a toy regression: its contract, not a model.

A linear layer learns y = 2x from 12 samples; the step and validation functions are the only
model-specific parts, as in the detector and pose trainers.
"""

from __future__ import annotations

import json

import pytest

torch = pytest.importorskip("torch")

from bopsurg.models import training  # noqa: E402
from bopsurg.models.checkpoint import load_tensors  # noqa: E402

X = torch.linspace(-1, 1, 12)[:, None]
Y = 2 * X


class Killed(Exception):
    """Stands for a run killed in the middle of an epoch."""


def _run(out, epochs, *, val_every=2, kill_in=None):
    schedule = training.Schedule(epochs, 4, 0.1, 0.0, 1.0, 0.5, val_every)
    settings = training.RunSettings("toy", "none", "train", "test", 3, {"lr": 0.1})
    run, state = training.open_run(out, settings, restart=False)
    model = torch.nn.Linear(1, 1)
    calls = []

    def step(idx, gen, epoch):
        if epoch == kill_in:
            raise Killed
        calls.append((epoch, idx.tolist()))
        loss = (model(X[idx]) - Y[idx]).pow(2).mean()
        return {"mse": loss.detach(), "total": loss}

    def validate(net):
        with torch.no_grad():
            return {"mse": float((net(X) - Y).pow(2).mean())}

    export = training.Export(out / "toy.pt", "toy", {"width": 1}, {"note": "x"})
    path = training.fit(
        model, run, state, schedule, n_train=len(X), step=step, validate=validate,
        export=export, device=torch.device("cpu"), progress=False,
    )  # fmt: skip
    return path, calls


def test_fit_steps_validates_on_cadence_and_exports(tmp_path):
    path, calls = _run(tmp_path, 5)
    assert [e for e, _ in calls] == [e for e in range(5) for _ in range(3)]  # 12 // 4 steps
    for epoch in range(5):  # every sample once per epoch
        assert sorted(i for e, idx in calls if e == epoch for i in idx) == list(range(12))
    log = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in log] == list(range(5))
    assert [("val_mse" in r) for r in log] == [False, True, False, True, True]  # 2nd, 4th, last
    assert log[-1]["loss_mse"] == pytest.approx(log[-1]["loss_total"])
    assert log[-1]["loss_mse"] < log[0]["loss_mse"]
    info = json.loads(path.with_suffix(".json").read_text())
    assert info["kind"] == "toy"
    assert info["meta"]["note"] == "x"
    assert info["meta"]["epoch"] == 5
    assert info["meta"]["validation"] == {"val_mse": log[-1]["val_mse"]}
    assert load_tensors(path)["weight"].dtype == torch.float16  # EMA weights, half
    # a copy of each validated epoch's export, to choose the epoch on validation afterwards
    kept = sorted(p.name for p in (tmp_path / "validated").iterdir())
    assert kept == ["e002", "e004", "e005"]
    e2 = json.loads((tmp_path / "validated" / "e002" / "toy.json").read_text())
    assert e2["meta"]["epoch"] == 2
    assert e2["meta"]["validation"] == {"val_mse": log[1]["val_mse"]}
    for k, v in load_tensors(tmp_path / "validated" / "e005" / "toy.pt").items():
        torch.testing.assert_close(v, load_tensors(path)[k], rtol=0, atol=0)  # the last: the export


def test_a_restart_drops_the_previous_runs_validated_copies(tmp_path):
    _run(tmp_path, 2, val_every=1)
    assert (tmp_path / "validated" / "e002").is_dir()
    settings = training.RunSettings("toy", "none", "train", "test", 3, {"lr": 0.1})
    training.open_run(tmp_path, settings, restart=True)
    assert not (tmp_path / "validated").exists()


def test_a_resumed_fit_replays_the_same_batches_and_ends_with_the_same_weights(tmp_path):
    full, calls_full = _run(tmp_path / "a", 4)
    with pytest.raises(Killed):
        _run(tmp_path / "b", 4, kill_in=2)
    part, calls_rest = _run(tmp_path / "b", 4)
    assert calls_rest == calls_full[6:]  # epochs 2 and 3 only, same shuffles
    a, b = load_tensors(full), load_tensors(part)
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    state = torch.load(tmp_path / "b" / "train_state.pt", weights_only=True)
    assert state["epoch"] == 3


def test_a_fixed_step_count_draws_from_consecutive_shuffles():
    """``steps_per_epoch``: that many full batches; every sample once before any twice."""
    gen = torch.Generator().manual_seed(0)
    got = list(training.batches(5, 3, gen, steps=4))
    assert [len(b) for b in got] == [3, 3, 3, 3]
    flat = torch.cat(got).tolist()
    assert sorted(flat[:5]) == list(range(5))
    assert sorted(flat[5:10]) == list(range(5))
    assert training.Schedule(1, 3, 0.1, 0.0, 0.0, 0.0, 1, 4).epoch_steps(5) == 4
    assert training.Schedule(1, 3, 0.1, 0.0, 0.0, 0.0, 1).epoch_steps(7) == 2
    with pytest.raises(ValueError, match="precision"):
        training.Schedule(1, 3, 0.1, 0.0, 0.0, 0.0, 1, precision="fp16")


@pytest.mark.parametrize(
    "device",
    ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
        not torch.cuda.is_available(), reason="needs a CUDA GPU"))],
)  # fmt: skip
def test_the_optimiser_is_fused_on_a_gpu_only(device):
    """One fused AdamW kernel on a GPU; the CPU keeps the default (its runs stay as recorded)."""
    schedule = training.Schedule(1, 4, 0.1, 0.0, 1.0, 0.5, 1)
    p = training._start(torch.nn.Linear(1, 1).to(device), None, schedule)
    assert bool(p.opt.defaults["fused"]) == (device == "cuda")
