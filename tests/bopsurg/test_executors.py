"""The Ray executor's connection checks and error lines, without a cluster (the cluster
tests in tests/test_ray_cluster.py need root; these run everywhere)."""

from __future__ import annotations

import logging
import os
import socket
import sys
import types

import pytest

from bopsurg.errors import BopsurgError
from bopsurg.executors import (
    AUTH_VARS,
    LocalExecutor,
    RayExecutor,
    _auth_env,
    _check_reachable,
    _connect_error,
    _environ,
    make_executor,
)


def test_local_instance_gets_a_throwaway_token_unless_the_user_chose():
    a, b = _auth_env(None, {}), _auth_env(None, {})
    assert a["RAY_AUTH_MODE"] == "token"
    assert len(a["RAY_AUTH_TOKEN"]) == 64
    assert a["RAY_AUTH_TOKEN"] != b["RAY_AUTH_TOKEN"]
    for var in AUTH_VARS:  # any explicit setting of the user wins
        assert _auth_env(None, {var: "x"}) == {}
    assert _auth_env("127.0.0.1:6379", {}) == {}  # a cluster: the user's setting, as it is


def test_environ_is_restored(monkeypatch):
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    monkeypatch.delenv("RAY_AUTH_TOKEN", raising=False)
    with _environ({"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": "t"}):
        assert os.environ["RAY_AUTH_MODE"] == "token"
        assert os.environ["RAY_AUTH_TOKEN"] == "t"
    assert os.environ["RAY_AUTH_MODE"] == "disabled"
    assert "RAY_AUTH_TOKEN" not in os.environ


def test_unreachable_or_malformed_address_is_one_line():
    with socket.socket() as s:  # a port nothing listens on: bound, never listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        with pytest.raises(BopsurgError, match=f"cannot reach a Ray cluster at 127.0.0.1:{port}"):
            _check_reachable(f"127.0.0.1:{port}", timeout_s=2)
    for bad in ("nohost", ":6379", "host:port"):
        with pytest.raises(BopsurgError, match="expected HOST:PORT"):
            _check_reachable(bad)
    _check_reachable("auto")  # forms Ray resolves itself pass through
    _check_reachable("ray://head:10001")


class AuthenticationError(Exception):
    """Stands for ray.exceptions.AuthenticationError (matched by name)."""


def _chained(inner: Exception) -> Exception:
    outer = ConnectionError("Failed to connect to Ray cluster at 127.0.0.1:6379")
    outer.__cause__ = inner
    return outer


@pytest.mark.parametrize(
    ("env", "inner", "expected"),
    [
        ({}, AuthenticationError("InvalidAuthToken"), "set RAY_AUTH_MODE=token and RAY_AUTH_TOKEN"),
        (
            {"RAY_AUTH_MODE": "token"},
            AuthenticationError("Token authentication is enabled but no authentication token"),
            "no token is given",
        ),
        (
            {"RAY_AUTH_MODE": "token"},
            AuthenticationError("RPC error: InvalidAuthToken: missing or incorrect"),
            "rejected the authentication token",
        ),
        (
            {},
            RuntimeError("Version mismatch: The cluster was started with Ray 2.9, Python 3.10"),
            "runs another Ray or Python version: Version mismatch",
        ),
        ({}, RuntimeError("something else"), "cannot connect to the Ray cluster at"),
    ],
)
def test_connect_errors_say_what_to_fix(monkeypatch, env, inner, expected):
    for var in AUTH_VARS:
        monkeypatch.delenv(var, raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    line = _connect_error(_chained(inner), "127.0.0.1:6379")
    assert expected in line
    assert "\n" not in line


def test_make_executor():
    assert isinstance(make_executor("local", workers=2), LocalExecutor)
    with pytest.raises(BopsurgError, match="unknown executor 'dask'"):
        make_executor("dask")


class _FakeRayError(Exception):
    pass


def _fake_ray(calls: list[str], fail_init: bool = False) -> types.ModuleType:
    """Just enough of ``ray`` for a driver that cannot connect (``fail_init``) or whose first
    actor the cluster cannot serve; its 'C++ core' writes to file descriptor 2, as Ray's does
    from its own threads."""
    ray = types.ModuleType("ray")

    def core_log(line: str) -> None:
        os.write(2, f"core_worker.cc:2488: {line}\n".encode())

    class Actor:
        class take:  # mirrors ray's actor.method.remote()
            @staticmethod
            def remote() -> str:
                return "ref"

    def remote(**_options):
        return lambda cls: types.SimpleNamespace(remote=lambda: Actor())

    def get(_ref):
        core_log("Failed to register actor")
        raise _FakeRayError("actor died")

    def init(**_kwargs):
        core_log("connecting")
        if fail_init:
            raise ConnectionError("Failed to connect to the cluster")
        calls.append("init")

    def is_initialized() -> bool:
        return "init" in calls and "shutdown" not in calls

    def shutdown():  # a no-op when not connected, as Ray's
        if is_initialized():
            calls.append("shutdown")
            core_log("stopping")

    ray.is_initialized = is_initialized
    ray.init, ray.shutdown, ray.remote, ray.get = init, shutdown, remote, get
    ray.exceptions = types.SimpleNamespace(RayError=_FakeRayError)
    return ray


@pytest.mark.parametrize("fail_init", [False, True], ids=["first actor", "ray.init"])
def test_a_driver_the_cluster_cannot_serve_gets_one_line_and_nothing_else(
    monkeypatch, capfd, caplog, fail_init
):
    calls: list[str] = []
    monkeypatch.setitem(sys.modules, "ray", _fake_ray(calls, fail_init))
    monkeypatch.setitem(sys.modules, "ray._raylet", types.ModuleType("ray._raylet"))
    for var in AUTH_VARS:
        monkeypatch.delenv(var, raising=False)
    expected = "cannot connect to a local Ray" if fail_init else "cannot run this driver's work"
    # only this test's log capture on the root logger: a CLI test run before it in this worker
    # may have left the CLI's stderr handler there, which would print the debug log to the
    # stderr this test checks
    monkeypatch.setattr(logging.getLogger(), "handlers", [caplog.handler])
    with (
        caplog.at_level(logging.DEBUG, logger="bopsurg.executors"),
        pytest.raises(BopsurgError, match=expected) as err,
    ):
        RayExecutor(None).map(lambda unit, report: unit, [1])
    assert "\n" not in str(err.value)
    assert capfd.readouterr().err == ""  # the core's lines went to the debug log instead
    assert "connecting" in caplog.text
    if not fail_init:
        assert "Failed to register actor" in caplog.text
        assert "stopping" in caplog.text  # shut down while still captured
        assert calls == ["init", "shutdown"]
