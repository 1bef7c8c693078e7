"""Exponential moving average of a model's weights (model-agnostic).

After each optimiser step, ``update(model)`` blends every floating-point entry of the state
dict (parameters and BatchNorm statistics) as ``ema = d·ema + (1 − d)·model`` with
``d = decay·(1 − exp(−updates/tau))``: the ramp lets the average follow the fast-changing
early weights, then settle to ``decay``. Integer entries (e.g. BN's counters) are copied.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import torch
from torch import nn


class ModelEMA:
    """EMA copy of a model; use ``ema.ema`` (kept in eval mode) for evaluation and export."""

    def __init__(self, model: nn.Module, decay: float = 0.9999, tau: float = 2000.0) -> None:
        self.ema = copy.deepcopy(_unwrap(model)).eval()
        for p in self.ema.parameters():
            p.requires_grad_(False)
        self.decay = decay
        self.tau = tau
        self.updates = 0

    def current_decay(self) -> float:
        """The blending factor d of the next :meth:`update` is computed from ``updates``."""
        return self.decay * (1 - math.exp(-self.updates / self.tau))

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Blend ``model``'s current weights into the average (call after optimizer.step())."""
        self.updates += 1
        d = self.current_decay()
        src = _unwrap(model).state_dict()
        mine, theirs = [], []
        for name, value in self.ema.state_dict().items():
            new = src[name].detach()
            if value.dtype.is_floating_point:
                mine.append(value)
                theirs.append(new.to(value.dtype))
            else:
                value.copy_(new)
        if mine:  # one fused kernel per operation over all tensors, not two per tensor
            torch._foreach_mul_(mine, d)
            torch._foreach_add_(mine, theirs, alpha=1 - d)

    def state_dict(self) -> dict[str, Any]:
        """The averaged weights plus the update count and hyper-parameters."""
        return {
            "ema": self.ema.state_dict(),
            "updates": self.updates,
            "decay": self.decay,
            "tau": self.tau,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.ema.load_state_dict(state["ema"])
        self.updates = int(state["updates"])
        self.decay = float(state.get("decay", self.decay))
        self.tau = float(state.get("tau", self.tau))


def _unwrap(model: nn.Module) -> nn.Module:
    """The module inside (Distributed)DataParallel, else the model itself."""
    wrappers = (nn.DataParallel, nn.parallel.DistributedDataParallel)
    return model.module if isinstance(model, wrappers) else model
