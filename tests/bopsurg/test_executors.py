"""The Ray executor's connection checks and error lines, without a cluster (the cluster
tests in tests/test_ray_cluster.py need root; these run everywhere)."""

from __future__ import annotations

import os
import socket

import pytest

from bopsurg.errors import BopsurgError
from bopsurg.executors import (
    AUTH_VARS,
    LocalExecutor,
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
