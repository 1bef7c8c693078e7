"""The one epoch loop of the detector and pose trainers, and what it needs: devices, seeds,
schedules, resumable state, logs.

A trainer builds its data and network, then hands :func:`fit` a *step function* (one batch of
indices → named scalar losses with a ``"total"``) and a *validation function* (EMA network →
named metrics). :func:`fit` owns everything else: the AdamW optimiser with decay on weights
only, the warm-up + flat + cosine schedule, the EMA, gradient clipping, resuming, the
validation cadence, the exported checkpoint, the training state and the log.

A training run lives in one folder::

    OUT/train_state.pt    model, EMA, optimiser and progress (weights-only; resumed from)
    OUT/train_state.json  the run's settings; a resume with other settings is refused
    OUT/log.jsonl         one JSON line per epoch: losses, validation, lr, seconds
    OUT/NAME.pt + .json   the exported model (EMA weights), rewritten after every epoch
    OUT/validated/eNNN/   a copy of the export after each validated epoch NNN (1-based), so
                          that the epoch can be chosen afterwards on the validation splits

Randomness: every epoch draws from ``torch.Generator().manual_seed(seed * 1000 + epoch)``
(the shuffle first, then the batch augmentations in step order), and per-sample augmentations
from seeds of (seed, epoch, sample index) (:func:`bopsurg.models.photometric.sample_seed`), so
a run killed after epoch k and resumed gives the same weights as an uninterrupted one.

Data: with a ``load`` function, :func:`fit` hands it the epoch's index batches up front and
the step receives what it yields (batches read from disk, possibly by background workers
that read ahead); without, the step receives the index tensors.
"""

from __future__ import annotations

import json
import logging
import math
import platform
import shutil
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from bopsurg.atomic import atomic_path, write_text
from bopsurg.bop.dataset import BopDataset
from bopsurg.errors import BopsurgError, CheckpointError
from bopsurg.models.checkpoint import load_checkpoint, load_tensors, load_weights, save_checkpoint
from bopsurg.models.data import open_split, split_scenes
from bopsurg.models.ema import ModelEMA

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


def batches(
    n: int,
    batch_size: int,
    gen: torch.Generator,
    *,
    drop_last: bool = True,
    steps: int = 0,
) -> Iterator[torch.Tensor]:
    """Shuffled index batches over ``range(n)``: one pass (the last partial batch dropped
    with ``drop_last``), or with ``steps > 0`` exactly that many full batches from shuffles
    drawn one after the other (every sample once before any twice)."""
    if steps <= 0:
        perm = torch.randperm(n, generator=gen)
        stop = n - n % batch_size if drop_last and n >= batch_size else n
        for i in range(0, stop, batch_size):
            yield perm[i : i + batch_size]
        return
    need = steps * batch_size
    perm = torch.cat([torch.randperm(n, generator=gen) for _ in range(-(-need // n))])
    for i in range(steps):
        yield perm[i * batch_size : (i + 1) * batch_size]


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
    decay: list[nn.Parameter] = []
    no_decay: list[nn.Parameter] = []
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
    model: dict[str, Any] = field(default_factory=dict)


class RunFolder:
    """The files of one training run (see the module docs)."""

    def __init__(
        self,
        out: str | Path,
        settings: RunSettings,
        *,
        restart: bool = False,
        legacy: dict[str, Any] | None = None,
    ) -> None:
        self.out = Path(out)
        self.settings = settings
        self.legacy = legacy or {}
        self.out.mkdir(parents=True, exist_ok=True)
        self.state_path = self.out / "train_state.pt"
        self.settings_path = self.out / "train_state.json"
        self.log_path = self.out / "log.jsonl"
        self.validated = self.out / "validated"  # a copy of each validated epoch's export
        if restart:
            for p in (self.state_path, self.settings_path, self.log_path):
                p.unlink(missing_ok=True)
            shutil.rmtree(self.validated, ignore_errors=True)

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
            legacy = _resumable(json.loads(json.dumps(self.legacy)))
            # a setting added after the run was written is taken at what the run used then
            saved = {**{k: v for k, v in legacy.items() if k not in saved}, **saved}
            diff = sorted(k for k in {*mine, *saved} if saved.get(k) != mine.get(k))
            if diff:
                changes = "; ".join(f"{k}: {saved.get(k)!r} -> {mine.get(k)!r}" for k in diff[:3])
                raise BopsurgError(
                    f"{self.out}: holds a run with other settings ({', '.join(diff)}); "
                    f"{changes}{' ...' if len(diff) > 3 else ''}; "
                    "use another --out or --restart"
                )
        try:
            state: dict[str, Any] = load_tensors(self.state_path)
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


@dataclass(frozen=True)
class Splits:
    """Where a run's samples come from.

    Attributes:
        train: The training split.
        train_ids: Its scenes that train.
        val: The validation split (``train`` when scenes of it are held out).
        val_ids: The validation scenes of ``val``.
    """

    train: BopDataset
    train_ids: list[int]
    val: BopDataset
    val_ids: list[int]


def open_splits(dataset: str | Path, split: str, val_split: str | None) -> Splits:
    """``split`` of ``dataset`` for training; validation on all of ``val_split``, or, when
    None, on one scene in 10 of ``split`` held out (a seeded draw of whole scenes: no shared
    trajectories). Either may name several splits, comma-separated
    (:class:`~bopsurg.models.data.SplitUnion`)."""
    ds = open_split(dataset, split)
    val_ds = open_split(dataset, val_split) if val_split else None
    train_ids, val_ids = split_scenes(ds, 10, val_ds)
    if val_ds is None:
        return Splits(ds, train_ids, ds, val_ids)
    return Splits(ds, train_ids, val_ds, val_ds.scene_ids)


def open_run(
    out: str | Path,
    settings: RunSettings,
    *,
    restart: bool,
    legacy: dict[str, Any] | None = None,
) -> tuple[RunFolder, dict[str, Any] | None]:
    """The run folder ``out`` and its saved state (None: a fresh run), then torch's global
    generator seeded with ``settings.seed`` for the network's initialisation.

    Args:
        out: The run folder.
        settings: This run's settings; a saved run with other settings is refused.
        restart: Discard a previous run in ``out``.
        legacy: Settings (nested like :class:`RunSettings`' dict) that runs written by an
            older bopsurg lack, with the value they implicitly had (so such runs resume).

    Raises:
        BopsurgError: ``out`` holds a run with other settings.
    """
    run = RunFolder(out, settings, restart=restart, legacy=legacy)
    state = run.load_state()
    torch.manual_seed(settings.seed)
    return run, state


def finished(run: RunFolder, state: dict[str, Any] | None, export: Path) -> bool:
    """Whether a resumed run has nothing left to train: its state holds the recipe's last
    epoch and its export exists (a trainer then returns ``export`` before loading any data)."""
    epochs = run.settings.recipe.get("epochs")
    done = state is not None and epochs is not None and int(state["epoch"]) + 1 >= int(epochs)
    if done and export.is_file():
        log.info("%s: all %d epochs trained; nothing to resume", run.out, epochs)
        return True
    return False


def init_weights(
    model: nn.Module,
    path: str | Path,
    kind: str,
    config: dict[str, Any],
    meta: dict[str, Any] | None = None,
    training_only: frozenset[str] = frozenset(),
) -> None:
    """Start ``model`` from the exported checkpoint ``path`` (fine-tuning).

    The checkpoint must hold a ``kind`` model of the same ``config``, but for the
    ``training_only`` keys (loss weights ..., which a fine-tuning run may change). With
    ``meta``, every key of it that the checkpoint's meta also has must agree (the pose head's
    object normaliser and surface regions: weights trained for other regions would be
    mislabelled).

    Raises:
        CheckpointError: Missing, corrupt or another kind of checkpoint.
        BopsurgError: Another architecture or object geometry than this run's.
    """
    state, info = load_checkpoint(path, kind)
    where = f"recipe.init {path}"
    keys = {*config, *info["config"]} - training_only
    diff = sorted(k for k in keys if config.get(k) != info["config"].get(k))
    if diff:
        k = diff[0]
        raise BopsurgError(
            f"{where}: its {kind} config differs from this run's ({', '.join(diff)}; "
            f"{k}: {info['config'].get(k)!r} there, {config.get(k)!r} here)"
        )
    theirs = info.get("meta") or {}
    for k, mine in (meta or {}).items():
        if k not in theirs:
            continue
        a, b = theirs[k], mine
        same = (
            np.allclose(np.asarray(a, float), np.asarray(b, float), atol=1e-4)
            if isinstance(a, list | float)
            and isinstance(b, list | float)
            and np.shape(a) == np.shape(b)
            else a == b
        )
        if not same:
            raise BopsurgError(f"{where}: its meta {k!r} differs from this dataset's object")
    load_weights(model, state, path)
    log.info("%s: starting from %s", kind, path)


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


#: What :attr:`Schedule.precision` may be.
PRECISIONS = ("fp32", "bf16")


@dataclass(frozen=True)
class Schedule:
    """The hyper-parameters the epoch loop reads from a trainer's recipe.

    Attributes:
        epochs: Epochs of the whole run (a resume may raise it).
        batch_size: Samples per step; an epoch is ``n_train // batch_size`` steps.
        lr: Peak learning rate.
        weight_decay: AdamW decay of conv/linear weights.
        warmup_epochs: Quadratic warm-up length, epochs.
        anneal_from: Start of the cosine, a fraction of all steps (0: right after warm-up).
        val_every: Validation cadence, epochs (the last epoch is always validated).
        steps_per_epoch: Steps of an epoch; 0: one pass over the training samples
            (``n_train // batch_size``). Trainers whose data is drawn rather than passed
            over (the needle segmenter and end classifier) count their run in steps; an
            epoch is then the unit of validation, resuming and export.
    """

    epochs: int
    batch_size: int
    lr: float
    weight_decay: float
    warmup_epochs: float
    anneal_from: float
    val_every: int
    steps_per_epoch: int = 0
    precision: str = "fp32"

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got "
                             f"{self.precision!r}")  # fmt: skip

    def epoch_steps(self, n_train: int) -> int:
        """Optimiser steps of one epoch over ``n_train`` samples."""
        return self.steps_per_epoch or max(1, n_train // self.batch_size)


#: One training step's losses: ``(batch, epoch generator, epoch) → {name: scalar}`` with a
#: ``"total"`` that is back-propagated; every entry is averaged into the log. The batch is the
#: index tensor, or what :data:`LoadFn` yields for it.
StepFn = Callable[[Any, torch.Generator, int], dict[str, torch.Tensor]]
#: Reads an epoch's index batches: ``[indices, ...] → the batches, in that order``.
LoadFn = Callable[[Sequence[torch.Tensor]], Iterable[Any]]
#: Validation of the EMA network: ``network → {name: value}`` (logged with a ``val_`` prefix).
ValidateFn = Callable[[nn.Module], dict[str, float]]


@dataclass(frozen=True)
class Export:
    """The checkpoint :func:`fit` writes after every epoch (EMA weights, float16).

    Attributes:
        path: The ``.pt`` file (its ``.json`` twin is written beside it).
        kind: ``"detector"`` or ``"pose"``, checked on load.
        config: The network's config dict.
        meta: What the estimator needs beside the weights (classes, object geometry ...);
            ``fit`` adds the epoch, the validation and the provenance.
    """

    path: Path
    kind: str
    config: dict[str, Any]
    meta: dict[str, Any]


@dataclass
class _Progress:
    """Optimiser, EMA and the first epoch to run: fresh, or restored from a saved state."""

    opt: torch.optim.Optimizer
    ema: ModelEMA
    start: int
    timer: Timer


def fit(
    model: nn.Module,
    run: RunFolder,
    state: dict[str, Any] | None,
    schedule: Schedule,
    *,
    n_train: int,
    step: StepFn,
    validate: ValidateFn,
    export: Export,
    device: torch.device,
    progress: bool = True,
    load: LoadFn | None = None,
) -> Path:
    """Train ``model`` for the remaining epochs of ``schedule``; returns ``export.path``.

    Per step: the learning rate of :func:`flat_cosine_lr`, ``step``'s losses, backward,
    gradient norm clipped to 10, AdamW, EMA update. Per epoch: validation of the EMA network
    after every ``val_every``-th and the last epoch, then the export (and for a validated
    epoch a copy of it in ``OUT/validated/eNNN/``), the training state and the log line, so a
    run killed at any point resumes after its last finished epoch.

    Args:
        model: The network, on ``device``, freshly initialised (seeded by the caller).
        run: The run folder.
        state: :meth:`RunFolder.load_state`'s result (None: a fresh run).
        schedule: Epochs, batch size, learning-rate schedule, validation cadence.
        n_train: Training samples; each epoch is ``n_train // batch_size`` steps.
        step: Losses of one batch.
        validate: Metrics of the EMA network.
        export: Where and how the exported checkpoint is written.
        device: Where the model lives (recorded in the provenance).
        progress: Show a progress bar per epoch.
        load: Reads the epoch's index batches (from disk); ``step`` then gets its batches.
    """
    if device.type == "cuda":  # convolutions run NHWC on tensor cores
        model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        # the input sizes are fixed per run: cuDNN times its algorithms once and keeps the
        # fastest (GPU runs are not bitwise repeatable anyway: atomics in the backward)
        torch.backends.cudnn.benchmark = True
    p = _start(model, state, schedule)
    for epoch in range(p.start, schedule.epochs):
        gen = epoch_generator(run.settings.seed, epoch)
        # the shuffle is drawn first, so a loader may read ahead of the augmentation draws
        order = list(batches(n_train, schedule.batch_size, gen, steps=schedule.steps_per_epoch))
        bar = tqdm(
            order if load is None else load(order), total=len(order),
            desc=f"{export.kind} {epoch + 1}/{schedule.epochs}", leave=False,
            disable=not (progress and sys.stderr.isatty()),  # no bar in a log file
        )  # fmt: skip
        record: dict[str, Any] = {"epoch": epoch}
        record.update(_train_epoch(model, p, schedule, n_train, bar, step, gen, epoch))
        if epoch == schedule.epochs - 1 or (epoch + 1) % schedule.val_every == 0:
            record.update({f"val_{n}": v for n, v in validate(p.ema.ema).items()})
        record["seconds"] = round(p.timer.seconds, 1)
        log.info("%s epoch %d: %s", export.kind, epoch + 1, format_record(record))
        _end_epoch(model, run, p, export, record, device)
    return export.path


def _train_epoch(
    model: nn.Module,
    p: _Progress,
    schedule: Schedule,
    n_train: int,
    bar: tqdm[Any],
    step: StepFn,
    gen: torch.Generator,
    epoch: int,
) -> dict[str, float]:
    """The steps of one epoch over ``bar``'s batches: the last learning rate, the mean of
    each loss (``loss_NAME``), and where the time went: ``samples_per_s`` and
    ``data_wait``, the share of the epoch spent waiting for the loader's next batch."""
    steps_per_epoch = schedule.epoch_steps(n_train)
    total = schedule.epochs * steps_per_epoch
    warmup = int(schedule.warmup_epochs * steps_per_epoch)
    sums: dict[str, torch.Tensor] = {}
    lr, waited, start = p.opt.param_groups[0]["lr"], 0.0, time.perf_counter()
    device = next(model.parameters()).device
    autocast = torch.autocast(device.type, torch.bfloat16, enabled=schedule.precision == "bf16")
    model.train()
    batches_in = iter(bar)
    for k in range(len(bar)):
        t = time.perf_counter()
        batch = next(batches_in)
        waited += time.perf_counter() - t
        lr = flat_cosine_lr(epoch * steps_per_epoch + k, total, warmup, schedule.anneal_from,
                            schedule.lr)  # fmt: skip
        for g in p.opt.param_groups:
            g["lr"] = lr
        with autocast:
            losses = step(batch, gen, epoch)
        p.opt.zero_grad(set_to_none=True)
        losses["total"].backward()  # type: ignore[no-untyped-call]
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        p.opt.step()
        p.ema.update(model)
        for name, v in losses.items():  # summed where they are: no wait for the device
            sums[name] = sums.get(name, 0) + torch.as_tensor(v).detach().float()
        if not bar.disable:
            bar.set_postfix(loss=f"{losses['total'].item():.3f}")
    means = {f"loss_{n}": float(v) / steps_per_epoch for n, v in sums.items()}
    seconds = time.perf_counter() - start  # after float(): the device has caught up
    speed = {"samples_per_s": len(bar) * schedule.batch_size / seconds,
             "data_wait": waited / seconds}  # fmt: skip
    return {"lr": float(lr), **means, **speed}


def _start(model: nn.Module, state: dict[str, Any] | None, schedule: Schedule) -> _Progress:
    """Optimiser and EMA of ``model``, restored from ``state`` when resuming."""
    ema = ModelEMA(model, tau=500.0)
    # on a GPU one fused kernel per step for all parameters (a small network's step is
    # otherwise launch-bound); the CPU keeps the default, so CPU runs stay as recorded
    fused = next(model.parameters()).device.type == "cuda"
    opt = torch.optim.AdamW(
        param_groups(model, schedule.weight_decay), lr=schedule.lr, fused=fused or None
    )
    if state is None:
        return _Progress(opt, ema, 0, Timer())
    model.load_state_dict(state["model"])
    ema.load_state_dict(state["ema"])
    opt.load_state_dict(state["optimizer"])
    return _Progress(opt, ema, int(state["epoch"]) + 1, Timer(float(state["seconds"])))


def _end_epoch(
    model: nn.Module,
    run: RunFolder,
    p: _Progress,
    export: Export,
    record: dict[str, Any],
    device: torch.device,
) -> None:
    """Export the EMA weights (and keep a copy of a validated epoch's), then save the
    training state and the log line of the epoch."""
    epoch = record["epoch"]
    validation = {k: v for k, v in record.items() if k.startswith("val_")}
    meta = {
        **export.meta, "epoch": epoch + 1, "validation": validation,
        **provenance(run.settings, p.timer.seconds, device),
    }  # fmt: skip
    state = p.ema.ema.state_dict()
    save_checkpoint(
        export.path, state, kind=export.kind, config=export.config, meta=meta, half=True
    )
    if validation:  # before the state: a resume after this epoch finds the copy in place
        kept = run.validated / f"e{epoch + 1:03d}" / export.path.name
        kept.parent.mkdir(parents=True, exist_ok=True)
        save_checkpoint(kept, state, kind=export.kind, config=export.config, meta=meta, half=True)
    run.save_state(
        {
            "model": model.state_dict(), "ema": p.ema.state_dict(),
            "optimizer": p.opt.state_dict(), "epoch": epoch, "seconds": p.timer.seconds,
        }
    )  # fmt: skip
    run.append_log(record)
