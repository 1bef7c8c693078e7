"""Fixtures shared by the model tests."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def one_thread():
    """Tiny models on a shared 2-core machine: one thread is faster and deterministic."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


class Killed(Exception):
    """Stands for a training run killed in the middle of an epoch."""


@pytest.fixture
def kill_in_epoch(monkeypatch):
    """``kill_in_epoch(k)``: from then on, a trainer's run (``training.fit``) raises
    :class:`Killed` at the first step of epoch ``k``; ``kill_in_epoch(None)`` stops that."""
    from bopsurg.models import training

    real_fit = training.fit

    def arm(k: int | None) -> type[Killed]:
        def killed_fit(*args, **kwargs):
            step = kwargs["step"]

            def dying(batch, gen, epoch):
                if epoch == k:
                    raise Killed
                return step(batch, gen, epoch)

            return real_fit(*args, **{**kwargs, "step": dying})

        monkeypatch.setattr(training, "fit", real_fit if k is None else killed_fit)
        return Killed

    return arm
