"""The CPU's cores for the segmenter's passes over a batch's images, side by side.

The segmenter's small convolutions gain less from a second intra-op thread than from a
second image, so the refinement stage runs the images' passes as groups at once on a pool of
threads, one intra-op thread each (torch lets go of the GIL inside its kernels), joined in
their order; as many groups as torch had threads when the stage began
(``torch.get_num_threads()``, the budget ``bopsurg predict`` gives the networks), so a run on
one thread splits nothing.

The fits do not run here: their ops are small (thousands of elements), so two threads
mostly hand the GIL to each other; they run on the calling thread with one intra-op thread
(:func:`.lm.fit_threads`; the measurement is in docs/benches.md).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

import numpy as np
import torch

T = TypeVar("T")
R = TypeVar("R")

_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_LOCK = threading.Lock()


def _forget_pool() -> None:
    """In a forked child the pool's threads do not exist: start a new pool when asked."""
    global _POOL, _POOL_SIZE
    _POOL, _POOL_SIZE = None, 0


os.register_at_fork(after_in_child=_forget_pool)


def _pool(workers: int) -> ThreadPoolExecutor:
    """One process-wide pool, kept between calls, grown when more workers are asked for."""
    global _POOL, _POOL_SIZE
    with _LOCK:
        if _POOL is None or workers > _POOL_SIZE:
            if _POOL is not None:
                _POOL.shutdown(wait=True)
            _POOL, _POOL_SIZE = ThreadPoolExecutor(workers, "bopsurg-refine"), workers
        return _POOL


def split(rows: np.ndarray, parts: int) -> list[np.ndarray]:
    """``rows`` in at most ``parts`` consecutive, non-empty groups whose sizes differ by at
    most one (the first ones the larger); one group, possibly empty, for no rows."""
    rows = np.asarray(rows)
    return np.array_split(rows, max(1, min(parts, len(rows))))


def run(fn: Callable[[T], R], groups: Sequence[T]) -> list[R]:
    """``fn`` of each group, side by side on the pool's threads (the last one on the calling
    thread), in the groups' order; an exception of any is raised."""
    if len(groups) <= 1:
        return [fn(g) for g in groups]

    def alone(group: T) -> R:
        if torch.get_num_threads() != 1:  # a pool thread keeps the count it first saw
            torch.set_num_threads(1)
        return fn(group)

    futures = [_pool(len(groups) - 1).submit(alone, g) for g in groups[:-1]]
    last = fn(groups[-1])
    return [f.result() for f in futures] + [last]


@contextmanager
def cpu_workers(device: torch.device) -> Iterator[int]:
    """How many groups to run side by side on ``device`` (the torch threads at entry on a
    CPU, else 1), with one intra-op thread per op meanwhile; restores the thread count."""
    if device.type != "cpu":
        yield 1
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield before
    finally:
        torch.set_num_threads(before)
