"""A process that computes VSD (:mod:`bopsurg.evaluation.vsd_images`) while the caller does the
rest of the evaluation: rendering holds the GIL, so a thread would not overlap it.

The caller starts the worker as early as it knows that VSD will run
(:meth:`VsdWorker.start`): the worker imports numpy and the renderer plugin while the caller
imports the rest. The caller then submits one :class:`~bopsurg.evaluation.vsd_images.VsdJob`
and collects the errors when it needs them. Messages are pickled over the worker's own pipes
(objects this program made, never a user's file). A worker that fails in any way raises
:class:`VsdWorkerError` on collection, and the caller computes VSD itself: the errors, and
any error message about the data, are then exactly those of the in-process path.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import pickle
import signal
import subprocess
import sys
import threading
from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bopsurg.errors import BopsurgError
from bopsurg.evaluation.vsd_images import (
    VsdImage,
    VsdJob,
    WindowRenderer,
    vsd_errors,
    window_renderer,
)

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Seconds to wait for a worker to exit after its input is closed.
EXIT_TIMEOUT_S = 5.0

_BOOT = (
    "import json, sys; sys.path[:] = json.loads(sys.argv[1]); "
    "from bopsurg.evaluation.vsd_worker import serve; serve(sys.argv[2])"
)


class VsdWorkerError(BopsurgError):
    """The worker process failed (the caller computes VSD itself)."""


class VsdWorker:
    """A worker process for one VSD job (see the module docstring).

    Usage::

        worker = VsdWorker.start("pybullet")  # None if it cannot start
        worker.submit(job)
        ...                                   # the rest of the evaluation
        errors = worker.result()              # (τ, P), or VsdWorkerError
        worker.close()
    """

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self._proc = proc
        self._sender: threading.Thread | None = None
        self._answered = False

    @classmethod
    def start(cls, renderer_name: str) -> VsdWorker | None:
        """Start a worker that renders with the renderer plugin ``renderer_name``; None when
        no process can be started (the caller then computes VSD itself)."""
        try:
            proc = subprocess.Popen(
                [sys.executable, "-c", _BOOT, json.dumps(sys.path), renderer_name],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
            )
        except OSError as err:
            log.debug("VSD worker not started: %s", err)
            return None
        return cls(proc)

    def submit(self, job: VsdJob, *, progress: bool = False) -> None:
        """Send the job (once) without waiting for the worker to read it (it may still be
        importing); its errors come back from :meth:`result`."""
        if self._sender is not None:
            raise VsdWorkerError("a VSD worker takes one job")
        data = pickle.dumps((job, progress), protocol=pickle.HIGHEST_PROTOCOL)
        self._sender = threading.Thread(target=self._send, args=(data,), daemon=True)
        self._sender.start()

    def _send(self, data: bytes) -> None:
        stdin = self._proc.stdin
        assert stdin is not None
        try:  # (pipe writes release the GIL)
            stdin.write(data)
            stdin.flush()
        except (OSError, ValueError) as err:  # the worker died or was closed: result() says so
            log.debug("VSD job not sent: %s", err)

    def result(self) -> F64:
        """The job's VSD errors (τ × P).

        Raises:
            VsdWorkerError: No job was submitted, or the worker failed or died.
        """
        if self._sender is None:
            raise VsdWorkerError("no VSD job was submitted")
        self._sender.join()
        assert self._proc.stdout is not None
        try:
            status, value = pickle.load(self._proc.stdout)
            self._answered = True
        except (EOFError, OSError, pickle.UnpicklingError) as err:
            self.close()
            raise VsdWorkerError(f"the VSD worker died ({err or type(err).__name__})") from err
        for stream in (self._proc.stdin, self._proc.stdout):
            if stream is not None:
                with contextlib.suppress(OSError):
                    stream.close()  # the worker exits; reaped without keeping the caller
        threading.Thread(target=self._proc.wait, daemon=True).start()
        if status != "ok":
            raise VsdWorkerError(f"the VSD worker failed: {value}")
        errors: F64 = np.asarray(value, dtype=np.float64)
        return errors

    def close(self) -> None:
        """End the worker (idempotent): after its reply it exits on its own once its input is
        closed; before (an error elsewhere, no job) it is killed."""
        proc = self._proc
        if not self._answered and proc.poll() is None:
            proc.kill()
        for stream in (proc.stdin, proc.stdout):
            if stream is not None and not stream.closed:
                with contextlib.suppress(OSError):
                    stream.close()
        try:
            proc.wait(timeout=EXIT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if self._sender is not None:
            self._sender.join()

    def __del__(self) -> None:
        if self._proc.poll() is None:
            self._proc.kill()


def serve(renderer_name: str) -> None:
    """The worker's main: load the renderer, then answer jobs from stdin until it closes.

    Replies go to the original stdout; what libraries print on stdout is discarded, so that
    it cannot corrupt a reply, and so is what the plugin prints on stderr while it loads
    (pybullet's banner, which the caller has printed already).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the caller's: it ends this
    replies = os.fdopen(os.dup(1), "wb")
    stderr = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    sys.stdout = sys.stderr
    render: WindowRenderer | None = None
    failure = ""
    try:
        from bopsurg.plugins import load_plugin

        render = window_renderer(load_plugin("renderer", renderer_name)())
    except Exception as err:  # reported in the reply to the job
        failure = f"{type(err).__name__}: {err}"
    os.dup2(stderr, 2)  # the progress bar, warnings
    os.close(stderr)
    os.close(devnull)
    while True:
        try:
            job, progress = pickle.load(sys.stdin.buffer)
        except EOFError:
            return
        reply = ("error", failure) if render is None else _answer(job, render, progress)
        pickle.dump(reply, replies, protocol=pickle.HIGHEST_PROTOCOL)
        replies.flush()


def _answer(job: VsdJob, render: WindowRenderer, progress: bool) -> tuple[str, Any]:
    """("ok", errors) or ("error", message) for one job."""
    try:
        images: Iterable[VsdImage] = job.images
        if progress:
            from tqdm import tqdm

            images = tqdm(job.images, desc="VSD", unit="img")
        return "ok", vsd_errors(job, render, images)
    except Exception as err:
        return "error", f"{type(err).__name__}: {err}"
