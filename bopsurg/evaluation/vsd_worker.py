"""A process that computes VSD (:mod:`bopsurg.evaluation.vsd_images`) while the caller does the
rest of the evaluation: rendering holds the GIL, so a thread would not overlap it.

The caller starts the worker as early as it knows that VSD may run (:meth:`VsdWorker.start`;
this module imports no numpy, so ``bopsurg eval`` starts it before loading anything) and
closes it if VSD does not run after all: the worker imports numpy and the renderer plugin
while the caller imports the rest. The caller then submits one
:class:`~bopsurg.evaluation.vsd_images.VsdJob` and collects the errors when it needs them;
with a claims folder (:class:`~bopsurg.evaluation.vsd_images.ImageClaims`) the worker takes
images from the front while the caller, once free, takes them from the back.
Messages are pickled over the worker's own pipes (objects this program made, never a user's
file). A worker that fails in any way raises :class:`VsdWorkerError` on collection, and the
caller computes VSD itself: the errors, and any error message about the data, are then
exactly those of the in-process path.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import logging
import os
import pickle
import signal
import subprocess
import sys
import threading
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from bopsurg.errors import BopsurgError

if TYPE_CHECKING:  # the caller starts a worker before it imports numpy (serve imports them)
    import numpy as np
    from numpy.typing import NDArray

    from bopsurg.evaluation.vsd_images import VsdImage, VsdJob, WindowRenderer

    F64 = NDArray[np.float64]

log = logging.getLogger(__name__)

#: Seconds to wait for a worker to exit after its input is closed.
EXIT_TIMEOUT_S = 5.0

_BOOT = (
    "import json, sys; sys.path[:] = json.loads(sys.argv[1]); "
    "from bopsurg.evaluation.vsd_worker import serve; serve(sys.argv[2], sys.argv[3])"
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

    def __init__(self, proc: subprocess.Popen[bytes], renderer_name: str = "") -> None:
        self._proc = proc
        #: The renderer plugin it renders with.
        self.renderer_name = renderer_name
        self._sender: threading.Thread | None = None
        self._answered = False

    @classmethod
    def start(cls, renderer_name: str, target: str | None = None) -> VsdWorker | None:
        """Start a worker that renders with the renderer plugin ``renderer_name`` (importable
        from ``target``, ``module:attribute``; default: looked up); None when no process can
        be started (the caller then computes VSD itself)."""
        if target is None:
            target = _plugin_target(renderer_name)
        try:
            proc = subprocess.Popen(
                [sys.executable, "-c", _BOOT, json.dumps(sys.path), renderer_name, target],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                # one BLAS thread unless the user chose: the caller works on the other core
                env={"OPENBLAS_NUM_THREADS": "1", **os.environ},
            )
        except OSError as err:
            log.debug("VSD worker not started: %s", err)
            return None
        return cls(proc, renderer_name)

    def submit(self, job: VsdJob, *, progress: bool = False, claims: str | None = None) -> None:
        """Send the job (once) without waiting for the worker to read it (it may still be
        importing); its errors come back from :meth:`result`.

        Args:
            job: The VSD to compute.
            progress: Show a progress bar over the images (on the worker's stderr).
            claims: A folder through which the caller shares the images out
                (:class:`~bopsurg.evaluation.vsd_images.ImageClaims`): the worker takes them
                from the front and computes only those; None: all of them.
        """
        if self._sender is not None:
            raise VsdWorkerError("a VSD worker takes one job")
        data = pickle.dumps((job, progress, claims), protocol=pickle.HIGHEST_PROTOCOL)
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
        """The job's VSD errors (τ × P); with claims, those of the images the worker took
        (the other columns 1).

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
        import numpy as np

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


def _plugin_target(renderer_name: str) -> str:
    """``module:attribute`` of the renderer plugin ``renderer_name``, or "" when none is
    installed under that name: the worker then imports it without reading every installed
    distribution's entry points again."""
    from bopsurg.plugins import available_plugins

    ep = available_plugins("renderer").get(renderer_name)
    return "" if ep is None else f"{ep.module}:{ep.attr}"


def _load_renderer(renderer_name: str, target: str) -> Any:
    """The renderer plugin's object: imported from ``target`` (:func:`_plugin_target`), or
    looked up by name (for its error message) when there is none."""
    if not target:
        from bopsurg.plugins import load_plugin

        return load_plugin("renderer", renderer_name)
    module, _, attr = target.partition(":")
    try:
        obj: Any = importlib.import_module(module)
    except ImportError as err:
        from bopsurg.plugins import install_hint

        hint = install_hint(err.name) if err.name else ""
        raise BopsurgError(
            f"renderer plugin {renderer_name!r} cannot be imported: {err}{hint}"
        ) from err
    for part in attr.split(".") if attr else ():
        obj = getattr(obj, part)
    return obj


def serve(renderer_name: str, target: str = "") -> None:
    """The worker's main: load the renderer (``renderer_name``, importable from ``target``:
    :func:`_plugin_target`), then answer jobs from stdin until it closes.

    Replies go to the original stdout; what libraries print on stdout is discarded, so that
    it cannot corrupt a reply, and so is what the plugin prints on stderr while it loads
    (pybullet's banner, which the caller has printed already).
    """
    from bopsurg.evaluation.vsd_images import window_renderer

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
        render = window_renderer(_load_renderer(renderer_name, target)())
    except Exception as err:  # reported in the reply to the job
        failure = f"{type(err).__name__}: {err}"
    os.dup2(stderr, 2)  # the progress bar, warnings
    os.close(stderr)
    os.close(devnull)
    while True:
        try:
            job, progress, claims = pickle.load(sys.stdin.buffer)
        except EOFError:
            return
        reply = ("error", failure) if render is None else _answer(job, render, progress, claims)
        pickle.dump(reply, replies, protocol=pickle.HIGHEST_PROTOCOL)
        replies.flush()


def _answer(
    job: VsdJob, render: WindowRenderer, progress: bool, claims: str | None
) -> tuple[str, Any]:
    """("ok", errors) or ("error", message) for one job (with ``claims``: of the images the
    worker takes from the front)."""
    from bopsurg.evaluation.vsd_images import ImageClaims, vsd_errors

    try:
        images: Iterable[VsdImage] = job.images
        if claims is not None:
            front = ImageClaims(claims, len(job.images)).from_front()
            images = (job.images[i] for i in front)
        elif progress:
            from tqdm import tqdm

            images = tqdm(job.images, desc="VSD", unit="img")
        return "ok", vsd_errors(job, render, images)
    except Exception as err:
        return "error", f"{type(err).__name__}: {err}"
