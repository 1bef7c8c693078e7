"""What the detector and pose trainers share: devices, seeds, schedules, resumable state, logs.

A training run lives in one folder::

    OUT/train_state.pt    model, EMA, optimiser and progress (weights-only; resumed from)
    OUT/train_state.json  the run's settings; a resume with other settings is refused
    OUT/log.jsonl         one JSON line per epoch: losses, validation, lr, seconds
    OUT/NAME.pt + .json   the exported model (EMA weights), rewritten after every epoch

Randomness: every epoch draws from ``torch.Generator().manual_seed(seed * 1000 + epoch)``,
so a run killed after epoch k and resumed gives the same weights as an uninterrupted one.
"""

from __future__ import annotations

import json
import logging
import math
import platform
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from bopsurg.atomic import atomic_path, write_text
from bopsurg.errors import BopsurgError, CheckpointError
from bopsurg.models.checkpoint import load_tensors

log = logging.getLogger(__name__)


def resolve_device(name: str = "auto") -> torch.device:
    """``"auto"`` → CUDA when available, else CPU; otherwise the named device, checked."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise BopsurgError(f"--device: unknown device {name!r}") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise BopsurgError(f"--device {name}: CUDA is not available on this machine")
    return device


def epoch_generator(seed: int, epoch: int) -> torch.Generator:
    """The CPU generator every random choice of one epoch draws from."""
    return torch.Generator().manual_seed(seed * 1000 + epoch)


def batches(n: int, batch_size: int, gen: torch.Generator, *, drop_last: bool = True) -> Iterator:
    """Shuffled index batches over ``range(n)``."""
    perm = torch.randperm(n, generator=gen)
    stop = n - n % batch_size if drop_last and n >= batch_size else n
    for i in range(0, stop, batch_size):
        yield perm[i : i + batch_size]


def flat_cosine_lr(step: int, total: int, warmup: int, anneal_from: float, base: float) -> float:
    """GDR-Net's ``flat_and_anneal`` (and YOLOX's warm-up + cosine with anneal_from 0):
    quadratic warm-up from 0 over ``warmup`` steps, flat, then cosine to 5 % of ``base``
    from ``anneal_from`` x total."""
    if step < warmup:
        return base * ((step + 1) / warmup) ** 2
    start = int(anneal_from * total)
    if step < start:
        return base
    frac = min(1.0, (step - start) / max(1, total - start))
    return base * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * frac)))


def param_groups(model: nn.Module, weight_decay: float) -> list[dict[str, Any]]:
    """Weight decay on conv/linear weights only (not norms or biases), as YOLOX and GDRNPP."""
    decay, no_decay = [], []
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        (decay if p.ndim > 1 and not name.endswith(".bias") else no_decay).append(p)
    return [
        {"params": decay, "weight_decay": weight_decay},
        {"params": no_decay, "weight_decay": 0.0},
    ]


@dataclass
class RunSettings:
    """Settings of a training run that must not change on resume (recorded in the output)."""

    kind: str
    dataset: str
    split: str
    preset: str
    seed: int
    recipe: dict[str, Any]
    extra: dict[str, Any] = field(default_factory=dict)


class RunFolder:
    """The files of one training run (see the module docs)."""

    def __init__(self, out: str | Path, settings: RunSettings, *, restart: bool = False) -> None:
        self.out = Path(out)
        self.settings = settings
        self.out.mkdir(parents=True, exist_ok=True)
        self.state_path = self.out / "train_state.pt"
        self.settings_path = self.out / "train_state.json"
        self.log_path = self.out / "log.jsonl"
        if restart:
            for p in (self.state_path, self.settings_path, self.log_path):
                p.unlink(missing_ok=True)

    def load_state(self) -> dict[str, Any] | None:
        """The saved training state, or None for a fresh run.

        Raises:
            BopsurgError: The folder holds a run with other settings (a resume would mix them).
        """
        if not self.state_path.is_file():
            return None
        if self.settings_path.is_file():
            saved = _resumable(json.loads(self.settings_path.read_text(encoding="utf-8")))
            mine = _resumable(json.loads(json.dumps(asdict(self.settings))))
            diff = sorted(k for k in {*mine, *saved} if saved.get(k) != mine.get(k))
            if diff:
                raise BopsurgError(
                    f"{self.out}: holds a run with other settings ({', '.join(diff)}); "
                    "use another --out or --restart"
                )
        try:
            state = load_tensors(self.state_path)
        except CheckpointError as err:
            raise BopsurgError(f"{err}; use --restart to start over") from err
        log.info("resuming %s after epoch %d", self.out, state["epoch"])
        return state

    def save_state(self, state: dict[str, Any]) -> None:
        """Atomically replace the training state (and the settings next to it)."""
        with atomic_path(self.state_path) as tmp:
            torch.save(state, tmp)
        write_text(self.settings_path, json.dumps(asdict(self.settings), indent=2) + "\n")

    def append_log(self, record: dict[str, Any]) -> None:
        """One line of ``log.jsonl`` (rewritten atomically so a kill cannot tear it)."""
        lines = self.read_log()
        epoch = record.get("epoch")
        lines = [r for r in lines if r.get("epoch") != epoch] + [record]
        write_text(self.log_path, "".join(json.dumps(r) + "\n" for r in lines))

    def read_log(self) -> list[dict[str, Any]]:
        """The epochs logged so far."""
        if not self.log_path.is_file():
            return []
        return [json.loads(ln) for ln in self.log_path.read_text().splitlines() if ln.strip()]


def _resumable(settings: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Settings that must match for a resume, flattened to dotted keys (``recipe.lr``): all but
    the epoch count, which may grow."""
    out: dict[str, Any] = {}
    for k, v in settings.items():
        if k == "epochs":
            continue
        if isinstance(v, dict):
            out.update(_resumable(v, f"{k}."))
        else:
            out[prefix + k] = v
    return out


def provenance(settings: RunSettings, seconds: float, device: torch.device) -> dict[str, Any]:
    """What a checkpoint records about how it was made."""
    return {
        "settings": asdict(settings),
        "train_seconds": round(seconds, 1),
        "device": str(device) if device.type == "cpu" else torch.cuda.get_device_name(device),
        "torch": torch.__version__,
        "host": platform.machine(),
        "threads": torch.get_num_threads(),
    }


def format_record(record: dict[str, Any]) -> str:
    """One log line of an epoch record."""
    return " ".join(
        f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in record.items()
    )


class Timer:
    """Wall-clock seconds, accumulated across resumes."""

    def __init__(self, already: float = 0.0) -> None:
        self.start = time.perf_counter() - already

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.start
