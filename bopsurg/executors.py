"""Where units of work run: worker processes on this machine, or a Ray cluster.

A *unit* is a picklable description of independent work (a replay for ``generate``, a group
of scenes for ``eval``); ``fn(unit, report)`` does it and returns a picklable result, calling
``report(n)`` to count progress (frames, images). Units must be idempotent and write only
their own files, so a unit retried after a crashed worker finishes the same way.

- :class:`LocalExecutor` (the default): ``spawn``-ed worker processes; one worker runs in
  this process.
- :class:`RayExecutor`: Ray tasks with automatic retries (``max_retries``), progress through
  a counter actor. Connects to ``address`` or starts a local Ray instance. Datasets must
  live on a path that every node sees (shared storage); results come back in input order, so
  outputs are byte-identical to the local executor's.

Ray authentication: a cluster started with token authentication (Ray's default for new
clusters) needs ``RAY_AUTH_MODE=token`` here and the head's token (``ray get-auth-token``
there prints it) in ``RAY_AUTH_TOKEN`` or in a file named by ``RAY_AUTH_TOKEN_PATH``, as
every node of it does; a cluster without authentication needs ``RAY_AUTH_MODE`` unset or
``disabled``. A mismatch is a one-line error. A local instance (no address) gets a throwaway
token for its lifetime, so it leaves no ``~/.ray/auth_token`` behind to change how later
clusters start.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import multiprocessing as mp
import os
import queue as queue_mod
import secrets
import socket
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import IO, Any, Protocol

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

        report = on_progress or _noop
        started_here = not ray.is_initialized()
        with contextlib.ExitStack() as stack:
            if started_here:
                stack.callback(_refresh_auth_config)  # last: Ray sees the restored variables
                stack.enter_context(_environ(_auth_env(self.address, os.environ)))
                stack.callback(ray.shutdown)  # idempotent; also after a failed connect
            # Ray's C++ core logs the failures below on fd 2 from its own threads; the user
            # gets our one-line error instead, and the core's lines go to the debug log.
            with _stderr_to_log("ray.init and the first actor"):
                try:
                    if started_here:
                        _connect(ray, self.address)
                    counter = _first_actor(ray, self.address)
                except BopsurgError:
                    if started_here:
                        ray.shutdown()  # still captured: the core logs as it stops
                    raise
            return self._run(ray, counter, fn, units, report)

    def _run(
        self, ray: Any, counter: Any, fn: UnitFn, units: Sequence[Any], report: Report
    ) -> list[Any]:
        task = ray.remote(max_retries=self.max_retries, num_cpus=self.num_cpus)(_ray_call)
        refs = [task.remote(fn, unit, counter) for unit in units]
        remaining = list(refs)
        while remaining:
            _, remaining = ray.wait(remaining, num_returns=len(remaining), timeout=0.5)
            report(ray.get(counter.take.remote()))  # one round trip per poll
        results: list[Any] = ray.get(refs)  # re-raises a unit's error here
        report(ray.get(counter.take.remote()))
        return results


#: Ray's authentication variables (see the module docstring).
AUTH_VARS = ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")


def _auth_env(address: str | None, environ: Mapping[str, str]) -> dict[str, str]:
    """Authentication variables to set while using ``address``: for a local instance (None)
    a throwaway token, unless the user set any of :data:`AUTH_VARS`; else none."""
    if address is not None or any(v in environ for v in AUTH_VARS):
        return {}
    return {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}


@contextlib.contextmanager
def _environ(values: Mapping[str, str]) -> Iterator[None]:
    """``os.environ`` updated with ``values`` inside the block, restored after."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, old in saved.items():
            if old is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = old


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail fast, in one line, when nothing listens at ``HOST:PORT`` (Ray itself retries for
    minutes); other address forms (``auto``, ``ray://...``) are left to Ray."""
    if address == "auto" or "://" in address:
        return
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise BopsurgError(f"--ray-address {address!r}: expected HOST:PORT of the Ray head")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as err:
        raise BopsurgError(
            f"cannot reach a Ray cluster at {address} ({err.strerror or err}); is the head "
            "running ('ray start --head --port=PORT') and is the address right?"
        ) from None


def _connect(ray: Any, address: str | None) -> None:
    """``ray.init``, with Ray's long errors turned into one line that says what to fix."""
    if address is not None:
        _check_reachable(address)
    _refresh_auth_config()
    try:
        ray.init(address=address, log_to_driver=False, configure_logging=False)
    except Exception as err:
        raise BopsurgError(_connect_error(err, address)) from None


def _first_actor(ray: Any, address: str | None) -> Any:
    """The progress counter actor, after one round trip to it: a driver that the cluster
    cannot serve (e.g. it authenticates and the cluster does not) fails here, in one line."""
    counter = ray.remote(num_cpus=0)(_ProgressCounter).remote()
    try:
        ray.get(counter.take.remote())
    except ray.exceptions.RayError as err:
        mode = os.environ.get("RAY_AUTH_MODE", "unset")
        raise BopsurgError(
            f"the Ray cluster at {address or 'this machine'} cannot run this driver's "
            f"work ({type(err).__name__}); with RAY_AUTH_MODE={mode} here, check that the "
            "cluster uses the same authentication (RAY_AUTH_MODE=token on every node, or "
            "none anywhere)"
        ) from None
    return counter


@contextlib.contextmanager
def _stderr_to_log(what: str) -> Iterator[None]:
    """File descriptor 2 captured inside the block and written to the debug log after it."""
    with tempfile.TemporaryFile() as captured:
        try:
            with _stderr_to(captured):
                yield
        finally:
            captured.seek(0)
            text = captured.read().decode(errors="replace").strip()
            if text:
                log.debug("%s: %s", what, text)


def _refresh_auth_config() -> None:
    """Make Ray read the authentication variables again: it caches them when ``ray`` is
    first imported, and they may have changed since (see :func:`_auth_env`)."""
    raylet = importlib.import_module("ray._raylet")
    config = getattr(raylet, "Config", None)
    loader = getattr(raylet, "AuthenticationTokenLoader", None)
    if config is None or loader is None:  # a Ray without token authentication
        return
    config.initialize("")
    loader.instance().reset_cache()


@contextlib.contextmanager
def _stderr_to(file: IO[bytes]) -> Iterator[None]:
    """File descriptor 2 (C/C++ code writes there too, not only ``sys.stderr``) sent to
    ``file`` inside the block."""
    sys.stderr.flush()
    saved = os.dup(2)
    os.dup2(file.fileno(), 2)
    try:
        yield
    finally:
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)


def _connect_error(err: BaseException, address: str | None) -> str:
    where = f"the Ray cluster at {address}" if address else "a local Ray instance"
    chain: list[BaseException] = []
    e: BaseException | None = err
    while e is not None and e not in chain:
        chain.append(e)
        e = e.__cause__ or e.__context__
    text = " ".join(str(c) for c in chain)
    auth_words = ("AuthenticationError", "InvalidAuthToken", "Unauthenticated")
    if any(type(c).__name__ == "AuthenticationError" for c in chain) or any(
        w in text for w in auth_words
    ):
        head_token = "the head's token ('ray get-auth-token' there)"
        if os.environ.get("RAY_AUTH_MODE", "").lower() != "token":
            return (
                f"{where} uses token authentication: set RAY_AUTH_MODE=token and "
                f"RAY_AUTH_TOKEN to {head_token} (or RAY_AUTH_TOKEN_PATH to a file holding it)"
            )
        if "no authentication token" in text:
            return (
                "RAY_AUTH_MODE=token but no token is given: set RAY_AUTH_TOKEN to "
                f"{head_token} or RAY_AUTH_TOKEN_PATH to a file holding it"
            )
        return (
            f"{where} rejected the authentication token (RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH "
            f"or ~/.ray/auth_token); use {head_token}"
        )
    if "version mismatch" in text.lower():
        mismatch = next(c for c in chain if "version mismatch" in str(c).lower())
        detail = " ".join(str(mismatch).split())
        return f"{where} runs another Ray or Python version: {detail[:300]}"
    first = " ".join(str(err).split()) or type(err).__name__
    return f"cannot connect to {where}: {first[:300]}"


class _ProgressCounter:
    """The Ray actor that sums the progress the units report; the driver takes it."""

    def __init__(self) -> None:
        self.count = 0

    def add(self, n: int) -> None:
        self.count += n

    def take(self) -> int:
        n, self.count = self.count, 0
        return n


class _BatchedReport:
    """Counts progress locally and sends it at most every ``interval`` seconds, without
    waiting for the actor (the send must not slow the unit down)."""

    def __init__(self, counter: Any, interval: float = 0.5) -> None:
        self.counter, self.interval = counter, interval
        self.pending, self.last = 0, time.monotonic()

    def __call__(self, n: int) -> None:
        self.pending += n
        if time.monotonic() - self.last >= self.interval:
            self.flush()

    def flush(self, *, wait: bool = False) -> None:
        """Send the pending count; ``wait``: until the actor has it (the unit's last send,
        so the driver's final take sees every frame)."""
        if self.pending:
            ref = self.counter.add.remote(self.pending)
            if wait:
                import ray

                ray.get(ref)
            self.pending = 0
        self.last = time.monotonic()


def _ray_call(fn: UnitFn, unit: Any, counter: Any) -> Any:
    report = _BatchedReport(counter)
    try:
        return fn(unit, report)
    finally:
        report.flush(wait=True)


def make_executor(name: str, *, workers: int = 1, ray_address: str | None = None) -> Executor:
    """The executor called ``name`` (``local`` or ``ray``)."""
    if name == "local":
        return LocalExecutor(workers)
    if name == "ray":
        return RayExecutor(ray_address)
    raise BopsurgError(f"unknown executor {name!r}; choose local or ray")
