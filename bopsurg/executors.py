"""Where units of work run: worker processes on this machine, or a Ray cluster.

A *unit* is a picklable description of independent work (a replay for ``generate``, a group
of scenes for ``eval``); ``fn(unit, report)`` does it and returns a picklable result, calling
``report(n)`` to count progress (frames, images). Units must be idempotent and write only
their own files, so a unit retried after a crashed worker finishes the same way.

- :class:`LocalExecutor` (the default): ``spawn``-ed worker processes; one worker runs in
  this process.
- :class:`RayExecutor`: Ray tasks with automatic retries (``max_retries``), progress through
  a cluster-wide queue. Connects to ``address`` or starts a local Ray instance. Datasets must
  live on a path that every node sees (shared storage); results come back in input order, so
  outputs are byte-identical to the local executor's.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import queue as queue_mod
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from bopsurg.errors import BopsurgError

log = logging.getLogger(__name__)

Report = Callable[[int], None]
UnitFn = Callable[[Any, Report], Any]


class Executor(Protocol):
    """Runs ``fn`` over units, in any order, and returns the results in input order."""

    def map(self, fn: UnitFn, units: Sequence[Any], on_progress: Report | None = None) -> list[Any]:
        """Run every unit; ``on_progress(n)`` is called in this process as work is reported."""
        ...


def _noop(_n: int) -> None:
    pass


# -- local worker processes ---------------------------------------------------------------
_LOCAL_QUEUE: Any = None


def _local_init(progress_queue: Any) -> None:
    global _LOCAL_QUEUE
    _LOCAL_QUEUE = progress_queue


def _local_call(job: tuple[UnitFn, Any]) -> Any:
    fn, unit = job
    return fn(unit, _LOCAL_QUEUE.put)


class LocalExecutor:
    """Worker processes on this machine (``spawn``: no inherited renderer state).

    Args:
        workers: Processes; 1 runs the units in this process.
    """

    def __init__(self, workers: int = 1) -> None:
        if workers < 1:
            raise BopsurgError("workers must be >= 1")
        self.workers = workers

    def map(self, fn: UnitFn, units: Sequence[Any], on_progress: Report | None = None) -> list[Any]:
        """See :class:`Executor`."""
        report = on_progress or _noop
        if self.workers == 1 or len(units) <= 1:
            return [fn(unit, report) for unit in units]
        ctx = mp.get_context("spawn")
        progress_queue = ctx.Queue()
        with ctx.Pool(self.workers, initializer=_local_init, initargs=(progress_queue,)) as pool:
            pending = pool.map_async(_local_call, [(fn, u) for u in units], chunksize=1)
            while True:
                try:
                    report(progress_queue.get(timeout=0.2))
                except queue_mod.Empty:
                    if pending.ready():
                        break
            results = pending.get()  # re-raises a worker's error here
            while not progress_queue.empty():
                report(progress_queue.get_nowait())
        return results


# -- Ray ------------------------------------------------------------------------------------
class RayExecutor:
    """Ray tasks, retried when a worker dies (see the module docstring).

    Args:
        address: Address of a running cluster (``host:port``); None starts a local Ray.
        max_retries: Retries of a unit whose worker died.
        num_cpus: CPUs per unit.
    """

    def __init__(self, address: str | None = None, *, max_retries: int = 3, num_cpus: float = 1):
        try:
            import ray  # noqa: F401 - optional dependency
        except ImportError:
            raise BopsurgError("--executor ray needs Ray: pip install 'bopsurg[ray]'") from None
        self.address = address
        self.max_retries = max_retries
        self.num_cpus = num_cpus

    def map(self, fn: UnitFn, units: Sequence[Any], on_progress: Report | None = None) -> list[Any]:
        """See :class:`Executor`."""
        import ray
        from ray.util.queue import Queue

        report = on_progress or _noop
        started_here = not ray.is_initialized()
        if started_here:
            ray.init(address=self.address, log_to_driver=False, configure_logging=False)
        try:
            progress = Queue()
            task = ray.remote(max_retries=self.max_retries, num_cpus=self.num_cpus)(_ray_call)
            refs = [task.remote(fn, unit, progress) for unit in units]
            remaining = list(refs)
            while remaining:
                _, remaining = ray.wait(remaining, num_returns=len(remaining), timeout=0.2)
                while not progress.empty():
                    report(progress.get_nowait())
            results = ray.get(refs)  # re-raises a unit's error here
            while not progress.empty():
                report(progress.get_nowait())
            return results
        finally:
            if started_here:
                ray.shutdown()


class _BatchedReport:
    """Counts progress locally and sends it at most every ``interval`` seconds: each send is
    a call to the queue actor, which shares the cores with the work."""

    def __init__(self, progress: Any, interval: float = 0.5) -> None:
        self.progress, self.interval = progress, interval
        self.pending, self.last = 0, time.monotonic()

    def __call__(self, n: int) -> None:
        self.pending += n
        if time.monotonic() - self.last >= self.interval:
            self.flush()

    def flush(self) -> None:
        if self.pending:
            self.progress.put(self.pending)
            self.pending = 0
        self.last = time.monotonic()


def _ray_call(fn: UnitFn, unit: Any, progress: Any) -> Any:
    report = _BatchedReport(progress)
    try:
        return fn(unit, report)
    finally:
        report.flush()


def make_executor(name: str, *, workers: int = 1, ray_address: str | None = None) -> Executor:
    """The executor called ``name`` (``local`` or ``ray``)."""
    if name == "local":
        return LocalExecutor(workers)
    if name == "ray":
        return RayExecutor(ray_address)
    raise BopsurgError(f"unknown executor {name!r}; choose local or ray")
